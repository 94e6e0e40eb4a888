// turnfit-track as a library function: options, run, turns.csv output.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit {

/// Everything turnfit-track is asked to do.
struct TrackOptions {
  cli::CommonOptions common;
  std::string machine;
  std::vector<std::string> sets;
  std::string dvars;
  std::string integrator;     ///< empty: machine's tracking.integrator, else "azimuth"
  int steps_per_turn = 0;     ///< rk4 (0: machine's, else 2880)
  double step_deg = 0;        ///< azimuth: largest step (0: machine's, else kDefaultStepDeg)
  double turns = 0;           ///< 0: machine's tracking.turns
  bool list_integrators = false;
  std::string kicks;          ///< --kicks FILE: every gap crossing as CSV
  bool opal_deflection = false;  ///< OPAL 2022.1's RF deflection (divided by 2 pi)
  bool reference_stepper = false;  ///< the reference stepper (checks, benchmarks)
  bool opal_compat = false;      ///< OPAL-cycl 2022.1's numerics throughout
  int particles = -1;            ///< bunch size (-1: machine's bunch.particles; 0: one particle)
  std::string bunch;             ///< --bunch FILE: offsets instead of the Gaussian
  bool centroid = false;         ///< --centroid: the bunch's centre by quadrature, not the reference particle
  std::string histograms;        ///< --histograms DIR: one probe profile per probe
  std::string orbit;             ///< --orbit FILE: the (reference) particle's path, every step
  bool space_charge = false;     ///< --space-charge: the bunch's own field (the machine's block or defaults)
  bool no_space_charge = false;  ///< --no-space-charge: none, even with the machine's block
  double current_uA = -1;        ///< --current-uA (negative: not given)
  std::string sc_grid;           ///< --sc-grid NxNxN (empty: the machine's or 32^3)
  int sc_every = 0;              ///< --sc-every K (0: the machine's or 1)
  bool sc_timing = false;        ///< --sc-timing: the solver's time split on stderr
};

/// Registers turnfit-track's options.
void add_track_options(CLI::App& app, TrackOptions& o);

/// Runs turnfit-track; returns the exit code.
int run_track(const TrackOptions& o);

/// Writes a bunch's centroids as turns.csv (architecture.md columns, then particles and
/// r_rms_mm), a '#' line per lost particle and a summary line.
void write_bunch_csv(std::ostream& os, const TrackModel& model, const BunchResult& res, bool provenance);

/// Writes one probe's histogram as a probe profile (position_mm,intensity; '#' metadata).
void write_profile_csv(std::ostream& os, const ProbeLine& probe, const ProbeHistogram& h, size_t particles,
                       bool provenance);

/// Writes probe crossings as turns.csv (architecture.md columns), ending with a '#' line per
/// particle that says how its track ended.
void write_turns_csv(std::ostream& os, const TrackModel& model, const std::vector<TurnRecord>& turns,
                     const std::vector<TrackEnd>& ends, bool provenance);

}  // namespace turnfit
