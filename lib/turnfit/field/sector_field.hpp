// Analytic separated-sector cyclotron fields: N sector magnets with smooth (tanh) edges, sector
// width and spiral as functions of radius, and a radial hill-field profile, sampled onto a polar
// grid (issue 4: the PSI-Ring-like default machine is built from this).
#pragma once

#include <vector>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// A function of radius given at nodes, linear between them and constant beyond the ends.
struct RadialTable {
  std::vector<double> r_mm;
  std::vector<double> value;
  /// The value at r [mm] (the only node's value for a one-node table).
  double at(double r_mm) const;
};

/// What a separated-sector field looks like. Field: B(r, theta) = B_hill(r) [v + (1 - v) S],
/// with S in [0, 1] the sector shape: 1 inside a magnet, 0 in the valleys, edges
/// S = (1 + tanh(d / lambda)) / 2 in the distance d [mm] along the arc from the edge.
struct SectorFieldSpec {
  int sectors = 8;
  /// Magnet width at each radius [deg of azimuth].
  RadialTable width_deg;
  /// Hill field B_hill(r) [T] (the field inside a magnet, far from its edges).
  RadialTable hill_T;
  double fringe_mm = 40;       ///< lambda: edge length (about half the magnet gap)
  double valley_fraction = 0;  ///< v = B_valley / B_hill
  /// Spiral angle xi [deg]: the magnet centre line is the logarithmic spiral
  /// theta_c(r) = tan(xi) ln(r / spiral_r0) (constant angle xi to the radial direction).
  double spiral_deg = 0;
  double spiral_r0_mm = 1000;
  /// The grid to sample on (one sector: theta_min .. theta_min + 360/N).
  PolarGrid grid;
};

/// The sector shape S(r, theta) in [0, 1] (sector 1 centred on theta_c(r), periodic in 360/N);
/// EX_DATAERR-free: the caller validates the spec with validate_sector_spec().
double sector_shape(const SectorFieldSpec& spec, double r_mm, double theta_deg);

/// Checks a spec (sectors >= 1, widths in (0, 360/N), positive edge length, valley fraction in
/// [0, 1], tables of equal length with increasing radii, a usable grid); EX_DATAERR naming the
/// field at fault.
void validate_sector_spec(const SectorFieldSpec& spec);

/// Samples the field onto spec.grid as a map (values in T).
PolarFieldMap make_sector_field(const SectorFieldSpec& spec);

}  // namespace turnfit
