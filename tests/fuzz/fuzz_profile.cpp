// Fuzz target: a probe profile (CSV with the wire's readings), as turnfit-peakfind reads it.
#include "fuzz.hpp"
#include "turnfit/peaks/peaks.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] { turnfit::read_profile(turnfit::fuzz::as_file(data, size, "profile.csv")); });
}
