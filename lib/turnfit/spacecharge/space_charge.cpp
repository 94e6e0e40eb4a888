// Space charge on a tracked bunch: rest-frame snapshot, Poisson solve, lab-frame kicks.
#include "turnfit/spacecharge/space_charge.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit::sc {

namespace {
constexpr size_t kBlock = 4096;  // particles per block of the frame and kick loops
double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
std::string num(double v) {
  char b[64];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}
}  // namespace

SpaceChargeSettings settings_of(const SpaceChargeSpec& spec) {
  SpaceChargeSettings s;
  s.current_uA = spec.current_uA;
  s.grid = {spec.grid[0], spec.grid[1], spec.grid[2]};
  s.every_steps = spec.every_steps;
  s.halo_sigma = spec.halo_sigma;
  return s;
}

SpaceChargeKick::SpaceChargeKick(const TrackModel& model, const SpaceChargeSettings& s, size_t particles,
                                 unsigned threads)
    : model_(model), settings_(s), solver_(s.grid, threads), threads_(resolve_thread_count(threads)) {
  if (!(s.current_uA >= 0))
    throw usage_error("space charge: the beam current must be >= 0 uA, got " + num(s.current_uA));
  if (s.current_uA > 0 && !(model.rf_MHz > 0))
    throw usage_error("space charge: the bunch charge is the current over the RF frequency, and the machine has no "
                      "RF (rf.frequency_MHz)");
  if (particles == 0) throw usage_error("space charge needs a bunch of particles (--particles N)");
  if (s.every_steps < 1) throw usage_error("space charge: solve every whole number of steps (at least 1)");
  solver_.halo_sigma = s.halo_sigma;
  stats_.bunch_charge_C = model.rf_MHz > 0 ? s.current_uA * 1e-6 / (model.rf_MHz * 1e6) : 0.0;
  q_particle_C_ = stats_.bunch_charge_C / static_cast<double>(particles);
}

CollectiveKick SpaceChargeKick::collective() {
  CollectiveKick ck;
  ck.every_nodes = settings_.every_steps;
  ck.kick = [this](double th, double dth, const std::vector<size_t>& index, const std::vector<LaneState>& states,
                   std::vector<double>& dp) { (*this)(th, dth, index, states, dp); };
  return ck;
}

