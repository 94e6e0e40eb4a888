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
  // A device or a FIFO (/dev/null, a named pipe) is written in place: renaming over it would
  // replace it with a regular file. A symbolic link is followed, so the link stays a link.
  std::string target = path_;
  struct stat st {};
  // Decide by what the path finally is (stat follows links: /dev/stdout may be a pipe).
  // Descriptor aliases are written through, so a shell's ">>" keeps what the file held.
  const bool fd_alias = path_.rfind("/dev/std", 0) == 0 || path_.rfind("/dev/fd/", 0) == 0 ||
                        path_.rfind("/proc/self/fd/", 0) == 0;
  if (::stat(path_.c_str(), &st) == 0 && (fd_alias || !S_ISREG(st.st_mode))) {
    if (S_ISDIR(st.st_mode)) throw Error(ExitCode::cant_create, path_ + ": cannot create: is a directory");
    file_ = std::make_unique<std::ofstream>(path_, std::ios::binary | std::ios::app);
    if (!*file_) throw Error(ExitCode::cant_create, path_ + ": cannot open: " + std::strerror(errno));
    direct_ = true;
    return;
  }
  for (int hops = 0; hops < 16 && ::lstat(target.c_str(), &st) == 0 && S_ISLNK(st.st_mode); ++hops) {
    std::vector<char> buf(4096);
    const ssize_t n = ::readlink(target.c_str(), buf.data(), buf.size() - 1);
    if (n <= 0) break;
    std::string next(buf.data(), static_cast<size_t>(n));
    if (next.front() != '/') {  // relative to the link's folder
      const auto slash = target.rfind('/');
      if (slash != std::string::npos) next = target.substr(0, slash + 1) + next;
    }
    target = next;
  }
  final_ = target;
  std::vector<char> name(target.begin(), target.end());
  const char suffix[] = ".tmp.XXXXXX";
  name.insert(name.end(), suffix, suffix + sizeof suffix);  // includes the NUL
  {
    const StopSignalsHeld held;  // no stop between the temporary's creation and its registration
    const int fd = ::mkstemp(name.data());
    if (fd < 0) throw Error(ExitCode::cant_create, path_ + ": cannot create: " + std::strerror(errno));
    ::close(fd);
    tmp_ = name.data();
    stop_ = StopCleanup::path(tmp_);
  }
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
  if (direct_) {
    committed_ = true;
    return;
  }
  // Keep the usual permissions of a new file (mkstemp makes it 0600).
  mode_t mask = ::umask(0);
  ::umask(mask);
  ::chmod(tmp_.c_str(), 0666 & ~mask);
  if (std::rename(tmp_.c_str(), final_.c_str()) != 0)
    throw Error(ExitCode::cant_create, path_ + ": cannot rename into place: " + std::strerror(errno));
  stop_.release();
  committed_ = true;
}

void write_output(const std::string& path, const std::string& content) {
  OutputFile out(path);
  out.stream() << content;
  out.commit();
}

}  // namespace turnfit
