// Relativistic kinematics of the tracked particle (momentum, rigidity, speed).
#pragma once

#include <cmath>

namespace turnfit {

/// Speed of light [m/s].
inline constexpr double kSpeedOfLight = 299792458.0;
/// pi.
inline constexpr double kPi = 3.14159265358979323846;

/// Kinematic quantities of a particle of rest energy m [MeV] and charge q [e] at
/// kinetic energy E [MeV].
struct Kinematics {
  double gamma = 1, beta = 0, betagamma = 0;
  double p_MeV = 0;       ///< momentum [MeV/c]
  double brho_Tm = 0;     ///< magnetic rigidity p/q [T m]
  double v_m_s = 0;       ///< speed [m/s]
};

/// Kinematics at kinetic energy e_MeV (Brho = p / (q c), p in eV/c).
inline Kinematics kinematics(double mass_MeV, double charge_e, double e_MeV) {
  Kinematics k;
  k.gamma = 1 + e_MeV / mass_MeV;
  k.betagamma = std::sqrt(k.gamma * k.gamma - 1);
  k.beta = k.betagamma / k.gamma;
  k.p_MeV = k.betagamma * mass_MeV;
  k.brho_Tm = k.p_MeV * 1e6 / (kSpeedOfLight * std::fabs(charge_e));
  k.v_m_s = k.beta * kSpeedOfLight;
  return k;
}

}  // namespace turnfit
