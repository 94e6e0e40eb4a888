// Midplane field maps Bz(r, theta) on a polar grid with N-fold symmetry, and their
// C1 bicubic-spline interpolation (tunes need continuous dBz/dr and dBz/dtheta).
#pragma once

#include <array>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace turnfit {

/// Bz and its first derivatives at one midplane point.
struct FieldSample {
  double bz_T = 0;          ///< Bz [T]
  double dbz_dr_T_m = 0;    ///< dBz/dr [T/m]
  double dbz_dth_T = 0;     ///< dBz/dtheta [T/rad]
};

/// The grid of a polar map covering one sector (periodic in theta with period
/// 2 pi / symmetry): radii r_min + i dr, azimuths theta_min + j dtheta,
/// with ntheta * dtheta * symmetry = 2 pi.
struct PolarGrid {
  // Kept in the file units (mm, deg) so that maps written and read back are identical.
  double r_min_mm = 0;
  double dr_mm = 0;
  int nr = 0;
  double theta_min_deg = 0;
  int ntheta = 0;
  int symmetry = 1;
  /// Azimuthal step [rad].
  double dtheta_rad() const;
  /// Smallest radius [m].
  double r_min_m() const { return r_min_mm * 1e-3; }
  /// Radial step [m].
  double dr_m() const { return dr_mm * 1e-3; }
  /// First azimuth [rad].
  double theta_min_rad() const;
  /// Largest radius of the grid [m].
  double r_max_m() const { return (r_min_mm + (nr - 1) * dr_mm) * 1e-3; }
};

/// A midplane field map with bicubic-spline interpolation.
///
/// The interpolant is the tensor-product cubic spline (not-a-knot in r, periodic in
/// theta), stored as one bicubic patch per cell, so Bz and both first derivatives are
/// continuous everywhere inside the map. Outside [r_min, r_max] there is no field:
/// sample() returns false and trackers report a loss.
class PolarFieldMap {
 public:
  PolarFieldMap() = default;
  /// Builds the interpolant from grid values bz_T[i * ntheta + j] (radius-major).
  /// Throws EX_DATAERR if the grid is inconsistent or a value is not finite.
  PolarFieldMap(const PolarGrid& grid, std::vector<double> bz_T, std::string label = {});

  /// Interpolated field at (r, theta); false (out untouched) outside the radial range.
  bool sample(double r_m, double theta_rad, FieldSample& out) const;
  /// Bz only (NaN outside the map), for tables and plots.
  double bz(double r_m, double theta_rad) const;
  /// Whether r lies inside the map's radial range.
  bool contains(double r_m) const { return r_m >= r_min_ && r_m <= r_max_; }

  /// The grid.
  const PolarGrid& grid() const { return grid_; }
  /// Grid values [T], radius-major.
  const std::vector<double>& values() const { return *bz_; }
  /// Grid value at radius index i, azimuth index j [T].
  double value(int i, int j) const { return (*bz_)[static_cast<size_t>(i) * grid_.ntheta + j]; }
  /// Free-text label (file label or generator description).
  const std::string& label() const { return label_; }
  /// Azimuthal average of the grid values at radius index i [T].
  double average(int i) const;
  /// Azimuthal average of Bz at radius r (by the interpolant at the grid azimuths) [T].
  double average_at(double r_m) const;

 private:
  void build();
  // The values and patches never change after construction and are shared between copies: an
  // optimizer builds a model (holding a copy of the map) per design, and copying ring8's 2.7 MB
  // of patches cost each design a memcpy and 700 page faults.
  PolarGrid grid_;
  std::shared_ptr<const std::vector<double>> bz_;
  std::string label_;
  double r_min_ = 0, r_max_ = 0, theta_min_ = 0;
  double inv_dr_ = 0, inv_dth_ = 0;
  std::shared_ptr<const std::vector<std::array<double, 16>>> coef_;  ///< per cell: a[k*4+l] u^k v^l
  const std::array<double, 16>* patch_ = nullptr;                    ///< coef_'s data (shared, so valid in copies)
};

/// Samples f(r_m, theta_rad) [T] on a grid: the analytic-field generator used by tests
/// and by machine builders.
PolarFieldMap make_field_map(const PolarGrid& grid,
                             const std::function<double(double, double)>& f,
                             const std::string& label);

}  // namespace turnfit
