// turnfit-track: where each turn crosses each probe, for one particle through a machine.
#include "turnfit/track/track_app.hpp"

#include <atomic>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/spacecharge/space_charge.hpp"

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
  app.add_flag("--reference-stepper", o.reference_stepper,
               "azimuth: track one particle at a time with the reference stepper (several times slower for "
               "bunches; the same results to 1e-6 mm: for checks and benchmarks)");
  app.add_flag("--opal-deflection", o.opal_deflection,
               "RF magnetic deflection as OPAL 2022.1 computes it (2 pi smaller than Faraday's law)");
  app.add_flag("--opal-compat", o.opal_compat,
               "OPAL-cycl 2022.1's numerics: rk4 in time, bilinear map with 5-point derivatives, its gap\n"
               "crossing estimate, kick and single-precision start (to check against an OPAL run)");
  app.add_option("--particles", o.particles, "Track a bunch of N particles (default: the machine's bunch.particles)")
      ->check(CLI::Range(0, 100000000));
  app.add_option("--bunch", o.bunch, "Bunch from a CSV of offsets (dr_mm,dpr_mrad,dz_mm,dpz_mrad,dE_MeV,dphase_deg)");
  app.add_flag("--centroid", o.centroid,
               "Write the bunch's centre at each crossing (a 13-particle quadrature of the machine's bunch or "
               "--bunch FILE), as a turn-pattern problem predicts what a probe measures");
  app.add_option("--histograms", o.histograms, "Write a probe profile per probe (DIR/<probe>.csv) of the bunch");
  app.add_option("--orbit", o.orbit, "Write the particle's path after every step (CSV; the reference particle of a bunch)");
  app.add_flag("--space-charge", o.space_charge,
               "The bunch's own field (particle-in-cell, turnfit-track(1)), with the machine's space_charge block or "
               "--current-uA");
  app.add_flag("--no-space-charge", o.no_space_charge, "No space charge, even if the machine has a space_charge block");
  app.add_option("--current-uA", o.current_uA, "Beam current for --space-charge [uA] (bunch charge: current / f_rf)");
  app.add_option("--sc-grid", o.sc_grid, "Space-charge grid points, radial x vertical x longitudinal (default 32x32x32)");
  app.add_option("--sc-every", o.sc_every, "One space-charge solve every K integration steps (default 1)")
      ->check(CLI::Range(1, 100000));
  app.add_flag("--sc-timing", o.sc_timing, "Print where the space-charge time went (deposit, FFT, gather) on stderr");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kThreads | cli::kSeed);
}

namespace {
/// The seven turns.csv columns (architecture.md) of one crossing, or of a bunch's centroid;
/// the phase is empty without RF. No line end: a bunch row goes on.
void write_crossing(std::ostream& os, const std::string& probe, int turn, double r_mm, double s_mm, double t_ns,
                    double energy_MeV, double phase_deg) {
  char buf[256];
  std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6f,%.6f,%.8f,", probe.c_str(), turn, r_mm, s_mm, t_ns, energy_MeV);
  os << buf;
  if (std::isfinite(phase_deg)) {
    std::snprintf(buf, sizeof buf, "%.5f", phase_deg);
    os << buf;
  }
}

/// The '# end' line of a particle: how its track ended.
void write_end(std::ostream& os, size_t particle, const TrackEnd& e) {
  char buf[200];
  std::snprintf(buf, sizeof buf, "# end particle=%zu turns=%.4f energy_MeV=%.6f r_mm=%.4f t_ns=%.3f status=", particle,
                e.turns, e.energy_MeV, e.r_mm, e.t_ns);
  os << buf << e.status << "\n";
}
}  // namespace

void write_bunch_csv(std::ostream& os, const TrackModel& model, const BunchResult& res, bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg,particles,r_rms_mm\n";
  char buf[200];
  for (const auto& c : res.centroids) {
    write_crossing(os, model.probes[c.probe].name, c.turn, c.r_mm, c.s_mm, c.t_ns, c.energy_MeV, c.phase_deg);
    std::snprintf(buf, sizeof buf, ",%llu,%.6f\n", static_cast<unsigned long long>(c.particles), c.r_rms_mm);
    os << buf;
  }
  for (const auto& [i, e] : res.lost) write_end(os, i, e);
  std::snprintf(buf, sizeof buf, "# bunch particles=%zu lost=%zu particle_turns=%.4f\n", res.particles,
                res.lost.size(), res.particle_turns);
  os << buf;
}

