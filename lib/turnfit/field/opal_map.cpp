// OPAL-cycl's bilinear field-map interpolation with 5-point-stencil derivatives.
#include "turnfit/field/opal_map.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include "turnfit/io/error.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {

double lagrange5_derivative(const double* f, int stride, int k, double h) {
  // Weights (times 12) of the first derivative of the quartic through 5 equally spaced points,
  // at each of the points (Lagrangian differentiation on equally spaced points: Abramowitz &
  // Stegun, Handbook of Mathematical Functions, Sec. 25.3). Exact for polynomials of degree 4.
  static constexpr double w[5][5] = {{-25, 48, -36, 16, -3},
                                     {-3, -10, 18, -6, 1},
                                     {1, -8, 0, 8, -1},
                                     {-1, 6, -18, 10, 3},
                                     {3, -16, 36, -48, 25}};
  double s = 0;
  for (int m = 0; m < 5; ++m) s += w[k][m] * f[m * stride];
  return s / (12 * h);
}

OpalBilinearMap::OpalBilinearMap(const PolarFieldMap& map) : grid_(map.grid()) {
  const int nr = grid_.nr, nt = grid_.ntheta;
  if (nr < 5 || nt < 5)
    throw Error(ExitCode::data, "field map: OPAL's interpolation needs at least 5 radii and 5 azimuths (got " +
                                    std::to_string(nr) + " x " + std::to_string(nt) + ")");
  r_min_ = grid_.r_min_m();
  r_max_ = grid_.r_max_m();
  inv_dr_ = 1.0 / grid_.dr_m();
  theta_min_deg_ = grid_.theta_min_deg;
  sector_deg_ = 360.0 / grid_.symmetry;
  const double dth_deg = 360.0 / (static_cast<double>(grid_.symmetry) * nt);
  inv_dth_deg_ = 1.0 / dth_deg;
  const double dth_rad = kPi / 180 * dth_deg, dr = grid_.dr_m();

  const std::vector<double>& v = map.values();  // radius-major, nt columns
  nodes_.resize(static_cast<size_t>(nr) * (nt + 1));
  for (int i = 0; i < nr; ++i) {
    // Stencils start two nodes before the node, clamped so all 5 nodes lie on the grid:
    // one-sided near the edges. In theta the sector's ends are edges too (OPAL does not
    // use the periodicity here).
    const int i0 = std::clamp(i - 2, 0, nr - 5);
    for (int j = 0; j < nt; ++j) {
      const int j0 = std::clamp(j - 2, 0, nt - 5);
      Node& n = nodes_[static_cast<size_t>(i) * (nt + 1) + j];
      n.b = v[static_cast<size_t>(i) * nt + j];
      n.db_dr = lagrange5_derivative(&v[static_cast<size_t>(i0) * nt + j], nt, i - i0, dr);
      n.db_dth = lagrange5_derivative(&v[static_cast<size_t>(i) * nt + j0], 1, j - j0, dth_rad);
    }
    nodes_[static_cast<size_t>(i) * (nt + 1) + nt] = nodes_[static_cast<size_t>(i) * (nt + 1)];
  }
}

bool OpalBilinearMap::sample(double r_m, double theta_rad, FieldSample& out) const {
  if (!(r_m >= r_min_ && r_m <= r_max_)) return false;
  const double x = (r_m - r_min_) * inv_dr_;
  int i = static_cast<int>(x);
  if (i > grid_.nr - 2) i = grid_.nr - 2;  // r = r_max: the last cell's outer edge
  const double u = x - i;
  // Azimuth within the sector in degrees, as OPAL's fmod(theta_deg, 360 / symmetry).
  double a = std::fmod(theta_rad * (180 / kPi) - theta_min_deg_, sector_deg_);
  if (a < 0) a += sector_deg_;
  const double y = a * inv_dth_deg_;
  int j = static_cast<int>(y);
  if (j > grid_.ntheta - 1) j = grid_.ntheta - 1;  // a rounded up to the sector's end
  const double v = y - j;
  const Node &n00 = node(i, j), &n10 = node(i + 1, j), &n01 = node(i, j + 1), &n11 = node(i + 1, j + 1);
  const double w00 = (1 - u) * (1 - v), w10 = u * (1 - v), w01 = (1 - u) * v, w11 = u * v;
  out.bz_T = n00.b * w00 + n10.b * w10 + n01.b * w01 + n11.b * w11;
  out.dbz_dr_T_m = n00.db_dr * w00 + n10.db_dr * w10 + n01.db_dr * w01 + n11.db_dr * w11;
  out.dbz_dth_T = n00.db_dth * w00 + n10.db_dth * w10 + n01.db_dth * w01 + n11.db_dth * w11;
  return true;
}

}  // namespace turnfit
