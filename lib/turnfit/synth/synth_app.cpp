// turnfit-synth: synthetic probe profiles, trim coil phase scans and the hidden truth of a run.
#include "turnfit/synth/synth_app.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {
namespace {

/// An rms or a length: 0 or more (CLI11 prefixes the option's name to the message).
const CLI::Validator kNonNegative(
    [](std::string& v) {
      double x = 0;
      if (!parse_decimal(v, x)) return v + " is not a number";
      return x >= 0 ? std::string() : v + " must be 0 or more";
    },
    "NONNEGATIVE");

}  // namespace

void add_synth_options(CLI::App& app, SynthOptions& o) {
  app.description(
      "Synthetic measurements of a truth machine: one wire-probe profile per probe (a bunch tracked\n"
      "through the machine, seen by a wire of finite width with noise and baseline), one phase-shift\n"
      "scan per trim coil (delta sin(phi) against radius), and truth.json with the hidden values.");
  app.add_option("machine", o.machine, "Truth machine file ('-' for stdin)");
  app.add_option("--set", o.sets, "Set a design variable or JSON pointer: NAME=VALUE (repeatable)")->allow_extra_args(false);
  app.add_option("--dvars", o.dvars, "JSON file of design-variable values");
  app.add_option("-o,--out", o.out, "Output folder (created if missing)");
  app.add_option("--current-uA", o.wire.current_uA,
                 "Beam current [uA]: the wire signal's scale and, with space charge, the bunch charge (default: the "
                 "machine's space_charge.current_uA, else 88)")
      ->check(CLI::Range(1e-6, 1e5))
      ->each([&o](const std::string&) { o.current_given = true; });
  app.add_flag("--space-charge", o.space_charge,
               "Track the profiles' bunch with its own field at --current-uA (on by itself for a machine with a "
               "space_charge block)");
  app.add_flag("--no-space-charge", o.no_space_charge, "No space charge, even if the machine has a space_charge block");
  app.add_option("--sc-grid", o.sc_grid, "Space-charge grid points, radial x vertical x longitudinal (default 32x32x32)");
  app.add_option("--sc-every", o.sc_every, "One space-charge solve every K integration steps (default 1)")
      ->check(CLI::Range(1, 100000));
  app.add_option("--particles", o.particles, "Bunch size (default: the machine's bunch.particles, else 2000)")
      ->check(CLI::Range(1, 100000000));
  app.add_option("--turns", o.turns, "Revolutions to track (default: the machine's tracking.turns)")->check(CLI::Range(0.0, 1e6));
  app.add_option("--integrator", o.integrator, "Integrator (azimuth or rk4; default: the machine's, else azimuth)")
      ->check(CLI::IsMember({"azimuth", "rk4"}));
  app.add_option("--step-deg", o.step_deg, "azimuth: largest step in degrees (default: the machine's, else 1)")
      ->check(CLI::Range(1e-4, 45.0));
  app.add_option("--wire-mm", o.wire.wire_mm, "Width of the probe wire [mm]")->check(CLI::Range(0.0, 100.0))->capture_default_str();
  app.add_option("--electronic-nA", o.wire.electronic_nA, "Rms electronic noise per reading [nA]")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--shot-nA", o.wire.shot_nA, "Shot-like noise: variance = this times the signal [nA]")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--baseline-nA", o.wire.baseline_nA, "Baseline offset [nA]")->capture_default_str();
  app.add_option("--baseline-drift-nA", o.wire.baseline_drift_nA, "Rms baseline drift over a scan [nA]")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  // The preset's values, shown in the help so that it cannot go stale.
  const SynthPreset none = synth_preset("none"), paper = synth_preset("paper");
  auto dflt = [](double a, double b) {
    return " (default: the preset's, none " + cli::fmt(a, 6) + ", paper " + cli::fmt(b, 6) + ")";
  };
  app.add_option("--scan-errors", o.scan_errors,
                 "Measurement-error preset: none (run-to-run drift only, the default) or paper (per-turn scan "
                 "errors and a smaller drift, together the paper's repeatability, sigma about 0.5 mm)")
      ->check(CLI::IsMember(synth_preset_names()))->capture_default_str();
  app.add_option("--drift-r-mm", o.drift_r_mm, "Run-to-run rms change of the injection radius [mm]" +
                                                   dflt(none.drift.r_mm, paper.drift.r_mm))
      ->check(kNonNegative);
  app.add_option("--drift-pr-mrad", o.drift_pr_mrad, "Run-to-run rms change of the injection angle [mrad]" +
                                                         dflt(none.drift.pr_mrad, paper.drift.pr_mrad))
      ->check(kNonNegative);
  app.add_option("--drift-voltage-rel", o.drift_voltage_rel, "Run-to-run rms relative change of the cavity voltages" +
                                                                 dflt(none.drift.voltage_rel, paper.drift.voltage_rel))
      ->check(kNonNegative);
  app.add_flag("--no-drift", o.no_drift, "Measure the truth machine itself (no run-to-run drift)");
  app.add_option("--intensity-rel", o.intensity_rel, "Rms relative fluctuation of the beam current during a scan" +
                                                         dflt(none.scan.intensity_rel, paper.scan.intensity_rel))
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--intensity-corr-mm", o.intensity_corr_mm,
                 "Correlation length of the current's fluctuation in wire travel [mm]" +
                     dflt(none.scan.intensity_corr_mm, paper.scan.intensity_corr_mm))
      ->check(kNonNegative);
  app.add_option("--drive-mm", o.drive_mm, "Rms probe drive error, the wire's true minus recorded position [mm]" +
                                               dflt(none.scan.drive_mm, paper.scan.drive_mm))
      ->check(kNonNegative);
  app.add_option("--drive-corr-mm", o.drive_corr_mm, "Correlation length of the drive error along the travel [mm]" +
                                                         dflt(none.scan.drive_corr_mm, paper.scan.drive_corr_mm))
      ->check(kNonNegative);
  app.add_option("--readout-mm", o.readout_mm, "Rms position error of each reading, independent [mm]" +
                                                   dflt(none.scan.readout_mm, paper.scan.readout_mm))
      ->check(kNonNegative);
  app.add_option("--phase-step-mm", o.phase.step_mm, "Radial spacing of the phase probes [mm]")
      ->check(CLI::Range(0.01, 1e4))->capture_default_str();
  app.add_option("--phase-azimuth-deg", o.phase.azimuth_deg, "Azimuth of the phase probes [deg]")->capture_default_str();
  app.add_option("--phase-noise-deg", o.phase.noise_deg, "Rms noise of a phase reading [deg]")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--tc-excitation-T", o.phase.excitation_T, "Test excitation of each trim coil in its phase scan [T]")
      ->capture_default_str();
  app.add_flag("--no-phase", o.no_phase, "No trim coil phase scans");
  app.add_flag("--reference-stepper", o.reference_stepper,
               "azimuth: track one particle at a time with the reference stepper (several times slower; "
               "the same results to 1e-6 mm: for checks and benchmarks)");
  app.add_flag("--no-profiles", o.no_profiles, "No probe profiles");
  cli::add_common_options(app, o.common, cli::kThreads | cli::kSeed);
}