void write_profile_csv(std::ostream& os, const ProbeLine& probe, const ProbeHistogram& h, size_t particles,
                       bool provenance) {
  if (provenance) os << cli::provenance_comment();
  char buf[256];
  std::snprintf(buf, sizeof buf, "# probe=%s step_mm=%.6g particles=%zu outside=%llu\n", probe.name.c_str(),
                h.step_mm, particles, static_cast<unsigned long long>(h.outside));
  os << buf << "position_mm,intensity\n";
  for (size_t k = 0; k < h.counts.size(); ++k) {
    std::snprintf(buf, sizeof buf, "%.6f,%llu\n", h.lo_mm + (static_cast<double>(k) + 0.5) * h.step_mm,
                  static_cast<unsigned long long>(h.counts[k]));
    os << buf;
  }
}

void write_turns_csv(std::ostream& os, const TrackModel& model, const std::vector<TurnRecord>& turns,
                     const std::vector<TrackEnd>& ends, bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg\n";
  for (const auto& t : turns) {
    write_crossing(os, model.probes[t.probe].name, t.turn, t.r_mm, t.s_mm, t.t_ns, t.energy_MeV, t.phase_deg);
    os << '\n';
  }
  for (size_t i = 0; i < ends.size(); ++i) write_end(os, i, ends[i]);
}

/// Warns about probes that lie wholly outside the field map's radii: they can never record a
/// turn (not an error: a design variable may have moved the probe there on purpose).
void warn_probes_outside(const cli::CommonOptions& common, const TrackModel& model) {
  const double lo = model.map.grid().r_min_m(), hi = model.map.grid().r_max_m();
  for (const auto& p : model.probes) {
    // Radii along the probe: sqrt(s^2 + a^2) for s in [s_min, s_max] (moved by the shift).
    const double s0 = p.s_min_m + p.shift_m, s1 = p.s_max_m + p.shift_m;
    const double smin = (s0 <= 0 && s1 >= 0) ? 0 : std::min(std::fabs(s0), std::fabs(s1));
    const double rmin = std::hypot(smin, p.a_m), rmax = std::hypot(std::max(std::fabs(s0), std::fabs(s1)), p.a_m);
    if (rmax < lo || rmin > hi)
      cli::warn(common, "probe '" + p.name + "' (r = " + cli::fmt(rmin * 1e3, 6) + " to " + cli::fmt(rmax * 1e3, 6) +
                            " mm) lies outside the field map (r = " + cli::fmt(lo * 1e3, 6) + " to " +
                            cli::fmt(hi * 1e3, 6) + " mm): it records no turns");
  }
}

/// The path as CSV: one row per integration step.
void write_path_csv(std::ostream& os, const std::vector<PathPoint>& path, bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "theta_deg,r_mm,z_mm,pr_mrad,t_ns,energy_MeV\n";
  char buf[200];
  for (const auto& p : path) {
    std::snprintf(buf, sizeof buf, "%.6f,%.6f,%.6f,%.6f,%.6f,%.8f\n", p.theta_deg, p.r_mm, p.z_mm, p.pr_mrad, p.t_ns,
                  p.energy_MeV);
    os << buf;
  }
}

