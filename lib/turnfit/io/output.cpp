// Atomic output files (temp + rename) and checked writes to stdout.
#include "turnfit/io/output.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <vector>

#include "turnfit/io/error.hpp"

namespace turnfit {

OutputFile::OutputFile(const std::string& path) : path_(path.empty() ? "-" : path) {
  if (path_ == "-") return;
  std::vector<char> name(path_.begin(), path_.end());
  const char suffix[] = ".tmp.XXXXXX";
  name.insert(name.end(), suffix, suffix + sizeof suffix);  // includes the NUL
  int fd = ::mkstemp(name.data());
  if (fd < 0) throw Error(ExitCode::cant_create, path_ + ": cannot create: " + std::strerror(errno));
  ::close(fd);
  tmp_ = name.data();
  file_ = std::make_unique<std::ofstream>(tmp_, std::ios::binary | std::ios::trunc);
  if (!*file_) {
    std::remove(tmp_.c_str());
    throw Error(ExitCode::cant_create, path_ + ": cannot create: " + std::strerror(errno));
  }
}

OutputFile::~OutputFile() {
  if (!committed_ && !tmp_.empty()) {
    file_.reset();
    std::remove(tmp_.c_str());
  }
}

std::ostream& OutputFile::stream() { return file_ ? static_cast<std::ostream&>(*file_) : std::cout; }

void OutputFile::commit() {
  if (committed_) return;
  if (!file_) {
    std::cout.flush();
    if (!std::cout) throw Error(ExitCode::io, "<stdout>: write error");
    committed_ = true;
    return;
  }
  file_->flush();
  bool ok = static_cast<bool>(*file_);
  file_->close();
  if (!ok || file_->fail()) throw Error(ExitCode::io, path_ + ": write error");
  // Keep the usual permissions of a new file (mkstemp makes it 0600).
  mode_t mask = ::umask(0);
  ::umask(mask);
  ::chmod(tmp_.c_str(), 0666 & ~mask);
  if (std::rename(tmp_.c_str(), path_.c_str()) != 0)
    throw Error(ExitCode::cant_create, path_ + ": cannot rename into place: " + std::strerror(errno));
  committed_ = true;
}

void write_output(const std::string& path, const std::string& content) {
  OutputFile out(path);
  out.stream() << content;
  out.commit();
}

}  // namespace turnfit
