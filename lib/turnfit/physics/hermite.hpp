// Cubic Hermite interpolation on one interval, shared by tables, profiles and dense output.
#pragma once

namespace turnfit {

/// The cubic Hermite basis at t in [0, 1] (values h.., slopes d.. per unit t).
struct HermiteBasis {
  double h00, h10, h01, h11, d00, d10, d01, d11;
  explicit HermiteBasis(double t) {
    const double t2 = t * t, u = 1 - t;
    h00 = (1 + 2 * t) * u * u, h10 = t * u * u, h01 = t2 * (3 - 2 * t), h11 = t2 * (t - 1);
    d00 = 6 * t2 - 6 * t, d10 = 3 * t2 - 4 * t + 1, d01 = -d00, d11 = 3 * t2 - 2 * t;
  }
  double value(double y0, double y1, double m0, double m1, double h) const {
    return h00 * y0 + h10 * h * m0 + h01 * y1 + h11 * h * m1;
  }
};

/// The cubic through (0, y0) and (h, y1) with slopes m0, m1 [per unit x], at x = t h
/// (t in [0, 1]); its slope there goes to dy.
inline double hermite(double y0, double y1, double m0, double m1, double h, double t, double& dy) {
  const HermiteBasis b(t);
  dy = (b.d00 * y0 + b.d01 * y1) / h + b.d10 * m0 + b.d11 * m1;
  return b.value(y0, y1, m0, m1, h);
}

/// hermite() for tables that keep 1 / h: a multiplication where hermite() divides (lookups
/// inside a tracker's field samples).
inline double hermite_inv(double y0, double y1, double m0, double m1, double h, double inv_h, double t, double& dy) {
  const HermiteBasis b(t);
  dy = (b.d00 * y0 + b.d01 * y1) * inv_h + b.d10 * m0 + b.d11 * m1;
  return b.value(y0, y1, m0, m1, h);
}

}  // namespace turnfit
