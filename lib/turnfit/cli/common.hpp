// The option block, error mapping and provenance that every turnfit tool shares.
#pragma once

#include <CLI/CLI.hpp>
#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace turnfit::cli {

/// Options every tool understands (samtools-style global options).
struct CommonOptions {
  std::string output = "-";   ///< -o: output path, "-" for stdout
  std::string format;         ///< --format: output format (tool-specific choices)
  bool quiet = false;         ///< -q: no warnings or progress on stderr
  unsigned threads = 0;       ///< --threads: 0 means all cores
  std::uint64_t seed = 1;     ///< --seed: random seed, for tools that draw numbers
  bool no_provenance = false; ///< --no-provenance: leave out tool/version/argv records
};

/// Which of the shared options a tool offers (-q and --no-provenance always).
enum Shared : unsigned {
  kOutput = 1u << 0,
  kFormat = 1u << 1,
  kThreads = 1u << 2,
  kSeed = 1u << 3,
};

/// Adds the shared options to app; `formats` lists the allowed --format values
/// (the first is the default).
void add_common_options(CLI::App& app, CommonOptions& opts, unsigned which,
                        const std::vector<std::string>& formats = {});

/// Runs a tool: parses argv (help and version exit 0, usage errors exit 64), then
/// calls body and maps turnfit::Error and other exceptions to sysexits codes with
/// "turnfit-<tool>: message" on stderr. Also records the invocation for provenance.
int run_tool(const std::string& tool, CLI::App& app, int argc, char** argv,
             const std::function<int()>& body);

/// Number of worker threads to use for a --threads value (0 = all cores, at least 1).
unsigned resolve_threads(unsigned requested);

/// {"tool", "version", "argv"} of this run (empty object if none was recorded).
nlohmann::json provenance();
/// The provenance as '#' comment lines for CSV outputs.
std::string provenance_comment();

/// Prints a warning on stderr unless quiet.
void warn(const CommonOptions& opts, const std::string& message);

/// Whether stderr is a terminal (progress bars only then).
bool stderr_is_tty();

/// Formats x with at most `digits` significant digits and no trailing noise.
std::string fmt(double x, int digits = 10);

}  // namespace turnfit::cli
