// turnfit-track: where each turn crosses each probe, for one particle through a machine.
#include "turnfit/track/track_app.hpp"

#include <cmath>
#include <iostream>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/machine/machine.hpp"

namespace turnfit {

void add_track_options(CLI::App& app, TrackOptions& o) {
  app.description(
      "Tracks a particle through a cyclotron machine file (field map, trim coils, RF gaps) and\n"
      "records where each turn crosses each probe: one CSV row per crossing.");
  app.add_option("machine", o.machine, "Machine file ('-' for stdin)");
  app.add_option("--set", o.sets, "Set a design variable or JSON pointer: NAME=VALUE (repeatable)")
      ->allow_extra_args(false);
  app.add_option("--dvars", o.dvars, "JSON file of design-variable values");
  app.add_option("--integrator", o.integrator, "Integrator (see --list-integrators)")
      ->check(CLI::IsMember({"azimuth", "rk4"}));
  app.add_option("--steps-per-turn", o.steps_per_turn, "rk4: time steps per turn (default 2880)")
      ->check(CLI::Range(16, 10000000));
  app.add_option("--step-deg", o.step_deg,
                 "azimuth: largest step in degrees, rounded to whole map cells (default 1)")
      ->check(CLI::Range(1e-4, 45.0));
  app.add_option("--turns", o.turns, "Revolutions to track (default: the machine's tracking.turns)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_flag("--list-integrators", o.list_integrators, "List the integrators and exit");
  app.add_option("--kicks", o.kicks, "Also write every gap crossing (CSV) to this file");
  app.add_flag("--opal-deflection", o.opal_deflection,
               "RF magnetic deflection as OPAL 2022.1 computes it (2 pi smaller than Faraday's law)");
  cli::add_common_options(app, o.common, cli::kOutput);
}

void write_turns_csv(std::ostream& os, const TrackModel& model, const std::vector<TurnRecord>& turns,
                     const std::vector<TrackEnd>& ends, bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg\n";
  char buf[256];
  for (const auto& t : turns) {
    std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6f,%.6f,%.8f,", model.probes[t.probe].name.c_str(), t.turn, t.r_mm,
                  t.s_mm, t.t_ns, t.energy_MeV);
    os << buf;
    if (std::isfinite(t.phase_deg)) {  // empty without RF
      std::snprintf(buf, sizeof buf, "%.5f", t.phase_deg);
      os << buf;
    }
    os << '\n';
  }
  for (size_t i = 0; i < ends.size(); ++i) {
    std::snprintf(buf, sizeof buf, "# end particle=%zu turns=%.4f energy_MeV=%.6f r_mm=%.4f t_ns=%.3f status=", i,
                  ends[i].turns, ends[i].energy_MeV, ends[i].r_mm, ends[i].t_ns);
    os << buf << ends[i].status << "\n";
  }
}

int run_track(const TrackOptions& o) {
  if (o.list_integrators) {
    for (const auto& [name, what] : list_integrators()) std::cout << name << "\t" << what << "\n";
    return 0;
  }
  if (o.machine.empty()) throw usage_error("give a machine file ('-' for stdin)");
  if (o.machine == "-" && o.dvars == "-") throw usage_error("only one input can be stdin");
  Machine m = load_machine(o.machine);
  apply_sets(m, o.sets);
  if (!o.dvars.empty()) apply_dvars_file(m, o.dvars);
  if (!m.injection) throw data_error(m.path, 0, "/injection: the machine has no injection block to track from");
  {
    const double g = 1 + m.injection->energy_MeV / m.particle.mass_MeV, P = std::sqrt(g * g - 1);
    const double pr = m.injection->pr_betagamma, pz = m.injection->pz_betagamma;
    if (pr * pr + pz * pz >= P * P)
      throw data_error(m.path, 0, "/injection: pr_betagamma and pz_betagamma exceed the total momentum " +
                                      cli::fmt(P, 6) + " of " + cli::fmt(m.injection->energy_MeV) + " MeV");
  }
  if (m.probes.empty()) cli::warn(o.common, "the machine has no probes: turns.csv will have no rows");
  TrackModel model = make_track_model(m);
  TrackSettings st;
  st.integrator = !o.integrator.empty() ? o.integrator : !m.tracking.integrator.empty() ? m.tracking.integrator : "azimuth";
  if (st.integrator != "azimuth" && st.integrator != "rk4")
    throw data_error(m.path, 0, "/tracking/integrator: unknown integrator '" + st.integrator + "'");
  st.steps_per_turn = o.steps_per_turn > 0 ? o.steps_per_turn : m.tracking.steps_per_turn > 0 ? m.tracking.steps_per_turn : 2880;
  if (st.steps_per_turn < 16)
    throw data_error(m.path, 0, "/tracking/steps_per_turn: " + std::to_string(st.steps_per_turn) + " is too few (at least 16)");
  if (!o.kicks.empty() && (o.kicks == "-") && (o.common.output == "-" || o.common.output.empty()))
    throw usage_error("--kicks - and the turns table cannot both go to stdout (use -o)");
  st.step_deg = o.step_deg > 0 ? o.step_deg : m.tracking.step_deg;
  st.turns = o.turns > 0 ? o.turns : m.tracking.turns > 0 ? m.tracking.turns : 0;
  if (!(st.turns > 0)) throw usage_error("no turn count: give --turns or tracking.turns in the machine");
  if (st.integrator == "rk4" && !(model.rf_MHz > 0))
    throw usage_error("the rk4 integrator needs an RF frequency (rf.frequency_MHz) for its time step");
  st.gap_physics = o.opal_deflection ? GapPhysics::opal : GapPhysics::turnfit;

  std::vector<TurnRecord> turns;
  std::vector<KickRecord> kicks;
  TrackEnd end = track_particle(model, injection_state(*m.injection, m.particle.mass_MeV), st, turns,
                                o.kicks.empty() ? nullptr : &kicks);
  // Open both outputs before committing either, so a failing one leaves neither behind.
  OutputFile out(o.common.output);
  std::unique_ptr<OutputFile> kout;
  if (!o.kicks.empty()) {
    kout = std::make_unique<OutputFile>(o.kicks);
    if (!o.common.no_provenance) kout->stream() << cli::provenance_comment();
    kout->stream() << "gap,turn,theta_deg,rho_n,phase_deg,transit,de_MeV,deflection_urad\n";
    char buf[256];
    for (const auto& k : kicks) {
      std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6f,%.5f,%.6f,%.8f,%.5f\n", model.gaps[k.gap].name().c_str(), k.turn,
                    k.theta_deg, k.kick.rho_n, k.kick.phase_deg, k.kick.transit, k.kick.de_MeV,
                    k.kick.deflection_rad * 1e6);
      kout->stream() << buf;
    }
  }
  write_turns_csv(out.stream(), model, turns, {end}, !o.common.no_provenance);
  out.commit();
  if (kout) kout->commit();
  if (end.lost) cli::warn(o.common, end.status);
  return 0;
}

}  // namespace turnfit
