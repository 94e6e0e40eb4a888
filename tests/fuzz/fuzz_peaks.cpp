// Fuzz target: a peaks table (turnfit-peakfind's output), as the matching tools read measured turns.
#include "fuzz.hpp"
#include "turnfit/optimize/turn_problem.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded(
      [&] { turnfit::read_measured_turns({turnfit::fuzz::as_file(data, size, "peaks.csv")}); });
}