void SpaceChargeKick::operator()(double /*theta_rad*/, double dtheta_rad, const std::vector<size_t>& /*index*/,
                                 const std::vector<LaneState>& states, std::vector<double>& dp) {
  const size_t n = states.size();
  dp.assign(3 * n, 0.0);
  if (n == 0 || q_particle_C_ == 0 || !(dtheta_rad > 0)) return;
  const auto t0 = std::chrono::steady_clock::now();
  // The mean position, momentum and time of the running particles.
  double X[3] = {0, 0, 0}, P[3] = {0, 0, 0}, T = 0;
  for (const LaneState& l : states) {
    X[0] += l.s.x;
    X[1] += l.s.y;
    X[2] += l.s.z;
    P[0] += l.s.px;
    P[1] += l.s.py;
    P[2] += l.s.pz;
    T += l.s.t;
  }
  const double inv_n = 1.0 / static_cast<double>(n);
  for (int k = 0; k < 3; ++k) {
    X[k] *= inv_n;
    P[k] *= inv_n;
  }
  T *= inv_n;
  const double p = std::sqrt(P[0] * P[0] + P[1] * P[1] + P[2] * P[2]);
  if (!(p > 0)) return;
  const double gamma = std::sqrt(1 + p * p);
  // The frame of the mean momentum: el along it, ev the vertical made normal to it, eh = el x ev
  // (outward for a bunch moving with increasing azimuth).
  const double el[3] = {P[0] / p, P[1] / p, P[2] / p};
  double ev[3] = {-el[2] * el[0], -el[2] * el[1], 1 - el[2] * el[2]};
  const double nv = std::sqrt(ev[0] * ev[0] + ev[1] * ev[1] + ev[2] * ev[2]);
  for (double& c : ev) c /= nv;
  const double eh[3] = {el[1] * ev[2] - el[2] * ev[1], el[2] * ev[0] - el[0] * ev[2], el[0] * ev[1] - el[1] * ev[0]};
  xyz_.resize(3 * n);
  q_.assign(n, q_particle_C_);
  e_.resize(3 * n);
  // (Particles are independent here and below: blocks of them on the workers, the same numbers
  // for any thread count.)
  const size_t blocks = (n + kBlock - 1) / kBlock;
  parallel_for(blocks, threads_, [&](size_t blk, unsigned) {
    for (size_t i = blk * kBlock, end = std::min(n, i + kBlock); i < end; ++i) {
      const ParticleState& s = states[i].s;
      // Where the particle is at the mean time, moving straight on (the bunch passes an azimuth
      // over a fraction of a degree of its orbit: the arc's sagitta is micrometres).
      const double g = std::sqrt(1 + s.px * s.px + s.py * s.py + s.pz * s.pz);
      const double dt = T - s.t, f = kSpeedOfLight * dt / g;
      const double d[3] = {s.x + s.px * f - X[0], s.y + s.py * f - X[1], s.z + s.pz * f - X[2]};
      xyz_[3 * i] = d[0] * eh[0] + d[1] * eh[1] + d[2] * eh[2];
      xyz_[3 * i + 1] = d[0] * ev[0] + d[1] * ev[1] + d[2] * ev[2];
      xyz_[3 * i + 2] = gamma * (d[0] * el[0] + d[1] * el[1] + d[2] * el[2]);
    }
  });
  stats_.frame_s += seconds_since(t0);
  solver_.solve(n, xyz_.data(), q_.data(), e_.data());
  const auto t1 = std::chrono::steady_clock::now();
  stats_.most_outside = std::max(stats_.most_outside, solver_.outside());
  ++stats_.kicks;
  // Lab fields: E = gamma E'_perp + E'_par, B = beta x E / c; the force on a particle of charge
  // q moving with v is q (E + v x B). Its momentum [m c] changes by q (E + v x B) dt / (m c),
  // dt = dt/dtheta dtheta, with m c = mass [eV] e / c.
  const double beta[3] = {P[0] / gamma, P[1] / gamma, P[2] / gamma};
  const double to_mc = model_.charge_e * kSpeedOfLight / (model_.mass_MeV * 1e6);
  std::vector<double> largest(blocks, 0.0);
  parallel_for(blocks, threads_, [&](size_t blk, unsigned) {
    for (size_t i = blk * kBlock, end = std::min(n, i + kBlock); i < end; ++i) {
      const double* ep = &e_[3 * i];
      double E[3];
      for (int k = 0; k < 3; ++k) E[k] = gamma * (ep[0] * eh[k] + ep[1] * ev[k]) + ep[2] * el[k];
      // c B = beta x E.
      const double cB[3] = {beta[1] * E[2] - beta[2] * E[1], beta[2] * E[0] - beta[0] * E[2],
                            beta[0] * E[1] - beta[1] * E[0]};
      const ParticleState& s = states[i].s;
      const double g = std::sqrt(1 + s.px * s.px + s.py * s.py + s.pz * s.pz);
      const double b[3] = {s.px / g, s.py / g, s.pz / g};  // v / c
      const double F[3] = {E[0] + b[1] * cB[2] - b[2] * cB[1], E[1] + b[2] * cB[0] - b[0] * cB[2],
                           E[2] + b[0] * cB[1] - b[1] * cB[0]};
      const double dt = states[i].dt_dtheta * dtheta_rad;
      double kick2 = 0;
      for (int k = 0; k < 3; ++k) {
        dp[3 * i + k] = to_mc * F[k] * dt;
        kick2 += dp[3 * i + k] * dp[3 * i + k];
      }
      const double pi = g * std::sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
      if (pi > 0) largest[blk] = std::max(largest[blk], std::sqrt(kick2) / pi);
    }
  });
  for (double v : largest) stats_.largest_kick = std::max(stats_.largest_kick, v);
  stats_.frame_s += seconds_since(t1);
  stats_.solver = solver_.times();
}

std::string stats_comment(const SpaceChargeSettings& set, const SpaceChargeStats& s) {
  char b[512];
  std::snprintf(b, sizeof b,
                "# space_charge current_uA=%.6g bunch_charge_pC=%.6g grid=%dx%dx%d every_steps=%d solves=%ld "
                "most_outside=%zu largest_kick=%.3g\n",
                set.current_uA, s.bunch_charge_C * 1e12, set.grid.nx, set.grid.ny, set.grid.nz, set.every_steps,
                s.kicks, s.most_outside, s.largest_kick);
  return b;
}

std::string timing_text(const SpaceChargeStats& s) {
  char b[512];
  std::snprintf(b, sizeof b,
                "space charge: %ld solves, %ld Green's function builds; deposit %.3f s, FFT %.3f s, gather %.3f s, "
                "Green's function %.3f s, frames and kicks %.3f s",
                s.kicks, s.solver.green_builds, s.solver.deposit_s, s.solver.fft_s, s.solver.gather_s,
                s.solver.green_s, s.frame_s);
  return b;
}

}  // namespace turnfit::sc
