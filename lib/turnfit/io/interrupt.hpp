// Clean stops (issue 18): SIGINT, SIGTERM and SIGHUP end a tool without leaving temporaries or
// orphaned children behind, and with the signal's own status (a shell sees 130, 143, 129).
#pragma once

#include <signal.h>
#include <sys/types.h>

#include <string>

namespace turnfit {

/// Installs the handlers (run_tool does, for every tool). On a stop signal the handler removes
/// every registered path (files first, then folders, which must be empty by then), sends SIGTERM
/// to every registered child process group, restores the default action and raises the signal
/// again, so that the tool ends as interrupted. Everything it does is async-signal-safe.
void install_stop_handlers();

/// Holds SIGINT, SIGTERM and SIGHUP back on this thread while it lives (they are delivered when it
/// ends): wrap the creation of a temporary or a child and its registration in one, so that no
/// stop falls between the two.
class StopSignalsHeld {
 public:
  StopSignalsHeld();
  ~StopSignalsHeld();
  StopSignalsHeld(const StopSignalsHeld&) = delete;
  StopSignalsHeld& operator=(const StopSignalsHeld&) = delete;

 private:
  sigset_t old_;
};

/// What a stop removes or stops while it is registered: a temporary path (an output's temporary
/// before its rename, a private folder) or a child's process group. Unregistered when destroyed.
/// At most 256 paths and 64 groups are registered at once; more are not tracked (and then left
/// behind by a stop, as without the handler).
class StopCleanup {
 public:
  /// Registers a path (at most 4095 bytes).
  static StopCleanup path(const std::string& path);
  /// Registers a child's process group (its pid, the group's leader).
  static StopCleanup group(pid_t pgid);
  StopCleanup() = default;
  StopCleanup(StopCleanup&& other) noexcept;
  StopCleanup& operator=(StopCleanup&& other) noexcept;
  StopCleanup(const StopCleanup&) = delete;
  StopCleanup& operator=(const StopCleanup&) = delete;
  ~StopCleanup();
  /// Unregisters now (the path was renamed into place, the child was reaped).
  void release();

 private:
  int slot_ = -1;
  bool is_group_ = false;
};

}  // namespace turnfit
