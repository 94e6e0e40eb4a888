// Fuzz target: a turnfit field map (turnfit-fieldmap(5)).
#include "fuzz.hpp"
#include "turnfit/field/map_io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    turnfit::read_field_map(turnfit::fuzz::as_file(data, size, "field.map"), turnfit::MapFormat::turnfit, 0);
  });
}
