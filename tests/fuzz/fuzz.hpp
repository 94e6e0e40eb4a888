// What every fuzz target shares: the rule that tells a refusal from a bug, and inputs as files.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <exception>
#include <new>
#include <string>

#include "turnfit/io/error.hpp"

namespace turnfit::fuzz {

/// Reports a bug (libFuzzer and the replay both take an abort as one) with what was thrown.
[[noreturn]] void bug(const std::string& what);

/// Set by guarded() when a reader refused its input (the replay checks that a regression input
/// is still refused and a seed still accepted; libFuzzer ignores it).
inline bool refused = false;

/// Runs one input through a reader. A refusal is the reader doing its job: a turnfit::Error
/// with a user's exit code (64, 65, 66) and a message. Anything else is a bug: another
/// exception (a library's own, which a tool would report as "internal error", exit 70), an
/// internal code, an empty message.
template <class F>
int guarded(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    refused = true;
    const int code = static_cast<int>(e.code());
    if (code != 64 && code != 65 && code != 66) bug("exit " + std::to_string(code) + ": " + e.what());
    if (std::string(e.what()).empty()) bug("a refusal without a message");
  } catch (const std::bad_alloc&) {
    bug("out of memory (a limit is missing)");
  } catch (const std::exception& e) {
    bug(std::string("internal error: ") + e.what());
  }
  return 0;
}

/// The input written to `name` in this process's private temporary folder (the readers take
/// paths, as the tools do), and that path.
std::string as_file(const std::uint8_t* data, std::size_t size, const std::string& name);

/// The private temporary folder (made on first use, removed at exit).
const std::string& work_dir();

/// The embedded default machine's folder in the source tree (share/turnfit/ring8).
std::string ring8_dir();

}  // namespace turnfit::fuzz
