// Fuzz target: a population log (turnfit-population(5)), as turnfit-nsga --resume reads it, for
// a problem with named variables and for one without.
#include "fuzz.hpp"
#include "turnfit/optimize/nsga_app.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  turnfit::fuzz::guarded([&] { turnfit::parse_population_log(text, "run.log", {}); });
  return turnfit::fuzz::guarded([&] { turnfit::parse_population_log(text, "run.log", {"x0", "x1"}); });
}
