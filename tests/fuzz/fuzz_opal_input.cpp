// Fuzz target: an OPAL-cycl input, as turnfit-import-opal reads it (the language, the import and
// the machine it writes), without touching the file system.
#include "fuzz.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/opal/opal_io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    const std::string text(reinterpret_cast<const char*>(data), size);
    const turnfit::OpalImport r = turnfit::import_opal(text, "fuzz.in", "", "", turnfit::kDefaultOpalVersion, false);
    turnfit::machine_from_json(r.machine, "fuzz.in (imported machine)", "");
  });
}
