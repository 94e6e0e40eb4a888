// Fuzz target: a problem file (turnfit-problem(5)), loaded as turnfit-nsga, turnfit-localsearch
// and turnfit-diagnose load it. It sits in a folder where "ring8" is the embedded machine's
// folder, so a seed can name "ring8/machine.json" and ring8's measured peaks.
#include <filesystem>

#include "fuzz.hpp"
#include "turnfit/optimize/problem_file.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const bool linked = [] {
    std::filesystem::create_directory_symlink(turnfit::fuzz::ring8_dir(), turnfit::fuzz::work_dir() + "/ring8");
    return true;
  }();
  (void)linked;
  return turnfit::fuzz::guarded(
      [&] { turnfit::load_problem(turnfit::fuzz::as_file(data, size, "problem.json"), "", -1, 0, 0); });
}