namespace {

std::string num(double v, int digits = 10) { return cli::fmt(v, digits); }

/// A file name from an element name, or EX_DATAERR naming where the name came from.
std::string file_name(const Machine& m, const std::string& where, const std::string& name) {
  if (name.empty() || name.find('/') != std::string::npos || name == "." || name == "..")
    throw data_error(m.path, 0, where + ": name '" + name + "' cannot name an output file");
  return name + ".csv";
}

}  // namespace

SynthPreset synth_models(const SynthOptions& o) {
  SynthPreset p = synth_preset(o.scan_errors);
  auto take = [](const std::optional<double>& v, double& into) {
    if (v) into = *v;
  };
  take(o.drift_r_mm, p.drift.r_mm);
  take(o.drift_pr_mrad, p.drift.pr_mrad);
  take(o.drift_voltage_rel, p.drift.voltage_rel);
  if (o.no_drift) p.drift = DriftModel{0, 0, 0};
  take(o.intensity_rel, p.scan.intensity_rel);
  take(o.intensity_corr_mm, p.scan.intensity_corr_mm);
  take(o.drive_mm, p.scan.drive_mm);
  take(o.drive_corr_mm, p.scan.drive_corr_mm);
  take(o.readout_mm, p.scan.readout_mm);
  return p;
}

