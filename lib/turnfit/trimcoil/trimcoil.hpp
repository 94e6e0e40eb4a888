// Trim coil fields: the rational PSI models, OPAL's mirrored TC15 shape, and tables,
// restricted by radius, azimuth window, sector list and the main-field threshold.
#pragma once

#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"

namespace turnfit {

/// A trim coil's contribution to the bending field b (turnfit's convention: b > 0 bends the
/// particle; a positive bmax_T strengthens the field for every type).
///
/// Relation to OPAL (physics.md): OPAL adds PSI-BFIELD and PSI-PHASE fields to the sign-flipped
/// Bz, so OPAL's BMAX = -bmax_T for those two types, and BMAX = +bmax_T for PSI-BFIELD-MIRRORED.
class TrimCoilField {
 public:
  /// Builds the coil (reads its table for type "table"); `symmetry` places the sectors.
  /// EX_DATAERR / EX_NOINPUT for an unusable description or table file.
  TrimCoilField(const TrimCoil& coil, int symmetry);

  /// Adds the coil to b and its derivatives at (r, theta), given the main field there
  /// (for the threshold fall-off). Units: m, rad, T.
  void add(double r_m, double theta_rad, double main_b_T, double main_db_dr, double main_db_dth,
           double threshold_T, double& b, double& db_dr, double& db_dth) const;

  /// The radial shape s(r) and ds/dr [1/m] (b = bmax * s before windows); 0 outside.
  void shape(double r_m, double& s, double& ds_dr) const;

  /// The coil's name.
  const std::string& name() const { return coil_.name; }
  /// The description it was built from.
  const TrimCoil& coil() const { return coil_; }

 private:
  bool in_azimuth(double theta_rad) const;
  TrimCoil coil_;
  int symmetry_;
  int kind_;  // 0 bfield, 1 phase, 2 mirrored, 3 table
  bool everywhere_ = false;  // full circle, all sectors: skip the azimuth test
  std::vector<double> tr_, ts_, tm_;  // table radii [m], shape values, Hermite slopes
};

/// Value, first and second derivative of the rational function f(x)/g(x) with polynomial
/// coefficients num (a_0 + a_1 x + ...) and den (b_0 + ...; empty: g = 1).
void rational(const std::vector<double>& num, const std::vector<double>& den, double x, double& q,
              double& dq, double& d2q);

}  // namespace turnfit
