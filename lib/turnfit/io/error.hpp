// Errors that carry a sysexits exit code and, where known, the file and line at fault.
#pragma once

#include <stdexcept>
#include <string>

namespace turnfit {

/// Exit codes of every tool, from <sysexits.h> (style.md).
enum class ExitCode : int {
  ok = 0,
  usage = 64,        ///< EX_USAGE: bad command line
  data = 65,         ///< EX_DATAERR: input data is malformed or out of range
  no_input = 66,     ///< EX_NOINPUT: an input file cannot be opened
  unavailable = 69,  ///< EX_UNAVAILABLE: a program the tool needs (gnuplot) is missing
  software = 70,     ///< EX_SOFTWARE: internal error
  cant_create = 73,  ///< EX_CANTCREAT: an output file cannot be created
  io = 74,           ///< EX_IOERR: a read or write failed
};

/// An error a tool reports to its user and maps to an exit code.
/// The message is complete ("file:line: what is wrong"); tools print it as is.
class Error : public std::runtime_error {
 public:
  /// An error with an exit code and a complete message.
  Error(ExitCode code, const std::string& message)
      : std::runtime_error(message), code_(code) {}
  /// The exit code the tool should return.
  ExitCode code() const { return code_; }

 private:
  ExitCode code_;
};

/// A malformed-input error "file:line: message" (line 0 leaves the line out).
Error data_error(const std::string& file, long line, const std::string& message);
/// A usage error (bad option value).
Error usage_error(const std::string& message);
/// "file: cannot open: <strerror>" with EX_NOINPUT.
Error open_error(const std::string& file, const std::string& reason);

}  // namespace turnfit
