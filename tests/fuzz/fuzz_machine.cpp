// Fuzz target: a machine file (turnfit-machine(5): field, cavities, trim coils, probes, bunch,
// effects, design variables), parsed and validated as every tool loads one. Paths in it resolve
// from ring8's folder, so the shipped machine is a seed that validates.
#include "fuzz.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/machine/machine.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    const std::string text(reinterpret_cast<const char*>(data), size);
    turnfit::machine_from_json(turnfit::parse_json(text, "machine.json"), "machine.json", turnfit::fuzz::ring8_dir());
  });
}
