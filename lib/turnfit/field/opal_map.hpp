// OPAL-cycl 2022.1's midplane field: bilinear interpolation of Bz and of its 5-point-stencil
// derivatives on the map grid (physics.md, "How OPAL-cycl (2022.1) treats the Ring inputs").
#pragma once

#include <vector>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// A polar field map interpolated as OPAL-cycl 2022.1 does it, for turn-by-turn comparisons
/// with OPAL runs (turnfit's own interpolant is PolarFieldMap's bicubic spline).
///
/// At every grid node, dBz/dr and dBz/dtheta come from 5-point Lagrange stencils on the grid
/// values: central where possible, one-sided within two nodes of an edge. The azimuthal edges
/// are the sector's first and last azimuth (the stencil does not wrap around the sector).
/// Bz and both derivatives are then interpolated bilinearly in (r, theta), with theta taken
/// modulo the sector; the cell after the last azimuth closes on the first azimuth's node
/// values. The interpolant is continuous but its derivatives are not: it is OPAL's
/// approximation, not an improvement on the spline.
class OpalBilinearMap {
 public:
  /// Builds the node derivatives from the grid values of map. Throws EX_DATAERR if the grid
  /// has fewer than 5 radii or 5 azimuths (the stencils need 5 nodes).
  explicit OpalBilinearMap(const PolarFieldMap& map);

  /// Interpolated field at (r, theta); false (out untouched) outside [r_min, r_max], the same
  /// radial range as PolarFieldMap::sample.
  bool sample(double r_m, double theta_rad, FieldSample& out) const;

  /// The grid.
  const PolarGrid& grid() const { return grid_; }

 private:
  /// Bz [T], dBz/dr [T/m], dBz/dtheta [T/rad] at one node.
  struct Node {
    double b, db_dr, db_dth;
  };
  const Node& node(int i, int j) const { return nodes_[static_cast<size_t>(i) * (grid_.ntheta + 1) + j]; }

  PolarGrid grid_;
  double r_min_ = 0, r_max_ = 0, inv_dr_ = 0;
  double theta_min_deg_ = 0, sector_deg_ = 0, inv_dth_deg_ = 0;
  /// Radius-major, ntheta + 1 columns: the last repeats the first, so every azimuth cell
  /// has both of its corner columns in the same row.
  std::vector<Node> nodes_;
};

/// Derivative at node k (0..4) of the 5-point Lagrange interpolant through f[0..4] spaced by h.
double lagrange5_derivative(const double* f, int stride, int k, double h);

}  // namespace turnfit
