// Fuzz target: a bunch file (particle offsets), read and turned into start states as
// turnfit-track --bunch does, about ring8's injection.
#include "fuzz.hpp"
#include "turnfit/track/bunch.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    const turnfit::BunchFile file = turnfit::read_bunch_file(turnfit::fuzz::as_file(data, size, "bunch.csv"));
    turnfit::Injection inj;
    inj.energy_MeV = 72;
    inj.r_mm = 2045;
    turnfit::offset_states(inj, 938.27208816, 50.65, file);
  });
}
