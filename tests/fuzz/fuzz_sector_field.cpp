// Fuzz target: a sector-field spec (turnfit-sector-field(5)), read and validated as
// turnfit-orbit --sector-field reads it, then sampled into a map when its grid is small (a large
// grid is valid but slow to sample, which is not what this target looks for).
#include "fuzz.hpp"
#include "turnfit/field/sector_field.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    const turnfit::SectorFieldSpec spec = turnfit::read_sector_spec(turnfit::fuzz::as_file(data, size, "spec.json"));
    if (static_cast<long>(spec.grid.nr) * spec.grid.ntheta <= 20000) turnfit::make_sector_field(spec);
  });
}
