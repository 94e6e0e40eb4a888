// Fuzz target: a design-variable file (--dvars), applied to ring8's machine as the tools do.
#include "fuzz.hpp"
#include "turnfit/machine/machine.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const turnfit::Machine ring8 = turnfit::load_machine(turnfit::fuzz::ring8_dir() + "/machine.json");
  return turnfit::fuzz::guarded([&] {
    turnfit::Machine m = ring8;
    turnfit::apply_dvars_file(m, turnfit::fuzz::as_file(data, size, "dvars.json"));
  });
}
