// Constructors for the common error shapes, so messages look the same in every tool.
#include "turnfit/io/error.hpp"

namespace turnfit {

Error data_error(const std::string& file, long line, const std::string& message) {
  std::string where = file.empty() ? std::string("<input>") : file;
  if (line > 0) where += ":" + std::to_string(line);
  return Error(ExitCode::data, where + ": " + message);
}

Error usage_error(const std::string& message) { return Error(ExitCode::usage, message); }

Error open_error(const std::string& file, const std::string& reason) {
  return Error(ExitCode::no_input, file + ": cannot open: " + reason);
}

}  // namespace turnfit
