// Relativistic kinematics of the tracked particle (momentum, rigidity, speed).
#pragma once

#include <cmath>

namespace turnfit {

/// Speed of light [m/s].
inline constexpr double kSpeedOfLight = 299792458.0;
/// pi.
inline constexpr double kPi = 3.14159265358979323846;

/// std::remainder(x, 2 pi): x - 2 pi n with n the integer nearest x / (2 pi), ties to even, in
/// [-pi, pi]. Azimuths in the trackers' landing steps are within a turn of that range, where
/// this takes a comparison and at most one subtraction (exact there: x and 2 pi are within a
/// factor 2 of each other) instead of glibc's remainder (2.6 % of a bunch's time); the same
/// number bit for bit for every x (tests/unit/test_fast_track.cpp).
inline double remainder_two_pi(double x) {
  constexpr double two_pi = 2 * kPi, three_pi = 3 * kPi;
  if (x >= -kPi && x <= kPi) return x;  // n = 0 (|x| = pi: the tie, n = 0 is even)
  // n = 1 or -1; a zero (x = 2 pi or -2 pi) takes x's sign, as remainder's does.
  if (x > kPi && x < three_pi) return x != two_pi ? x - two_pi : 0.0;
  if (x < -kPi && x > -three_pi) return x != -two_pi ? x + two_pi : -0.0;
  return std::remainder(x, two_pi);  // farther out, NaN and infinities
}

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