void write_synth_profile(std::ostream& os, const SynthProfile& p, const WireModel& w, std::uint64_t seed,
                         bool provenance, const ScanErrorModel& scan, const std::string& preset) {
  if (provenance) os << cli::provenance_comment();
  os << "# probe=" << p.probe << " step_mm=" << num(p.step_mm, 6) << " current_uA=" << num(w.current_uA, 6)
     << " seed=" << seed << "\n";
  os << "# synthetic: wire_mm=" << num(w.wire_mm, 6) << " intensity=reading/" << num(p.scale_nA, 6)
     << "nA (normalized to the highest reading)\n";
  if (scan.active() || preset != "none")
    os << "# scan errors: preset=" << preset << " intensity_rel=" << num(scan.intensity_rel, 6)
       << " intensity_corr_mm=" << num(scan.intensity_corr_mm, 6) << " drive_mm=" << num(scan.drive_mm, 6)
       << " drive_corr_mm=" << num(scan.drive_corr_mm, 6) << " readout_mm=" << num(scan.readout_mm, 6) << "\n";
  os << "position_mm,intensity\n";
  char buf[96];
  for (size_t k = 0; k < p.position_mm.size(); ++k) {
    std::snprintf(buf, sizeof buf, "%.6f,%.6g\n", p.position_mm[k], p.intensity[k]);
    os << buf;
  }
}

void write_phase_scan(std::ostream& os, const PhaseScan& s, const PhaseModel& pm, std::uint64_t seed,
                      bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "# coil=" << s.coil << " excitation_T=" << num(s.excitation_T, 8) << " seed=" << seed
     << " azimuth_deg=" << num(pm.azimuth_deg, 8) << " phase_noise_deg=" << num(pm.noise_deg, 6) << "\n";
  os << "# delta sin(phi): beam phase (0 = crest) with the coil at nominal + excitation minus at nominal\n";
  os << "r_mm,dsinphi\n";
  char buf[96];
  for (size_t j = 0; j < s.r_mm.size(); ++j) {
    std::snprintf(buf, sizeof buf, "%.4f,%.6e\n", s.r_mm[j], s.dsinphi[j]);
    os << buf;
  }
}

