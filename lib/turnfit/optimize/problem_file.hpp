// Problems from the command line: built-in test problems, problem files (turnfit-problem/1),
// and designs evaluated by an external command (one process per design, JSON in and out).
#pragma once

#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/optimize/problems.hpp"

namespace turnfit {

/// Evaluates each design by running a shell command: the design goes to its stdin as one JSON
/// object {"x": {name: value, ...}} (or {"x": [values]} when the variables have no names), and
/// it answers on stdout with {"f": [...], "g": [...]} (each an array, or an object keyed by the
/// objective and constraint names), or {"error": "why"}. A non-zero exit, a timeout, a signal,
/// or an answer that is not such JSON makes the design a failed evaluation with that reason.
class CommandProblem : public Problem {
 public:
  /// The command's problem: bounds, sizes and names, the command line (run by /bin/sh -c in
  /// folder cwd, "" = the current one), and its time limit (0 = none).
  CommandProblem(std::string name, std::vector<double> lower, std::vector<double> upper,
                 std::vector<std::string> variable_names, std::vector<std::string> objective_names,
                 std::vector<std::string> constraint_names, std::string command, std::string cwd,
                 double timeout_s);
  /// Runs the command on x (thread-safe: one process per call).
  Evaluation evaluate(const std::vector<double>& x) const override;
  /// The command line.
  const std::string& command() const { return command_; }

 private:
  std::vector<std::string> objective_names_, constraint_names_;
  std::string command_, cwd_;
  double timeout_s_;
};

/// Parses a command's answer (see CommandProblem) into an Evaluation; a malformed answer gives
/// ok = false with the reason.
Evaluation parse_command_answer(const std::string& out, const std::vector<std::string>& objective_names,
                                const std::vector<std::string>& constraint_names);

/// A problem ready to optimize, with the names the outputs use.
struct LoadedProblem {
  std::unique_ptr<Problem> problem;
  std::vector<std::string> objective_names;   ///< f1, f2, ... when the problem names none
  std::vector<std::string> constraint_names;  ///< g1, ... likewise
  std::vector<double> reference;              ///< hypervolume reference for progress (may be empty)
  std::string source;                         ///< "builtin" or the problem file's path
};

/// The problem --problem names: a built-in (ZDT1 ... C2-DTLZ2, case-insensitive; n_variables
/// and n_objectives 0 = the usual sizes) or a problem file (turnfit-problem/1, see
/// turnfit-problem(5)). eval_cmd, when given, evaluates the designs instead (a built-in then
/// lends only its bounds and sizes); timeout_s < 0 takes the file's (default none).
/// Errors: EX_USAGE for an unknown name, EX_NOINPUT for a missing file, EX_DATAERR naming the
/// file and key for a bad one.
LoadedProblem load_problem(const std::string& name_or_file, const std::string& eval_cmd, double timeout_s,
                           size_t n_variables = 0, size_t n_objectives = 0);

}  // namespace turnfit
