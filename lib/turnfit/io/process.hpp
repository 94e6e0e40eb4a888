// Child processes: run a program with text on its stdin, collect stdout and stderr, time it out.
#pragma once

#include <string>
#include <vector>

namespace turnfit {

/// How a child process ended.
struct ProcessResult {
  bool started = false;     ///< false: the program could not be run (spawn_error says why)
  std::string spawn_error;  ///< strerror of the failed spawn (e.g. "No such file or directory")
  bool timed_out = false;   ///< killed (with its process group) after the time limit
  int exit_code = -1;       ///< exit status when it exited, else -1
  int signal = 0;           ///< the signal that ended it, else 0
  std::string out, err;     ///< what it wrote (each cut at max_output bytes)

  /// Exited with status 0 in time.
  bool ok() const { return started && !timed_out && exit_code == 0; }
  /// "exit 3", "signal 11", "timed out after 60 s", or the spawn error.
  std::string describe(double timeout_s) const;
};

/// What to run and how.
struct ProcessSpec {
  std::vector<std::string> argv;  ///< argv[0] is looked up on PATH unless it holds a '/'
  std::string input;              ///< written to its stdin, which is then closed
  double timeout_s = 0;           ///< 0: no limit
  size_t max_output = 16u << 20;  ///< bytes kept of stdout and of stderr each
  bool merge_stderr = false;      ///< stderr into out (err stays empty)
  std::string cwd;                ///< working folder of the child ("" = the caller's)
};

/// Runs a child in its own process group with stdin fed from spec.input and stdout/stderr
/// captured, all through close-on-exec descriptors so concurrent calls from several threads do
/// not leak each other's pipes. Never throws for the child's failures (see ProcessResult); safe
/// against a child that exits without reading its input (no SIGPIPE).
ProcessResult run_process(const ProcessSpec& spec);

/// argv for `/bin/sh -c command` (an evaluator command line as a user writes it).
std::vector<std::string> shell_argv(const std::string& command);

}  // namespace turnfit
