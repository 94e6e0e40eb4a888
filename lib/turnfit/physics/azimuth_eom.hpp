// Equations of motion with azimuth as the independent variable, shared by the closed-orbit
// finder and the tracker (physics.md "Orbit equations with azimuth as the independent variable").
#pragma once

#include <cmath>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// Derivatives d/dtheta of r, x = p_r/p, z, xz = p_z/p and t, with the normalized field.
struct AzimuthDerivs {
  double dr, dx, dz, dxz, dt;
  double s;           ///< p_theta / p
  double b, br, bt;   ///< field, dB/dr, dB/dtheta times sign(q) / (B rho)
};

/// The derivatives at radius r for bending field f (b > 0 bends; physical Bz = -b, first order
/// off the midplane: Br = -z db/dr, Btheta = -(z/r) db/dtheta). inv_brho = sign(q) / (B rho),
/// inv_v = 1 / speed. False when the momentum has no azimuthal component left.
inline bool azimuth_eom(double r, double x, double z, double xz, const FieldSample& f, double inv_brho,
                        double inv_v, AzimuthDerivs& d) {
  const double s2 = 1 - x * x - xz * xz;
  if (!(s2 > 0)) return false;
  d.s = std::sqrt(s2);
  const double r_s = r / d.s, inv_s = 1 / d.s;  // one division per evaluation
  d.b = f.bz_T * inv_brho;
  d.br = f.dbz_dr_T_m * inv_brho;
  d.bt = f.dbz_dth_T * inv_brho;
  d.dr = r_s * x;
  d.dx = d.s - r * d.b + xz * inv_s * z * d.bt;
  d.dz = r_s * xz;
  d.dxz = z * (r * d.br - x * inv_s * d.bt);
  d.dt = r_s * inv_v;
  return true;
}

}  // namespace turnfit
