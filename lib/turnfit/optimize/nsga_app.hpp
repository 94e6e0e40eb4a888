// turnfit-nsga as a library: options, the population log (JSON Lines, also the checkpoint),
// resuming from it, the front, and the run on threads (or MPI, when built with it).
#pragma once

#include <CLI/CLI.hpp>
#include <istream>
#include <ostream>
#include <set>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/optimize/nsga2.hpp"
#include "turnfit/optimize/problem_file.hpp"

namespace turnfit {

/// Everything turnfit-nsga is asked to do.
struct NsgaOptions {
  cli::CommonOptions common;       ///< -o: the population log; --threads, --seed, -q
  std::string problem;             ///< built-in name or problem file
  size_t n_variables = 0;          ///< --variables: size of a built-in (0: its usual)
  size_t n_objectives = 0;         ///< --objectives: of DTLZ2/C2-DTLZ2 (0: 3)
  std::string eval_cmd;            ///< --eval-cmd: evaluate by this shell command
  double timeout_s = -1;           ///< --timeout: per evaluation (<0: the file's, else none)
  Nsga2Settings settings;          ///< population, generations, operators, seed
  std::string front;               ///< --front: the final non-dominated set (JSON)
  std::string resume;              ///< --resume: a population log to continue
  std::vector<double> reference;   ///< --reference: hypervolume reference for progress
};

/// Registers turnfit-nsga's options.
void add_nsga_options(CLI::App& app, NsgaOptions& o);

/// A population log as read back: the run record and the evaluated individuals.
struct PopulationLog {
  nlohmann::json run;                ///< the "run" record (null if the log has none)
  std::vector<Individual> evaluated; ///< every "eval" record, in file order
  std::set<size_t> generations;      ///< the generations a "generation" record reports
  size_t valid_bytes = 0;            ///< length of the complete, valid records (a torn last line is cut)
  bool torn_tail = false;            ///< the last line was incomplete (a killed run)
};

/// Parses a population log (name for messages). A final line without its newline, or one that
/// is not complete JSON, is a record a killed run was writing: dropped (torn_tail). A bad line
/// elsewhere: EX_DATAERR naming file and line.
PopulationLog parse_population_log(const std::string& text, const std::string& name,
                                   const std::vector<std::string>& variable_names);

/// The "eval" record of an individual (one JSON line without the newline).
std::string eval_record(const Individual& ind, const std::vector<std::string>& variable_names);

/// The front as turnfit-nsga writes it: a JSON array of {"id", "x", "f", "violation"} (x an
/// object by variable name, or an array when the problem names none).
nlohmann::json front_json(const std::vector<Individual>& front, const std::vector<std::string>& variable_names);

/// Runs turnfit-nsga; returns the exit code.
int run_nsga(const NsgaOptions& o);

}  // namespace turnfit
