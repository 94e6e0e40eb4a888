// Single-particle tracking through a cyclotron: RF gap kicks, trim coils, probe crossings.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/track/model.hpp"

namespace turnfit {

/// A particle's phase-space point: position [m], momentum in units of m c (beta gamma
/// components), time [s].
struct ParticleState {
  double x = 0, y = 0, z = 0;
  double px = 0, py = 0, pz = 0;
  double t = 0;
};

/// A particle's state at a node of a collective run (bunch.hpp's CollectiveKick).
struct LaneState {
  ParticleState s;        ///< position [m], momentum (beta gamma), time [s]
  double dt_dtheta = 0;   ///< time per radian of azimuth [s]: r / (v p_theta / p)
};

/// One crossing of a probe, as turns.csv records it.
struct TurnRecord {
  int probe = 0;          ///< index into TrackModel::probes
  int turn = 0;           ///< 1 for the first crossing of this probe line, 2 for the next, ...
  double r_mm = 0;        ///< radius of the crossing point, minus the probe's shift (ProbeLine::recorded_r)
  double s_mm = 0;        ///< position along the probe, minus its shift
  double t_ns = 0;        ///< time since the start
  double energy_MeV = 0;  ///< kinetic energy
  double phase_deg = 0;   ///< RF phase 360 f_rf t, wrapped to (-180, 180]
};

/// One gap crossing, for diagnostics and tests.
struct KickRecord {
  int gap = 0;
  int turn = 0;
  double theta_deg = 0;
  GapKick kick;
};

/// One point of a particle's path, after every integration step (--orbit).
struct PathPoint {
  double theta_deg = 0;   ///< azimuth since the start, unwrapped (360 per turn)
  double r_mm = 0, z_mm = 0;
  double pr_mrad = 0;     ///< p_r / p
  double t_ns = 0;
  double energy_MeV = 0;
};

/// How a track ended.
struct TrackEnd {
  bool lost = false;
  std::string status;       ///< "turn limit", or "lost: ..." with where and when
  double turns = 0;         ///< revolutions completed (fractional)
  double energy_MeV = 0;
  double r_mm = 0;
  double theta_deg = 0;
  double t_ns = 0;
};

/// Default largest azimuth step [deg]: 3 cells of the PSI Ring map (1/3 deg), where the
/// fifth-order scheme stays within 0.005 mm of RK4 at 23040 steps/turn over 190 turns (4 cells:
/// 0.05 mm near the map edge; bench/RESULTS.md).
constexpr double kDefaultStepDeg = 1.0;

/// Tracking settings.
struct TrackSettings {
  /// "azimuth": fifth-order Runge-Kutta (Dormand-Prince) in azimuth with steps aligned to the
  /// field map's grid, exact gap and probe crossings (the default); "rk4": RK4 in time with a fixed number of steps per turn (OPAL's
  /// scheme) and crossings interpolated between steps.
  std::string integrator = "azimuth";
  int steps_per_turn = 0;  ///< rk4: steps per RF period times h (default 2880)
  /// azimuth: largest step [deg]; steps are whole multiples (or whole fractions) of the map's
  /// azimuthal cell, so every step starts and ends on grid lines. 0: kDefaultStepDeg.
  double step_deg = 0;
  double turns = 190;      ///< revolutions to track
  GapPhysics gap_physics = GapPhysics::turnfit;
  /// rk4 only: OPAL-cycl 2022.1's gap handling (straight-line gap-time estimate, no gap test in
  /// the step after a kick). The rest of OPAL's numerics are ModelOptions::opal_map,
  /// GapPhysics::opal and injection_state(..., opal_single_precision).
  bool opal_compat = false;
  /// azimuth only: the reference stepper, one particle with every field sample through
  /// TrackModel::field (the stepper before the fast paths of issue 17, kept unchanged), instead of the
  /// group stepper with the map's row table. The two agree to a few 1e-9 mm over 190 turns
  /// (rounding: tests/unit/test_fast_track.cpp asserts 1e-6 mm);
  /// tests and benchmarks use this one as their reference.
  bool reference_stepper = false;
};

/// Names and one-line descriptions of the integrators.
std::vector<std::pair<std::string, std::string>> list_integrators();

/// The injection state of a machine (OPAL's convention: total momentum from the energy,
/// p_r given, p_theta along increasing azimuth, rotated to the injection azimuth).
/// opal_single_precision: p_theta as OPAL-cycl 2022.1 computes it, the square root of
/// P^2 - p_r^2 - p_z^2 rounded to float and taken in float (a 1e-4 mm effect on the orbit).
ParticleState injection_state(const Injection& inj, double mass_MeV, bool opal_single_precision = false);

/// The machine's injection with its `injection-offset` effect applied (the machine's own
/// injection when it has none): r + dr, E + dE, p_r / p + dpr, z + dz, p_z / p + dpz, and the
/// start time moved by dphase / (360 f_rf), exactly as a bunch file's offsets move a particle
/// (offset_state in bunch.hpp). Every tool that tracks a machine's beam starts from this.
/// The machine must have an injection block (EX_DATAERR otherwise).
Injection effective_injection(const Machine& m);

/// Tracking settings from a machine's `tracking` block: its integrator unless `integrator` is
/// given (else azimuth), its steps per turn (else 2880), step and turns (0 if it has none: the
/// caller decides what a missing turn count means). EX_DATAERR naming /tracking/integrator for
/// an unknown integrator. Tools apply their own options on top.
TrackSettings machine_track_settings(const Machine& m, const std::string& integrator = "");

/// Kinetic energy [MeV] of a state.
double kinetic_energy(const ParticleState& s, double mass_MeV);

/// Tracks one particle; appends its probe crossings to `turns` (gap kicks to `kicks` and the
/// state after every step to `path`, if given). Never throws for physics: losses are reported in the result.
TrackEnd track_particle(const TrackModel& model, const ParticleState& start, const TrackSettings& settings,
                        std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks = nullptr,
                        std::vector<PathPoint>* path = nullptr);

/// Tracks n particles (ends[i] and turns[i] as track_particle gives them for starts[i]; turns are
/// appended). The azimuth integrator steps particles that start at one azimuth together in
/// groups, which is several times faster per particle than one by one; particle i's records
/// do not depend on which others share its group.
void track_particles(const TrackModel& model, const ParticleState* starts, size_t n, const TrackSettings& settings,
                     std::vector<TurnRecord>* turns, TrackEnd* ends);

/// track_particles with a model per particle (models[i] for starts[i]): an optimizer's designs.
/// Particles whose models share one field map (copies of one map, as make_track_model makes
/// them from one ModelFiles) are stepped together; each one's records are what track_particle
/// gives it with its model alone, bit for bit.
void track_particles(const TrackModel* const* models, const ParticleState* starts, size_t n,
                     const TrackSettings& settings, std::vector<TurnRecord>* turns, TrackEnd* ends);

}  // namespace turnfit
