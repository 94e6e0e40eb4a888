// Space charge on a tracked bunch: its particles' own field, by the particle-in-cell solver of
// poisson.hpp in the bunch's rest frame, as momentum kicks between the azimuth integrator's steps.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/spacecharge/poisson.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/model.hpp"

namespace turnfit::sc {

/// How a bunch run computes its space charge.
struct SpaceChargeSettings {
  double current_uA = 0;  ///< beam current (bunch charge current / f_rf); 0: none
  GridSize grid;          ///< solver grid: radial, vertical, longitudinal
  int every_steps = 1;    ///< one solve per this many integration steps
  double halo_sigma = 8;  ///< halo cut of the solver (OpenPoissonSolver::halo_sigma)
};

/// The settings of a machine's space_charge block (defaults without one).
SpaceChargeSettings settings_of(const SpaceChargeSpec& spec);

/// What a space-charge run did, for reports and benchmarks.
struct SpaceChargeStats {
  SolveTimes solver;          ///< deposit, FFT, gather, Green's function
  double frame_s = 0;         ///< the rest-frame transforms and kicks [s]
  long kicks = 0;             ///< solves
  size_t most_outside = 0;    ///< most particles left out of the grid by one solve (halo)
  double bunch_charge_C = 0;  ///< current / f_rf
  double largest_kick = 0;    ///< largest |dp| / p of one kick
};

/// The space-charge kick of a bunch of `particles` particles (their charge is the bunch charge
/// shared equally; a lost particle takes its share away) in `model`'s machine. At each kick the
/// running particles, all at one azimuth, are moved to the mean time along their velocities
/// (the bunch's lab-frame snapshot), their offsets from the mean are put in the frame of the
/// mean momentum (radial-like, vertical, longitudinal) and stretched by gamma along it (the rest
/// frame), the solver gives E' there, and the lab field is E_perp = gamma E'_perp, E_par = E'_par,
/// B = beta x E / c (Jackson, Classical Electrodynamics, 11.10). Each particle's momentum
/// changes by q (E + v x B) dt, dt its own time over the kick's azimuth interval.
/// EX_USAGE for a negative current, a machine without RF (no bunch charge) or an empty bunch.
class SpaceChargeKick {
 public:
  SpaceChargeKick(const TrackModel& model, const SpaceChargeSettings& s, size_t particles, unsigned threads);
  /// The collective kick for track_bunch (bound to this object: keep it alive during the run).
  CollectiveKick collective();
  /// The kick itself (CollectiveKick::kick's arguments).
  void operator()(double theta_rad, double dtheta_rad, const std::vector<size_t>& index,
                  const std::vector<LaneState>& states, std::vector<double>& dp);
  const SpaceChargeStats& stats() const { return stats_; }
  /// The bunch charge [C] and each particle's share.
  double bunch_charge_C() const { return stats_.bunch_charge_C; }

 private:
  const TrackModel& model_;
  SpaceChargeSettings settings_;
  OpenPoissonSolver solver_;
  unsigned threads_ = 1;
  double q_particle_C_ = 0;
  SpaceChargeStats stats_;
  std::vector<double> xyz_, q_, e_;
};

/// The run's settings and what is reproducible of its stats as a '#' comment line (turnfit-track's
/// bunch output): the same for every thread count.
std::string stats_comment(const SpaceChargeSettings& set, const SpaceChargeStats& s);
/// Where the time went, one line of text (turnfit-track --sc-timing).
std::string timing_text(const SpaceChargeStats& s);

}  // namespace turnfit::sc
