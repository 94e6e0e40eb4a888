// turnfit-localsearch as a library: options, the start (dvars file, nsga front or population
// log), the fit, and its outputs (best dvars, report, residuals).
#pragma once

#include <CLI/CLI.hpp>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/optimize/coordinate_search.hpp"
#include "turnfit/optimize/localsearch.hpp"

namespace turnfit {

/// Everything turnfit-localsearch is asked to do.
struct LocalSearchOptions {
  cli::CommonOptions common;  ///< -o: the best design as a dvars file; --threads, -q
  std::string problem;        ///< the turn-pattern problem file
  std::string start;          ///< --start: dvars file, nsga front or population log ("" = the machine's values)
  std::string pick = "linf";  ///< --pick: which design of a front or log (linf | sum)
  std::string report;         ///< --report: JSON report
  std::string residuals;      ///< --residuals: compare's residual CSV of the result
  LocalSearchSettings settings;
  std::string method = "lm";  ///< --method: lm | coordinate
  int sweeps_without_gain = 3;  ///< --sweeps (coordinate): stop after this many sweeps without gain
};

/// Registers turnfit-localsearch's options.
void add_localsearch_options(CLI::App& app, LocalSearchOptions& o);

/// The start design from a file: a dvars file ({name: value}; variables it does not name keep
/// the machine's value), a turnfit-nsga front (a JSON array of {x, f, violation}) or population
/// log (JSON Lines): the feasible design with the smallest largest objective (pick "linf") or
/// smallest sum (pick "sum"). EX_DATAERR naming the file and key for an unknown variable, a
/// value outside the problem's bounds, or a front/log with no usable design.
std::vector<double> read_start(const TurnPatternProblem& p, const std::string& path, const std::string& pick);

/// The report (turnfit-localsearch/1) of a finished search.
nlohmann::json localsearch_report(const TurnPatternProblem& p, const LocalSearchResult& r, const std::string& start,
                                  bool provenance, double tolerance_mm);

/// The report (turnfit-localsearch/1, method "coordinate") of a finished coordinate search.
nlohmann::json coordinate_report(const TurnPatternProblem& p, const CoordinateResult& r, const std::string& start,
                                 bool provenance);

/// Runs turnfit-localsearch; returns the exit code.
int run_localsearch(const LocalSearchOptions& o);

}  // namespace turnfit
