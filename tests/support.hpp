// Helpers for tests: where the shared reference data is, and skipping when it is absent.
#pragma once

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <sys/stat.h>

#include "turnfit/io/error.hpp"

namespace turnfit::test {

/// The shared data folder (env TURNFIT_SHARED overrides the build-time default).
inline std::string shared_dir() {
  if (const char* env = std::getenv("TURNFIT_SHARED")) return env;
  return TURNFIT_SHARED_DIR;
}

/// Path of a file below shared/, or "" if it does not exist.
inline std::string shared_file(const std::string& rel) {
  std::string p = shared_dir() + "/" + rel;
  struct stat st {};
  return ::stat(p.c_str(), &st) == 0 ? p : std::string();
}

/// A file in tests/data.
inline std::string test_file(const std::string& rel) {
  return std::string(TURNFIT_TEST_DIR) + "/data/" + rel;
}

/// Runs f; the exit code of the turnfit::Error it throws (0 if none), its message in *msg.
inline int error_code(const std::function<void()>& f, std::string* msg = nullptr) {
  try {
    f();
  } catch (const Error& e) {
    if (msg) *msg = e.what();
    return static_cast<int>(e.code());
  }
  return 0;
}

/// A fresh folder under /tmp, removed with everything in it when the object goes.
struct TempDir {
  std::string path;
  TempDir() {
    char name[] = "/tmp/turnfit-test.XXXXXX";
    if (!::mkdtemp(name)) throw std::runtime_error("mkdtemp failed");
    path = name;
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  /// Writes text to name inside the folder; returns its path.
  std::string file(const std::string& name, const std::string& text) const {
    const std::string p = path + "/" + name;
    std::ofstream(p) << text;
    return p;
  }
};

/// Whether a missing `what` ("shared", "gnuplot", "mpi") fails a test instead of skipping it:
/// shared data under CI=true (CI has it), and whatever the build requires (CMake's
/// TURNFIT_TEST_REQUIRE_BUILD: gnuplot and MPI in the build the README makes, where they are
/// dependencies; the environment variable TURNFIT_TEST_REQUIRE overrides it).
inline bool required(const std::string& what) {
  const char* ci = std::getenv("CI");
  if (what == "shared" && ci && std::string(ci) == "true") return true;
  const char* req = std::getenv("TURNFIT_TEST_REQUIRE");
  if (!req) req = TURNFIT_TEST_REQUIRE_BUILD;
  const std::string list = std::string(",") + req + ",";
  return list.find("," + what + ",") != std::string::npos;
}

}  // namespace turnfit::test

/// Skips the current Catch2 test: prints the line ctest's SKIP_REGULAR_EXPRESSION turns into
/// "Skipped" (tests/CMakeLists.txt), then returns; when `what` is required (see required()),
/// fails instead. Catch2 2.13 has no skip of its own, and a bare return would report Passed.
#define TURNFIT_SKIP_TEST(what, message)                                                   \
  do {                                                                                     \
    std::ostringstream turnfit_skip_msg_;                                                  \
    turnfit_skip_msg_ << message;                                                          \
    if (turnfit::test::required(what))                                                     \
      FAIL("missing " << (what) << ", which this build requires: " << turnfit_skip_msg_.str()); \
    std::cout << "TURNFIT_SKIPPED: " << turnfit_skip_msg_.str() << std::endl;              \
    return;                                                                                \
  } while (0)

/// Skips the current Catch2 test when shared data is missing (a failure under CI=true).
#define TURNFIT_REQUIRE_SHARED(var, rel)                                                   \
  const std::string var = turnfit::test::shared_file(rel);                                \
  if (var.empty())                                                                         \
    TURNFIT_SKIP_TEST("shared", "shared data " << rel << " not found under "              \
                                               << turnfit::test::shared_dir())
