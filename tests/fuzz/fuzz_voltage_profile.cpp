// Fuzz target: a cavity's voltage profile (OPAL's rffield format), as a machine's cavities read it.
#include "fuzz.hpp"
#include "turnfit/rf/cavity.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded(
      [&] { turnfit::VoltageProfile::read(turnfit::fuzz::as_file(data, size, "rffield.dat")); });
}
