// Internals shared by the integrators (not installed API).
#pragma once

#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
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


/// The group stepper's run (track_azimuth_group) over up to kMaxLanes particles of one model
/// that start at one azimuth, a grid node at a time, so that a caller can act on the lanes
/// between nodes: the space-charge driver kicks them there. Every run of a bunch passes the same
/// nodes (the map's grid from the injection azimuth), so runs advanced node for node stay in
/// step. Run to the end without kicks, each lane's records are track_azimuth_group's, bit for bit.
class AzimuthGroupRun {
 public:
  /// EX_SOFTWARE if n is 0 or over kMaxLanes, or the particles start at different azimuths.
  AzimuthGroupRun(const TrackModel& m, const ParticleState* s0, size_t n, const TrackSettings& st, GroupOutput* out);
  ~AzimuthGroupRun();
  AzimuthGroupRun(AzimuthGroupRun&&) noexcept;
  AzimuthGroupRun& operator=(AzimuthGroupRun&&) noexcept;
  /// Takes every lane up to `nodes` grid nodes further; false once the run has ended.
  bool advance(long nodes);
  bool running() const;
  /// The node azimuth the run is at (unwrapped, rad).
  double azimuth() const;
  /// The azimuth advance(nodes) would take the run to (the end at most), and the end's.
  double azimuth_after(long nodes) const;
  double end_azimuth() const;
  size_t size() const;
  /// Lane l's state; false (s untouched) when the lane was lost or has ended.
  bool lane(size_t l, LaneState& s) const;
  /// Adds (dpx, dpy, dpz) [m c] to lane l's momentum at its place (a running lane only).
  void kick(size_t l, double dpx, double dpy, double dpz);
  /// Writes each lane's end (GroupOutput::end).
  void finish();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// RK4 in time with a fixed number of steps per turn (OPAL-cycl's scheme).
TrackEnd track_time(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                    std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path);

}  // namespace turnfit::detail
