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

/// The most particles the group stepper takes through a step together.
constexpr int kMaxLanes = TrackModel::kMaxLanes;

/// Where the group stepper puts one particle's records (kicks and path optional).
struct GroupOutput {
  std::vector<TurnRecord>* turns = nullptr;
  std::vector<KickRecord>* kicks = nullptr;
  std::vector<PathPoint>* path = nullptr;
  TrackEnd* end = nullptr;
};

/// The same integrator for n particles stepped together in groups of up to kMaxLanes (one
/// group of one is the single-particle path): particles that start at one azimuth share every
/// grid step, and the main field comes from the map's row table at the stage azimuths. Each
/// particle's records and end are what track_azimuth gives to rounding (the same equations, the
/// field's rows evaluated before instead of during the step, the equations of motion in
/// another order), and do not depend on which particles share its group.
void track_azimuth_group(const TrackModel& m, const ParticleState* s0, size_t n, const TrackSettings& st,
                         GroupOutput* out);
/// The same with a model per particle (ms[i] for s0[i]: an optimizer's designs). Particles
/// whose models share one main field map (copies of one map) go through the grid steps
/// together, each with its own coils, effects, gaps and probes.
void track_azimuth_group(const TrackModel* const* ms, const ParticleState* s0, size_t n, const TrackSettings& st,
                         GroupOutput* out);

/// RK4 in time with a fixed number of steps per turn (OPAL-cycl's scheme).
TrackEnd track_time(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                    std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path);

}  // namespace turnfit::detail
