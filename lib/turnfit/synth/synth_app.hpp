// turnfit-synth as a library function: options, run, the files it writes.
#pragma once

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/synth/synth.hpp"

namespace turnfit {

/// Everything turnfit-synth is asked to do.
struct SynthOptions {
  cli::CommonOptions common;
  std::string machine;
  std::vector<std::string> sets;
  std::string dvars;
  std::string out;            ///< --out DIR
  int particles = -1;         ///< -1: the machine's bunch.particles, else 2000
  double turns = 0;           ///< 0: the machine's tracking.turns
  std::string integrator;     ///< empty: the machine's, else "azimuth"
  double step_deg = 0;        ///< 0: the machine's, else the tracker's default
  WireModel wire;
  std::string scan_errors = "none";  ///< --scan-errors: the preset of scan errors and drift
  /// Overrides of the preset's values (unset: the preset's).
  std::optional<double> drift_r_mm, drift_pr_mrad, drift_voltage_rel;
  std::optional<double> intensity_rel, intensity_corr_mm, drive_mm, drive_corr_mm, readout_mm;
  bool no_drift = false;
  PhaseModel phase;
  bool no_phase = false;
  bool reference_stepper = false;  ///< track with the reference stepper (checks, benchmarks)
  bool no_profiles = false;
  bool current_given = false;      ///< --current-uA was given (else the machine's space_charge current, else 88)
  bool space_charge = false;       ///< --space-charge
  bool no_space_charge = false;    ///< --no-space-charge
  std::string sc_grid;             ///< --sc-grid (empty: the machine's or 32^3)
  int sc_every = 0;                ///< --sc-every (0: the machine's or 1)
};

/// Registers turnfit-synth's options.
void add_synth_options(CLI::App& app, SynthOptions& o);

/// Runs turnfit-synth; returns the exit code.
int run_synth(const SynthOptions& o);

/// The drift and scan-error models an invocation asks for: the preset's, with the options given
/// in their place, and no drift at all with --no-drift. EX_USAGE for an unknown preset.
SynthPreset synth_models(const SynthOptions& o);

/// Writes one synthetic probe profile (position_mm,intensity with '#' metadata lines; a line
/// with the scan-error model when `scan` is on or the preset is not "none").
void write_synth_profile(std::ostream& os, const SynthProfile& p, const WireModel& w, std::uint64_t seed,
                         bool provenance, const ScanErrorModel& scan = {}, const std::string& preset = "none");

/// Writes one phase scan (r_mm,dsinphi with '#' metadata lines).
void write_phase_scan(std::ostream& os, const PhaseScan& s, const PhaseModel& pm, std::uint64_t seed,
                      bool provenance);

/// The hidden values of a synthesis: the truth machine's design variables and effects, the
/// run's drift, seed and current, the measurement model and the true turn positions.
nlohmann::json truth_json(const Machine& truth, const SynthSettings& s, const SynthResult& r);

}  // namespace turnfit
