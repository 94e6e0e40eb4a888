// Child processes through posix_spawn: stdin from a socket (no SIGPIPE), stdout and stderr
// through pipes, all read and written in one poll loop with a deadline.
#include "turnfit/io/process.hpp"

#include "turnfit/io/interrupt.hpp"

#include <fcntl.h>
#include <poll.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstring>

#include "turnfit/cli/common.hpp"

extern char** environ;

namespace turnfit {

std::string ProcessResult::describe(double timeout_s) const {
  if (!started) return "cannot run: " + spawn_error;
  if (timed_out) return "timed out after " + cli::fmt(timeout_s, 6) + " s";
  if (signal) return "killed by signal " + std::to_string(signal) + " (" + strsignal(signal) + ")";
  return "exit " + std::to_string(exit_code);
}

std::vector<std::string> shell_argv(const std::string& command) { return {"/bin/sh", "-c", command}; }

namespace {

struct Fd {
  int fd = -1;
  ~Fd() { reset(); }
  void reset() {
    if (fd >= 0) ::close(fd);
    fd = -1;
  }
};

}  // namespace

ProcessResult run_process(const ProcessSpec& spec) {
  ProcessResult res;
  if (spec.argv.empty()) {
    res.spawn_error = "empty command";
    return res;
  }
  // stdin: a socket pair, so writing to a child that is gone gives EPIPE (MSG_NOSIGNAL), not
  // a SIGPIPE that would kill the caller. Every descriptor is close-on-exec: another thread's
  // child must not inherit them (or this child's EOF would wait for that one to exit).
  int in_pair[2], out_pipe[2], err_pipe[2];
  if (::socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, in_pair) != 0) {
    res.spawn_error = std::string("socketpair: ") + std::strerror(errno);
    return res;
  }
  Fd in_w{in_pair[0]}, in_r{in_pair[1]};
  if (::pipe2(out_pipe, O_CLOEXEC) != 0) {
    res.spawn_error = std::string("pipe: ") + std::strerror(errno);
    return res;
  }
  Fd out_r{out_pipe[0]}, out_w{out_pipe[1]};
  if (::pipe2(err_pipe, O_CLOEXEC) != 0) {
    res.spawn_error = std::string("pipe: ") + std::strerror(errno);
    return res;
  }
  Fd err_r{err_pipe[0]}, err_w{err_pipe[1]};
  ::shutdown(in_r.fd, SHUT_WR);

  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_adddup2(&fa, in_r.fd, 0);
  posix_spawn_file_actions_adddup2(&fa, out_w.fd, 1);
  posix_spawn_file_actions_adddup2(&fa, spec.merge_stderr ? out_w.fd : err_w.fd, 2);
  if (!spec.cwd.empty()) posix_spawn_file_actions_addchdir_np(&fa, spec.cwd.c_str());
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  posix_spawnattr_setpgroup(&attr, 0);  // its own group: a timeout kills the shell's children too
  sigset_t none, dfl;
  sigemptyset(&none);
  sigemptyset(&dfl);
  sigaddset(&dfl, SIGPIPE);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setsigdefault(&attr, &dfl);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETPGROUP | POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETSIGDEF);
  std::vector<std::string> args = spec.argv;
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  pid_t pid = 0;
  int rc = 0;
  // A stop signal to the tool stops the child's group too (it is a group of its own, which a
  // terminal's ^C does not reach); none may fall between the spawn and the registration. The
  // child starts with no signal blocked (its attributes set the mask).
  StopCleanup stop_child;
  {
    const StopSignalsHeld held;
    rc = args[0].find('/') == std::string::npos
             ? posix_spawnp(&pid, args[0].c_str(), &fa, &attr, argv.data(), environ)
             : posix_spawn(&pid, args[0].c_str(), &fa, &attr, argv.data(), environ);
    if (rc == 0) stop_child = StopCleanup::group(pid);
  }
  posix_spawn_file_actions_destroy(&fa);
  posix_spawnattr_destroy(&attr);
  in_r.reset();
  out_w.reset();
  err_w.reset();
  if (rc != 0) {
    res.spawn_error = std::strerror(rc);
    return res;
  }
  res.started = true;

  size_t written = 0;
  if (spec.input.empty()) in_w.reset();
  const auto start = std::chrono::steady_clock::now();
  char buf[65536];
  while (out_r.fd >= 0 || err_r.fd >= 0 || in_w.fd >= 0) {
    int wait_ms = -1;
    if (spec.timeout_s > 0) {
      const double left =
          spec.timeout_s - std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      if (left <= 0) {
        res.timed_out = true;
        ::kill(-pid, SIGKILL);
        break;
      }
      wait_ms = static_cast<int>(left * 1000.0) + 1;
    }
    pollfd pfd[3];
    int n = 0, i_in = -1, i_out = -1, i_err = -1;
    if (in_w.fd >= 0) pfd[i_in = n++] = {in_w.fd, POLLOUT, 0};
    if (out_r.fd >= 0) pfd[i_out = n++] = {out_r.fd, POLLIN, 0};
    if (err_r.fd >= 0) pfd[i_err = n++] = {err_r.fd, POLLIN, 0};
    const int pr = ::poll(pfd, static_cast<nfds_t>(n), wait_ms);
    if (pr < 0) {
      if (errno == EINTR) continue;
      break;
    }
    if (pr == 0) continue;
    if (i_in >= 0 && pfd[i_in].revents) {
      const ssize_t w = ::send(in_w.fd, spec.input.data() + written, spec.input.size() - written,
                               MSG_NOSIGNAL | MSG_DONTWAIT);
      if (w > 0) written += static_cast<size_t>(w);
      if ((w < 0 && errno != EAGAIN && errno != EINTR) || written == spec.input.size()) in_w.reset();
    }
    auto drain = [&](int idx, Fd& fd, std::string& dst) {
      if (idx < 0 || !pfd[idx].revents) return;
      const ssize_t r = ::read(fd.fd, buf, sizeof buf);
      if (r > 0) {
        const size_t keep = std::min(static_cast<size_t>(r), spec.max_output - std::min(spec.max_output, dst.size()));
        dst.append(buf, keep);
      } else if (r == 0 || (errno != EINTR && errno != EAGAIN)) {
        fd.reset();
      }
    };
    drain(i_out, out_r, res.out);
    drain(i_err, err_r, res.err);
  }
  // The child may still run with its output closed: wait for it within the same deadline.
  int status = 0;
  for (;;) {
    const pid_t w = ::waitpid(pid, &status, res.timed_out || spec.timeout_s <= 0 ? 0 : WNOHANG);
    if (w == pid) break;
    if (w < 0 && errno != EINTR) break;
    if (w == 0) {
      if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() >= spec.timeout_s) {
        res.timed_out = true;
        ::kill(-pid, SIGKILL);
      } else {
        ::usleep(2000);
      }
    }
  }
  if (!res.timed_out) {
    if (WIFEXITED(status)) res.exit_code = WEXITSTATUS(status);
    else if (WIFSIGNALED(status)) res.signal = WTERMSIG(status);
  }
  return res;
}

}  // namespace turnfit
