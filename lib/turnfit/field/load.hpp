// Building the main field of a machine from its description.
#pragma once

#include "turnfit/field/field_map.hpp"
#include "turnfit/machine/machine.hpp"

namespace turnfit {

/// Reads the machine's field map (resolved path, format, symmetry) and applies its scale.
PolarFieldMap load_main_field(const Machine& m);

/// A copy of map with every value multiplied by factor.
PolarFieldMap scaled(const PolarFieldMap& map, double factor);

}  // namespace turnfit
