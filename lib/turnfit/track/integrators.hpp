// Internals shared by the integrators (not installed API).
#pragma once

#include <cmath>
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include "turnfit/physics/particle.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit::detail {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kTwoPi = 2 * kPi;

/// printf-style formatting of up to three numbers, for loss messages.
inline std::string fmt(const char* f, double a, double b = 0, double c = 0) {
  char buf[160];
  std::snprintf(buf, sizeof buf, f, a, b, c);
  return buf;
}

/// An angle [rad] in degrees, wrapped to (-180, 180]. (std::remainder rounds ties to even, so
/// odd multiples of 180 deg would come out as +180 and -180 on alternate turns.)
inline double wrap_deg(double rad) {
  const double d = rad * 180 / kPi;
  return d - 360 * std::ceil((d - 180) / 360);
}

/// Fifth-order Runge-Kutta in azimuth with grid-aligned steps (the default integrator).
TrackEnd track_azimuth(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                       std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path);

/// RK4 in time with a fixed number of steps per turn (OPAL-cycl's scheme).
TrackEnd track_time(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                    std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path);

}  // namespace turnfit::detail
