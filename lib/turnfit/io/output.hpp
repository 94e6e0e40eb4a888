// Atomic outputs: results go to a temporary file that is renamed into place on success.
#pragma once

#include <fstream>
#include <memory>
#include <ostream>
#include <string>

#include "turnfit/io/interrupt.hpp"

namespace turnfit {

/// An output that is either stdout ("-" or empty path) or a file written atomically:
/// data goes to a temporary file in the same folder, renamed to the final path by
/// commit(). Destroyed without commit(), it removes the temporary, so an interrupted
/// or failed run never leaves a half-written result. Devices and FIFOs are written in place;
/// symbolic links are followed.
class OutputFile {
 public:
  /// Opens the output (EX_CANTCREAT if the temporary cannot be created).
  explicit OutputFile(const std::string& path);
  ~OutputFile();
  OutputFile(const OutputFile&) = delete;
  OutputFile& operator=(const OutputFile&) = delete;

  /// The stream to write to.
  std::ostream& stream();
  /// Flushes, checks for write errors (EX_IOERR) and renames into place.
  void commit();
  /// The final path ("-" for stdout).
  const std::string& path() const { return path_; }
  /// The temporary being written ("" for stdout, a device or a FIFO). Another process may
  /// write it (turnfit-plot's gnuplot); commit() then renames what it wrote into place.
  const std::string& temp_path() const { return tmp_; }

 private:
  std::string path_;
  std::string final_;  ///< where the temporary is renamed to (a symlink's target)
  std::string tmp_;
  bool direct_ = false;  ///< writing straight into a device or FIFO
  std::unique_ptr<std::ofstream> file_;
  bool committed_ = false;
  StopCleanup stop_;  ///< a stop signal removes the temporary
};

/// Writes a whole string to path atomically (or to stdout for "-").
void write_output(const std::string& path, const std::string& content);

}  // namespace turnfit