nlohmann::json truth_json(const Machine& truth, const SynthSettings& s, const SynthResult& r) {
  using nlohmann::json;
  json j;
  j["format"] = "turnfit-synth-truth/1";
  j["machine"] = truth.path;
  j["seed"] = s.seed;
  j["current_uA"] = s.wire.current_uA;
  if (s.space_charge)
    j["space_charge"] = {{"current_uA", s.wire.current_uA},
                         {"grid", {s.sc.grid.nx, s.sc.grid.ny, s.sc.grid.nz}},
                         {"every_steps", s.sc.every_steps},
                         {"halo_sigma", s.sc.halo_sigma}};
  j["particles"] = r.particles;
  j["lost"] = r.lost;
  json dv = json::object();
  for (const auto& [name, d] : truth.dvars) dv[name] = dvar_value(truth, name);
  j["dvars"] = dv;
  j["effects"] = truth.effects;
  j["drift"] = {{"model", {{"r_mm", s.drift.r_mm}, {"pr_mrad", s.drift.pr_mrad}, {"voltage_rel", s.drift.voltage_rel}}},
                {"dr_mm", r.drift.dr_mm},
                {"dpr_mrad", r.drift.dpr_mrad},
                {"dvoltage_rel", r.drift.dvoltage_rel}};
  if (r.bunch_mean.particles > 0) {
    // Offsets in bunch_columns' units; at_reference_time: the same start at the reference's time.
    const BunchMean& b = r.bunch_mean;
    auto offsets = [](const BunchOffset& o) {
      return json{{"dr_mm", o.dr_mm}, {"dpr_mrad", o.dpr_mrad}, {"dz_mm", o.dz_mm},
                  {"dpz_mrad", o.dpz_mrad}, {"dE_MeV", o.dE_MeV}};
    };
    json mean = offsets(b.offset);
    mean["dphase_deg"] = b.offset.dphase_deg;
    mean["dt_ns"] = b.dt_ns;
    mean["particles"] = b.particles;
    json at = offsets(b.at_reference_time);
    at["dphi_deg"] = b.dphi_deg;
    mean["at_reference_time"] = at;
    j["bunch_mean"] = mean;
  }
  json prof = json::object();
  for (const auto& p : r.profiles)
    prof[p.probe] = {{"baseline_nA", p.baseline_nA}, {"drift_nA", p.drift_nA}, {"scale_nA", p.scale_nA}};
  j["wire"] = {{"wire_mm", s.wire.wire_mm},
               {"electronic_nA", s.wire.electronic_nA},
               {"shot_nA", s.wire.shot_nA},
               {"baseline_nA", s.wire.baseline_nA},
               {"baseline_drift_nA", s.wire.baseline_drift_nA},
               {"profiles", prof}};
  if (s.scan.active() || s.preset != "none") {
    // Only then: a run without scan errors writes the truth.json it always wrote.
    json per = json::object();
    auto rms_of = [](const std::vector<double>& v, double centre) {
      double q = 0;
      for (double x : v) q += (x - centre) * (x - centre);
      return v.empty() ? 0.0 : std::sqrt(q / static_cast<double>(v.size()));
    };
    for (const auto& p : r.profiles)
      per[p.probe] = {{"drive_rms_mm", rms_of(p.scan.drive_mm, 0)},
                      {"readout_rms_mm", rms_of(p.scan.readout_mm, 0)},
                      {"intensity_rms_rel", rms_of(p.scan.intensity_factor, 1)}};
    j["scan_errors"] = {{"preset", s.preset},
                        {"intensity_rel", s.scan.intensity_rel},
                        {"intensity_corr_mm", s.scan.intensity_corr_mm},
                        {"drive_mm", s.scan.drive_mm},
                        {"drive_corr_mm", s.scan.drive_corr_mm},
                        {"readout_mm", s.scan.readout_mm},
                        {"profiles", per}};
  }
  json coils = json::object();
  for (const auto& p : r.phases) coils[p.coil] = {{"nominal_T", p.nominal_T}, {"excitation_T", p.excitation_T}};
  j["phase"] = {{"step_mm", s.phase.step_mm},
                {"azimuth_deg", s.phase.azimuth_deg},
                {"noise_deg", s.phase.noise_deg},
                {"coils", coils}};
  // The bunch's true crossing positions of this run: what a perfect peak finder would report.
  json turns = json::object();
  for (const auto& name : r.probe_names) turns[name] = json::array();
  // With a drive error: its value at each turn's centre (the wire's true minus recorded position
  // there; the turn's peak appears about that much further in), interpolated between readings.
  std::map<std::string, const SynthProfile*> prof_of;
  for (const auto& p : r.profiles) prof_of[p.probe] = &p;
  for (const auto& c : r.centroids) {
    const std::string& name = r.probe_names[static_cast<size_t>(c.probe)];
    json t = {{"turn", c.turn}, {"r_mm", c.r_mm}, {"r_rms_mm", c.r_rms_mm}, {"particles", c.particles}};
    if (auto it = prof_of.find(name); it != prof_of.end() && !it->second->scan.drive_mm.empty()) {
      const SynthProfile& p = *it->second;
      const std::vector<double>& x = p.position_mm;
      const double u = x.size() > 1 ? (c.r_mm - x.front()) / (x[1] - x[0]) : 0.0;
      const size_t n = x.size();
      const double uc = std::clamp(u, 0.0, static_cast<double>(n - 1));
      const size_t k = std::min(n > 1 ? n - 2 : 0, static_cast<size_t>(uc));
      const double a = n > 1 ? uc - static_cast<double>(k) : 0.0;
      t["drive_mm"] = n > 1 ? (1 - a) * p.scan.drive_mm[k] + a * p.scan.drive_mm[k + 1] : p.scan.drive_mm[0];
    }
    turns[name].push_back(t);
  }
  j["turns"] = turns;
  j["machine_doc"] = truth.doc;
  if (auto p = cli::provenance(); !p.empty()) j["provenance"] = p;
  return j;
}

