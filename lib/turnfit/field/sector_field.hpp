// Analytic separated-sector cyclotron fields: N sector magnets with smooth (tanh) edges, sector
// width and spiral as functions of radius, and a radial hill-field profile, sampled onto a polar
// grid; read from and written to turnfit-sector-field/1 JSON (the PSI-Ring-like default machine
// ring8 is built from one).
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// A smooth function of radius given at nodes: the natural cubic spline through them (C2),
/// continued as a straight line beyond the end nodes (still C2: a natural spline has no
/// curvature there). One node: a constant; two: a straight line.
struct RadialTable {
  std::vector<double> r_mm;
  std::vector<double> value;
  /// The value at r [mm].
  double at(double r_mm) const;
  /// The slope d value / dr [1/mm] at r.
  double slope(double r_mm) const;
  /// Whether the table has no nodes.
  bool empty() const { return r_mm.empty(); }
  /// The spline's second derivatives at the nodes [1/mm^2] (zero at the ends).
  std::vector<double> curvatures() const;
};

/// What a separated-sector field looks like. Field: B(r, theta) = B_hill(r) [v + (1 - v) S],
/// with S in [0, 1] the sector shape: 1 inside a magnet, 0 in the valleys, edges
/// S = (1 + tanh(d / lambda)) / 2 in the distance d [mm] along the arc from the edge.
struct SectorFieldSpec {
  std::string description;
  int sectors = 8;
  /// Magnet width at each radius [deg of azimuth].
  RadialTable width_deg;
  /// Hill field B_hill(r) [T] (the field inside a magnet, far from its edges).
  RadialTable hill_T;
  double fringe_mm = 40;       ///< lambda: edge length (about half the magnet gap)
  double valley_fraction = 0;  ///< v = B_valley / B_hill
  /// Spiral angle xi(r) [deg] between the magnet centre line and the radial direction (empty:
  /// no spiral). The centre line is theta_c(r) = integral from spiral_r0 to r of tan(xi)/r' dr'
  /// (a constant xi gives the logarithmic spiral tan(xi) ln(r / r0)).
  RadialTable spiral_deg;
  double spiral_r0_mm = 1000;  ///< radius where the centre line crosses theta = 0
  /// The grid to sample on (one sector: theta_min .. theta_min + 360/N).
  PolarGrid grid;
  /// Settings for turnfit-orbit --isochronize kept with the field they made (a JSON object,
  /// read by the orbit module; null when absent).
  nlohmann::json isochronize;
};

/// Azimuth of magnet 1's centre line at radius r [deg].
double sector_centre_deg(const SectorFieldSpec& spec, double r_mm);

/// The sector shape S(r, theta) in [0, 1] (sector 1 centred on theta_c(r), periodic in 360/N).
/// The caller validates the spec with validate_sector_spec().
double sector_shape(const SectorFieldSpec& spec, double r_mm, double theta_deg);

/// Checks a spec (sectors >= 1, widths in (0, 360/N) at every grid radius, positive edge
/// length, valley fraction in [0, 1], tables with increasing radii, a usable grid);
/// EX_DATAERR naming the field at fault.
void validate_sector_spec(const SectorFieldSpec& spec);

/// Samples the field onto spec.grid as a map (values in T).
PolarFieldMap make_sector_field(const SectorFieldSpec& spec);

/// Reads a turnfit-sector-field/1 document (strict: unknown keys, wrong units and bad values
/// are EX_DATAERR naming `name` and the key path) and validates it.
SectorFieldSpec sector_spec_from_json(const nlohmann::json& doc, const std::string& name);

/// Reads a turnfit-sector-field/1 file ("-" for stdin).
SectorFieldSpec read_sector_spec(const std::string& path);

/// The spec as a turnfit-sector-field/1 document (numbers with 17 digits: reading it back
/// gives the same field bit for bit).
nlohmann::json sector_spec_to_json(const SectorFieldSpec& spec);

}  // namespace turnfit
