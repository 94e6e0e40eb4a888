// turnfit-compare as a library function: options, the comparison report, and its writers.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/metrics/metrics.hpp"

namespace turnfit {

/// Everything turnfit-compare is asked to do.
struct CompareOptions {
  cli::CommonOptions common;  ///< -o (errors), --format json|text, -q, --no-provenance
  std::string measured;       ///< peaks.csv (or a turns.csv: model against model); "-" stdin
  std::string simulated;      ///< turns.csv; "-" stdin
  std::string objectives;     ///< --objectives: a spec, or @FILE (problem file or array)
  double tol_mm = 0;          ///< --tol: largest |r_sim - r_meas| that counts as agreeing
  std::string residuals;      ///< --residuals FILE: one CSV row per matched turn
};

/// Registers turnfit-compare's options.
void add_compare_options(CLI::App& app, CompareOptions& o);

/// A finished comparison: the matched turns, statistics per probe and overall, objectives.
struct CompareReport {
  TurnTable measured;                   ///< measured turns (peaks or turns format)
  TurnTable simulated;                  ///< simulated turns
  Comparison comparison;                ///< matching and turn counts
  std::vector<ErrorStats> probe_stats;  ///< per measured probe; largest_index into residuals
  ErrorStats overall;                   ///< all matched turns pooled (the paper's Tables III-IV)
  std::vector<Objective> objectives;    ///< as asked
  std::vector<ObjectiveValue> values;   ///< parallel to objectives
  double tol_mm = 0;                    ///< the tolerance the verdict uses

  /// Max |dr| within tol_mm, at least one turn matched and the turn counts agree (exit 0).
  bool agrees() const;
};

/// Compares measured and simulated turns and evaluates the objectives (EX_DATAERR if an
/// objective does not fit the measured data).
CompareReport make_compare_report(TurnTable measured, TurnTable simulated, std::vector<Objective> objectives,
                                  double tol_mm);

/// errors.json: per probe and overall statistics, turn counts, objectives, verdict.
void write_errors_json(std::ostream& os, const CompareReport& r, bool provenance);
/// The people-readable form: turn-by-turn tables per probe, then the summary.
void write_errors_text(std::ostream& os, const CompareReport& r);
/// residuals.csv: probe,turn,r_meas_mm,r_sim_mm,delta_mm (delta = sim - meas), unmatched
/// turns as '#' lines.
void write_residuals_csv(std::ostream& os, const CompareReport& r, bool provenance);

/// Runs turnfit-compare; returns 0 when the simulation agrees within --tol, 1 when it does
/// not (like diff); errors are thrown as turnfit::Error.
int run_compare(const CompareOptions& o);

}  // namespace turnfit
