// Stop-signal handling: fixed tables the handler reads without locks or allocation.
#include "turnfit/io/interrupt.hpp"

#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>

namespace turnfit {
namespace {

constexpr int kPaths = 256, kGroups = 64, kPathBytes = 4096;

// A path slot is written while its state is 1 (being filled) and read by the handler only in
// state 2, so the handler never reads a half-written path.
char g_paths[kPaths][kPathBytes];
std::atomic<int> g_path_state[kPaths];
std::atomic<pid_t> g_groups[kGroups];

void on_stop(int sig) {
  const int saved = errno;
  for (auto& g : g_groups) {
    const pid_t p = g.load();
    if (p > 0) ::kill(-p, SIGTERM);
  }
  for (int i = 0; i < kPaths; ++i)
    if (g_path_state[i].load() == 2) ::unlink(g_paths[i]);
  for (int i = 0; i < kPaths; ++i)  // folders, now that their files are gone
    if (g_path_state[i].load() == 2) ::rmdir(g_paths[i]);
  errno = saved;
  ::signal(sig, SIG_DFL);
  ::raise(sig);
}

// The signals that stop a tool (turnfit(1), SIGNALS), and the same as a set.
constexpr int kStopSignals[] = {SIGINT, SIGTERM, SIGHUP};
sigset_t stop_signals() {
  sigset_t set;
  sigemptyset(&set);
  for (int sig : kStopSignals) sigaddset(&set, sig);
  return set;
}

}  // namespace

void install_stop_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_stop;
  sa.sa_mask = stop_signals();  // one stop at a time
  for (int sig : kStopSignals) {
    // A signal the caller ignores (nohup, a background job's SIGINT) stays ignored.
    struct sigaction old {};
    if (::sigaction(sig, nullptr, &old) == 0 && old.sa_handler == SIG_IGN) continue;
    ::sigaction(sig, &sa, nullptr);
  }
}

StopSignalsHeld::StopSignalsHeld() {
  const sigset_t stops = stop_signals();
  ::pthread_sigmask(SIG_BLOCK, &stops, &old_);
}

StopSignalsHeld::~StopSignalsHeld() { ::pthread_sigmask(SIG_SETMASK, &old_, nullptr); }

StopCleanup StopCleanup::path(const std::string& path) {
  StopCleanup c;
  if (path.empty() || path.size() >= static_cast<size_t>(kPathBytes)) return c;
  for (int i = 0; i < kPaths; ++i) {
    int free_state = 0;
    if (!g_path_state[i].compare_exchange_strong(free_state, 1)) continue;
    std::memcpy(g_paths[i], path.c_str(), path.size() + 1);
    g_path_state[i].store(2);
    c.slot_ = i;
    return c;
  }
  return c;
}

StopCleanup StopCleanup::group(pid_t pgid) {
  StopCleanup c;
  c.is_group_ = true;
  for (int i = 0; i < kGroups && pgid > 0; ++i) {
    pid_t free_slot = 0;
    if (g_groups[i].compare_exchange_strong(free_slot, pgid)) {
      c.slot_ = i;
      break;
    }
  }
  return c;
}

StopCleanup::StopCleanup(StopCleanup&& other) noexcept : slot_(other.slot_), is_group_(other.is_group_) {
  other.slot_ = -1;
}

StopCleanup& StopCleanup::operator=(StopCleanup&& other) noexcept {
  if (this != &other) {
    release();
    slot_ = other.slot_;
    is_group_ = other.is_group_;
    other.slot_ = -1;
  }
  return *this;
}

StopCleanup::~StopCleanup() { release(); }

void StopCleanup::release() {
  if (slot_ < 0) return;
  if (is_group_) g_groups[slot_].store(0);
  else g_path_state[slot_].store(0);
  slot_ = -1;
}

}  // namespace turnfit
