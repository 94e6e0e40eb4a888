// Fuzz target: an OPAL RING field map (PSI's CARBONCYCL format), as machines with
// "format": "psi-ring" read it.
#include "fuzz.hpp"
#include "turnfit/field/map_io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    turnfit::read_field_map(turnfit::fuzz::as_file(data, size, "bfield.dat"), turnfit::MapFormat::psi_ring, 0);
  });
}
