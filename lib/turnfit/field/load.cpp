// Main-field construction from the machine file.
#include "turnfit/field/load.hpp"

#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"

namespace turnfit {

PolarFieldMap scaled(const PolarFieldMap& map, double factor) {
  if (factor == 1.0) return map;
  std::vector<double> v = map.values();
  for (double& x : v) x *= factor;
  return PolarFieldMap(map.grid(), std::move(v), map.label());
}

PolarFieldMap load_main_field(const Machine& m) {
  if (m.field.map.empty())
    throw data_error(m.path, 0, "/field/map: the machine has no field map");
  PolarFieldMap map = read_field_map(m.field.map, parse_map_format(m.field.format), m.field.symmetry);
  return scaled(map, m.field.scale);
}

}  // namespace turnfit
