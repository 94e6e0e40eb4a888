// Reading and writing field maps: OPAL's RING format and turnfit's own text format.
#pragma once

#include <ostream>
#include <string>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// Map file formats turnfit reads and writes.
enum class MapFormat { psi_ring, turnfit };

/// Parses "psi-ring" or "turnfit" (EX_USAGE otherwise).
MapFormat parse_map_format(const std::string& name);

/// Reads an OPAL TYPE="RING" map (PSI measured-field format, see physics.md): kG on a
/// polar grid, one record per radius. `symmetry` 0 takes the sector count from the grid
/// (360 / (ntheta * dtheta)). Errors name the file and line.
PolarFieldMap parse_psi_ring(const std::string& text, const std::string& name, int symmetry = 0);

/// Reads a turnfit-fieldmap/1 text map (man 5 turnfit-fieldmap).
PolarFieldMap parse_turnfit_map(const std::string& text, const std::string& name);

/// Reads a map file ("-" for stdin) in the given format; symmetry 0 keeps the file's.
PolarFieldMap read_field_map(const std::string& path, MapFormat format, int symmetry = 0);

/// Writes a map in OPAL's RING format (Bz in kG, 9 significant digits; the derivative
/// blocks OPAL skips are written as zeros). Readable by OPAL 2022 and by turnfit.
void write_psi_ring(std::ostream& os, const PolarFieldMap& map);

/// Writes a map in turnfit-fieldmap/1 (values in T with 17 significant digits, so a
/// map read back is bit-identical).
void write_turnfit_map(std::ostream& os, const PolarFieldMap& map);

}  // namespace turnfit