int run_track(const TrackOptions& o) {
  if (o.list_integrators) {
    for (const auto& [name, what] : list_integrators()) std::cout << name << "\t" << what << "\n";
    return 0;
  }
  if (o.machine.empty()) throw usage_error("give a machine file ('-' for stdin)");
  if ((o.machine == "-") + (o.dvars == "-") + (o.bunch == "-") > 1)
    throw usage_error("only one input can be stdin (machine, --dvars, --bunch)");
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
  // The beam starts where the machine's injection-offset effect puts it (if any).
  const Injection injection = effective_injection(m);
  if (m.probes.empty()) cli::warn(o.common, "the machine has no probes: turns.csv will have no rows");
  if (o.opal_compat && !o.integrator.empty() && o.integrator != "rk4")
    throw usage_error("--opal-compat tracks with the rk4 integrator: drop --integrator " + o.integrator);
  ModelOptions mo;
  mo.opal_map = o.opal_compat;
  TrackModel model = make_track_model(m, mo);
  // Effects are physics, not numerics: --opal-compat applies them like the default mode, but a
  // run with ones an OPAL input cannot state has no OPAL run to be checked against.
  if (o.opal_compat)
    for (const auto& line : effects_without_opal_input(m.effect_set))
      cli::warn(o.common, "--opal-compat with effect " + line + "; applied, but this run has no OPAL counterpart");
  warn_probes_outside(o.common, model);
  TrackSettings st = machine_track_settings(m, o.opal_compat ? "rk4" : o.integrator);
  if (o.steps_per_turn > 0) st.steps_per_turn = o.steps_per_turn;
  if (st.steps_per_turn < 16)
    throw data_error(m.path, 0, "/tracking/steps_per_turn: " + std::to_string(st.steps_per_turn) + " is too few (at least 16)");
  if (o.step_deg > 0) st.step_deg = o.step_deg;
  st.reference_stepper = o.reference_stepper;
  if (o.turns > 0) st.turns = o.turns;
  if (!(st.turns > 0)) throw usage_error("no turn count: give --turns or tracking.turns in the machine");
  if (st.integrator == "rk4" && !(model.rf_MHz > 0))
    throw usage_error("the rk4 integrator needs an RF frequency (rf.frequency_MHz) for its time step");
  st.gap_physics = (o.opal_deflection || o.opal_compat) ? GapPhysics::opal : GapPhysics::turnfit;
  st.opal_compat = o.opal_compat;
  const ParticleState reference = injection_state(injection, m.particle.mass_MeV, o.opal_compat);

  // A bunch when asked for by count or file (here or in the machine); --particles 0 forces
  // the single reference particle.
  const int n = o.particles >= 0 ? o.particles : m.bunch ? m.bunch->particles : 0;
  const std::string bfile = !o.bunch.empty() ? o.bunch : m.bunch ? m.bunch->file : std::string();
  const bool bunch = n > 0 || (!bfile.empty() && o.particles != 0);
  if (o.centroid && o.particles > 0) throw usage_error("--centroid computes the centre without a bunch: not with --particles");
  if (o.centroid && (!o.kicks.empty() || !o.histograms.empty() || !o.orbit.empty()))
    throw usage_error("--centroid writes the bunch's centre only: not with --kicks, --histograms or --orbit");
  // Space charge: the machine's block or --space-charge, unless --no-space-charge.
  if (o.space_charge && o.no_space_charge) throw usage_error("--space-charge with --no-space-charge: choose one");
  const bool sc_on = !o.no_space_charge && (o.space_charge || m.space_charge);
  const bool sc_option = o.current_uA >= 0 || !o.sc_grid.empty() || o.sc_every > 0;
  if (o.current_uA < 0 && o.current_uA != -1)
    throw usage_error("--current-uA must be >= 0, got " + cli::fmt(o.current_uA));
  if (sc_option && !sc_on)
    throw usage_error(o.no_space_charge ? "--current-uA, --sc-grid and --sc-every go with space charge, not with "
                                          "--no-space-charge"
                                        : "--current-uA, --sc-grid and --sc-every set space charge: add --space-charge "
                                          "(or a space_charge block in the machine)");
  sc::SpaceChargeSettings scs = m.space_charge ? sc::settings_of(*m.space_charge) : sc::SpaceChargeSettings{};
  if (sc_on) {
    if (o.current_uA >= 0) scs.current_uA = o.current_uA;
    else if (!m.space_charge)
      throw usage_error("--space-charge needs a beam current: --current-uA I (or space_charge.current_uA in the machine)");
    if (!o.sc_grid.empty()) scs.grid = sc::parse_grid(o.sc_grid);
    if (o.sc_every > 0) scs.every_steps = o.sc_every;
    // Asked for here, space charge without a bunch is an error; a machine's block only leaves
    // the single particle (or the quadrature) as it is, with a warning.
    if ((!bunch || o.centroid) && (o.space_charge || sc_option))
      throw usage_error("space charge is the field of a bunch's particles on each other: it needs a bunch "
                        "(--particles N or --bunch FILE" +
                        std::string(o.centroid ? "), not --centroid's quadrature" : ")"));
  }
  const bool sc_run = sc_on && bunch && !o.centroid;
  if (sc_on && !sc_run)
    cli::warn(o.common, "the machine's space_charge block acts on a bunch (--particles N): " +
                            std::string(o.centroid ? "the quadrature is tracked without it"
                                                   : "one particle is tracked without it"));
  if (o.centroid) {
    const std::vector<QuadratureNode> nodes = machine_bunch_quadrature(m, o.bunch);
    if (nodes.empty())
      throw data_error(m.path, 0, "/bunch: --centroid needs a bunch with spread: the machine's bunch block "
                                  "(emittances, sigma_E_MeV, sigma_phase_deg) or --bunch FILE");
    const CentroidTurns ct = centroid_turns(model, reference, injection, m.particle.mass_MeV, nodes, st,
                                            cli::resolve_threads(o.common.threads));
    OutputFile out(o.common.output);
    write_turns_csv(out.stream(), model, ct.centre, {ct.end}, !o.common.no_provenance);
    out.commit();
    if (ct.unknown)
      cli::warn(o.common, std::to_string(ct.unknown) +
                                " crossings that a particle of the quadrature misses, or where the probe sees under 5 % "
                                "of the bunch, keep the reference particle's record");
    if (ct.end.lost) cli::warn(o.common, ct.end.status);
    return 0;
  }
  if (!bunch && !o.bunch.empty()) throw usage_error("--bunch with --particles 0: choose one");
  if (bunch && !o.kicks.empty()) throw usage_error("--kicks records one particle: not with a bunch");
  {
    int to_stdout = (o.common.output.empty() || o.common.output == "-") + (o.kicks == "-") + (o.orbit == "-");
    if (to_stdout > 1) throw usage_error("only one output can go to stdout (use -o, --kicks FILE, --orbit FILE)");
  }
  // The reference particle's path (also for a bunch: its centre line).
  std::vector<PathPoint> path;
  std::unique_ptr<OutputFile> orbit_out;
  auto open_orbit = [&] {
    if (o.orbit.empty()) return;
    orbit_out = std::make_unique<OutputFile>(o.orbit);
    write_path_csv(orbit_out->stream(), path, !o.common.no_provenance);
  };

  // Probe profile files, checked before the work so a bad name fails fast.
  std::vector<std::string> hist_paths;
  if (!o.histograms.empty()) {
    for (const auto& p : model.probes) {
      if (p.name.empty() || p.name.find('/') != std::string::npos || p.name == "." || p.name == "..")
        throw data_error(m.path, 0, "/probes: probe name '" + p.name + "' cannot name a profile file");
      hist_paths.push_back((std::filesystem::path(o.histograms) / (p.name + ".csv")).string());
    }
    std::error_code ec;
    std::filesystem::create_directories(o.histograms, ec);
    if (ec || !std::filesystem::is_directory(o.histograms))
      throw Error(ExitCode::cant_create, o.histograms + ": cannot create the histogram folder" +
                                           (ec ? " (" + ec.message() + ")" : std::string()));
  }
  std::vector<std::unique_ptr<OutputFile>> hist_out;
  auto open_histograms = [&](const std::vector<ProbeHistogram>& hs, size_t particles) {
    for (size_t p = 0; p < hist_paths.size(); ++p) {
      hist_out.push_back(std::make_unique<OutputFile>(hist_paths[p]));
      write_profile_csv(hist_out.back()->stream(), model.probes[p], hs[p], particles, !o.common.no_provenance);
    }
  };

  if (bunch) {
    std::vector<BunchOffset> offs;
    std::vector<ParticleState> starts;
    if (!bfile.empty()) {
      const BunchFile file = read_bunch_file(bfile);
      if (n > 0 && static_cast<size_t>(n) > file.offsets.size())
        throw usage_error("--particles " + std::to_string(n) + ": " + bfile + " has only " +
                          std::to_string(file.offsets.size()) + " particles");
      starts = offset_states(injection, m.particle.mass_MeV, model.rf_MHz, file, static_cast<size_t>(std::max(n, 0)));
      offs.assign(file.offsets.begin(), file.offsets.begin() + static_cast<long>(starts.size()));
    } else {
      if (!m.bunch)
        throw data_error(m.path, 0, "/bunch: a bunch needs a distribution: the machine's bunch block "
                                    "(emittances, sigma_E_MeV, sigma_phase_deg) or --bunch FILE");
      const Bunch& b = *m.bunch;
      if (b.emittance_r_mm_mrad == 0 && b.emittance_z_mm_mrad == 0 && b.sigma_E_MeV == 0 && b.sigma_phase_deg == 0)
        cli::warn(o.common, "the bunch block has no spread (emittances, sigma_E_MeV, sigma_phase_deg all 0): " +
                                std::to_string(n) + " identical particles");
      offs = gaussian_bunch(b, static_cast<size_t>(n), o.common.seed);
      starts = offset_states(injection, m.particle.mass_MeV, model.rf_MHz, offs);
    }
    const bool show = !o.common.quiet && cli::stderr_is_tty();
    std::atomic<size_t> shown{0};
    auto progress = [&](size_t done) {
      if (!show) return;
      const size_t pct = done * 100 / starts.size();
      if (pct > shown.exchange(pct)) std::fprintf(stderr, "\rturnfit-track: %zu%% of %zu particles", pct, starts.size());
    };
    if (!o.orbit.empty()) {
      std::vector<TurnRecord> unused;
      track_particle(model, reference, st, unused, nullptr, &path);
    }
    // A current of 0 is no space charge: the run without it, byte for byte.
    std::unique_ptr<sc::SpaceChargeKick> sck;
    CollectiveKick ck;
    if (sc_run && scs.current_uA > 0) {
      sck = std::make_unique<sc::SpaceChargeKick>(model, scs, starts.size(), cli::resolve_threads(o.common.threads));
      ck = sck->collective();
    }
    BunchResult res = track_bunch(model, starts, st, cli::resolve_threads(o.common.threads), progress, {},
                                  sck ? &ck : nullptr);
    if (show) std::fprintf(stderr, "\r\033[K");
    if (sck && o.sc_timing) std::fprintf(stderr, "turnfit-track: %s\n", sc::timing_text(sck->stats()).c_str());
    OutputFile out(o.common.output);
    write_bunch_csv(out.stream(), model, res, !o.common.no_provenance);
    if (sck) out.stream() << sc::stats_comment(scs, sck->stats());
    open_histograms(res.histograms, res.particles);
    open_orbit();
    out.commit();
    for (auto& h : hist_out) h->commit();
    if (orbit_out) orbit_out->commit();
    if (!res.lost.empty())
      cli::warn(o.common, std::to_string(res.lost.size()) + " of " + std::to_string(res.particles) +
                              " particles lost; first: particle " + std::to_string(res.lost.front().first) + " " +
                              res.lost.front().second.status);
    return 0;
  }

  std::vector<TurnRecord> turns;
  std::vector<KickRecord> kicks;
  TrackEnd end = track_particle(model, reference, st, turns, o.kicks.empty() ? nullptr : &kicks,
                                o.orbit.empty() ? nullptr : &path);
  // Open every output before committing any, so a failing one leaves none behind.
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
  if (!hist_paths.empty()) {
    std::vector<ProbeHistogram> hs = empty_histograms(model);
    for (const auto& t : turns) add_crossing(hs, t);
    open_histograms(hs, 1);
  }
  open_orbit();
  out.commit();
  if (kout) kout->commit();
  for (auto& h : hist_out) h->commit();
  if (orbit_out) orbit_out->commit();
  if (end.lost) cli::warn(o.common, end.status);
  return 0;
}

}  // namespace turnfit