int run_synth(const SynthOptions& o) {
  if (o.machine.empty()) throw usage_error("give a truth machine file ('-' for stdin)");
  if (o.out.empty()) throw usage_error("give an output folder: --out DIR");
  if (o.machine == "-" && o.dvars == "-") throw usage_error("only one input can be stdin (machine, --dvars)");
  if (o.no_phase && o.no_profiles) throw usage_error("--no-phase with --no-profiles leaves nothing to do");
  Machine m = load_machine(o.machine);
  apply_sets(m, o.sets);
  if (!o.dvars.empty()) apply_dvars_file(m, o.dvars);
  if (!m.injection) throw data_error(m.path, 0, "/injection: the machine has no injection block to track from");

  SynthSettings s;
  s.seed = o.common.seed;
  s.threads = cli::resolve_threads(o.common.threads);
  s.wire = o.wire;
  if (o.space_charge && o.no_space_charge) throw usage_error("--space-charge with --no-space-charge: choose one");
  s.space_charge = !o.no_space_charge && (o.space_charge || m.space_charge);
  if ((!o.sc_grid.empty() || o.sc_every > 0) && !s.space_charge)
    throw usage_error("--sc-grid and --sc-every set space charge: add --space-charge (or a space_charge block in the "
                      "machine)");
  if (m.space_charge) s.sc = sc::settings_of(*m.space_charge);
  if (!o.sc_grid.empty()) s.sc.grid = sc::parse_grid(o.sc_grid);
  if (o.sc_every > 0) s.sc.every_steps = o.sc_every;
  if (!o.current_given && m.space_charge && m.space_charge->current_uA > 0) s.wire.current_uA = m.space_charge->current_uA;
  if (s.space_charge && o.no_profiles)
    throw usage_error("space charge acts on the profiles' bunch: not with --no-profiles");
  const SynthPreset models = synth_models(o);
  s.drift = models.drift;
  s.scan = models.scan;
  s.preset = models.name;
  s.phase = o.phase;
  s.profiles = !o.no_profiles;
  s.phases = !o.no_phase;
  s.particles = o.particles > 0 ? static_cast<size_t>(o.particles)
                : (m.bunch && m.bunch->particles > 0) ? static_cast<size_t>(m.bunch->particles) : 2000;
  TrackSettings& st = s.track;
  st = machine_track_settings(m, o.integrator);
  if (o.step_deg > 0) st.step_deg = o.step_deg;
  st.reference_stepper = o.reference_stepper;
  if (o.turns > 0) st.turns = o.turns;
  if (!(st.turns > 0)) throw usage_error("no turn count: give --turns or tracking.turns in the machine");
  if (st.integrator == "rk4" && !(m.rf.frequency_MHz > 0))
    throw usage_error("the rk4 integrator needs an RF frequency (rf.frequency_MHz) for its time step");

  // Output names first, so a bad one fails before the work.
  std::vector<std::string> profile_files, phase_files;
  if (s.profiles)
    for (size_t i = 0; i < m.probes.size(); ++i)
      profile_files.push_back(file_name(m, "/probes/" + std::to_string(i) + "/name", m.probes[i].name));
  if (s.phases)
    for (size_t i = 0; i < m.trimcoils.size(); ++i)
      phase_files.push_back(file_name(m, "/trimcoils/" + std::to_string(i) + "/name", m.trimcoils[i].name));
  if (s.profiles && m.probes.empty()) cli::warn(o.common, "the machine has no probes: no profiles");
  if (s.phases && m.trimcoils.empty()) cli::warn(o.common, "the machine has no trim coils: no phase scans");
  {
    std::error_code ec;
    if (std::filesystem::exists(o.out, ec) && !std::filesystem::is_directory(o.out, ec))
      throw Error(ExitCode::cant_create, o.out + ": cannot create the output folder: a file of that name exists");
  }

  const SynthResult r = synthesize(m, s);

  for (const auto& p : r.profiles)
    if (!(p.scale_nA > 0) || std::all_of(p.signal_nA.begin(), p.signal_nA.end(), [](double v) { return v == 0; }))
      cli::warn(o.common, "probe '" + p.probe + "' saw no beam: its profile is noise and baseline only");
  if (r.lost > 0) cli::warn(o.common, std::to_string(r.lost) + " of " + std::to_string(r.particles) + " particles lost");

  // Folders, then every file to a temporary, then all renamed: a failure leaves no result.
  namespace fs = std::filesystem;
  auto make_dir = [](const fs::path& d) {
    std::error_code ec;
    fs::create_directories(d, ec);
    if (ec || !fs::is_directory(d))
      throw Error(ExitCode::cant_create, d.string() + ": cannot create the output folder" +
                                             (ec ? " (" + ec.message() + ")" : std::string()));
  };
  make_dir(o.out);
  if (!r.phases.empty()) make_dir(fs::path(o.out) / "phase");
  const bool prov = !o.common.no_provenance;
  std::vector<std::unique_ptr<OutputFile>> files;
  for (size_t i = 0; i < r.profiles.size(); ++i) {
    files.push_back(std::make_unique<OutputFile>((fs::path(o.out) / profile_files[i]).string()));
    write_synth_profile(files.back()->stream(), r.profiles[i], s.wire, s.seed, prov, s.scan, s.preset);
  }
  for (size_t i = 0; i < r.phases.size(); ++i) {
    files.push_back(std::make_unique<OutputFile>((fs::path(o.out) / "phase" / phase_files[i]).string()));
    write_phase_scan(files.back()->stream(), r.phases[i], s.phase, s.seed, prov);
  }
  files.push_back(std::make_unique<OutputFile>((fs::path(o.out) / "truth.json").string()));
  nlohmann::json tj = truth_json(m, s, r);
  if (!prov) tj.erase("provenance");
  files.back()->stream() << json_text(tj, 2) << "\n";
  for (auto& f : files) f->commit();
  return 0;
}

}  // namespace turnfit
