// Fuzz target: a trim coil's phase scan, as turnfit-tc-fit reads it.
#include "fuzz.hpp"
#include "turnfit/trimcoil/tcfit_app.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] { turnfit::read_phase_data(turnfit::fuzz::as_file(data, size, "TC1.csv")); });
}
