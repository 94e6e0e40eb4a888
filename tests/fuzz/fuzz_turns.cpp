// Fuzz target: a turns table (turnfit-track's output, or peaks), as turnfit-compare reads either.
#include "fuzz.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/metrics/metrics.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return turnfit::fuzz::guarded([&] {
    turnfit::turn_table_from_csv(turnfit::CsvTable::read(turnfit::fuzz::as_file(data, size, "turns.csv")));
  });
}
