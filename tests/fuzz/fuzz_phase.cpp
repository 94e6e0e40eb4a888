// Fuzz target: a trim coil's phase scan, as turnfit-tc-fit reads it. The reader keeps a coil's
// error beside the coil (tc-fit fits the others and names it); such an error is a refusal.
#include "fuzz.hpp"
#include "turnfit/trimcoil/tcfit_app.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    for (const turnfit::PhaseData& d : turnfit::read_phase_data(turnfit::fuzz::as_file(data, size, "TC1.csv")))
      if (!d.error.empty()) throw turnfit::Error(turnfit::ExitCode::data, d.error);
  });
}
