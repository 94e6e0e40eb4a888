// RK4 in time with a fixed number of steps per turn (OPAL-cycl's scheme); gap kicks at the
// crossing time located on the Hermite path through the step's ends (or, with opal_compat, at
// OPAL's straight-line estimate of it), probe crossings interpolated on the Hermite path.
#include <array>
#include <cmath>

#include "turnfit/physics/hermite.hpp"
#include "turnfit/track/integrators.hpp"

namespace turnfit::detail {
namespace {

// ---------------------------------------------------------------------------------------------
// Time integrator: Cartesian RK4 with a fixed step dt = h / (steps_per_turn f_rf), as OPAL-cycl.
using TState = std::array<double, 6>;  // x, y, z [m], px, py, pz [beta gamma]

struct TimeRhs {
  const TrackModel& m;
  double k;  // q c^2 / (m c^2) [1 / (T s)] times sign: d(beta gamma)/dt = k (p/gamma) x B
  bool operator()(const TState& s, TState& d) {
    const double r = std::hypot(s[0], s[1]);
    const double th = std::atan2(s[1], s[0]);
    FieldSample f;
    if (!m.field(r, th, f)) {
      return false;
    }
    const double c = std::cos(th), sn = std::sin(th);
    const double bz = -f.bz_T, br = -s[2] * f.dbz_dr_T_m, bt = -s[2] / r * f.dbz_dth_T;
    const double bx = br * c - bt * sn, by = br * sn + bt * c;
    const double gamma = std::sqrt(1 + s[3] * s[3] + s[4] * s[4] + s[5] * s[5]);
    const double vx = s[3] / gamma, vy = s[4] / gamma, vz = s[5] / gamma;  // in units of c
    d[0] = vx * kSpeedOfLight;
    d[1] = vy * kSpeedOfLight;
    d[2] = vz * kSpeedOfLight;
    d[3] = k * (vy * bz - vz * by);
    d[4] = k * (vz * bx - vx * bz);
    d[5] = k * (vx * by - vy * bx);
    return true;
  }
};

bool rk4_t(TimeRhs& f, double h, TState& y) {
  TState k1, k2, k3, k4, t;
  if (!f(y, k1)) return false;
  for (int i = 0; i < 6; ++i) t[i] = y[i] + 0.5 * h * k1[i];
  if (!f(t, k2)) return false;
  for (int i = 0; i < 6; ++i) t[i] = y[i] + 0.5 * h * k2[i];
  if (!f(t, k3)) return false;
  for (int i = 0; i < 6; ++i) t[i] = y[i] + h * k3[i];
  if (!f(t, k4)) return false;
  for (int i = 0; i < 6; ++i) y[i] += h / 6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]);
  return true;
}

/// Position at fraction u of a step of length h, on the cubic Hermite path through the step's
/// end states (positions and velocities).
void hermite_pos(const TState& a, const TState& da, const TState& b, const TState& db, double h, double u,
                 double& x, double& y) {
  double unused;
  x = hermite(a[0], b[0], da[0], db[0], h, u, unused);
  y = hermite(a[1], b[1], da[1], db[1], h, u, unused);
}

/// Fraction of the step where a line with signed distance `dist(x, y)` (positive before it) is
/// crossed, by bisection on the Hermite path (O(h^4) accurate).
template <class Dist>
double crossing_fraction(const TState& a, const TState& da, const TState& b, const TState& db, double h, Dist dist) {
  double lo = 0, hi = 1;
  for (int it = 0; it < 60; ++it) {
    const double mid = 0.5 * (lo + hi);
    double xm, ym;
    hermite_pos(a, da, b, db, h, mid, xm, ym);
    (dist(xm, ym) > 0 ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

}  // namespace

TrackEnd track_time(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                    std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path) {
  TrackEnd end;
  const int spt = st.steps_per_turn > 0 ? st.steps_per_turn : 2880;
  const double f_rev = m.rf_MHz * 1e6 / std::max(1, m.harmonic);
  const double dt = 1.0 / (spt * f_rev);
  TimeRhs f{m, (m.charge_e * kSpeedOfLight * kSpeedOfLight) / (m.mass_MeV * 1e6)};
  TState y{s0.x, s0.y, s0.z, s0.px, s0.py, s0.pz};
  double t = s0.t;
  double th = std::atan2(y[1], y[0]);
  const double th0 = th, th_end = th0 + kTwoPi * st.turns;
  std::vector<int> gap_count(m.gaps.size(), 0), probe_count(m.probes.size(), 0);
  const double mass = m.mass_MeV;
  auto energy = [&](const TState& s) { return (std::sqrt(1 + s[3] * s[3] + s[4] * s[4] + s[5] * s[5]) - 1) * mass; };
  auto lose = [&](const std::string& why) {
    end.lost = true;
    // At the last state inside (y: a failed step leaves it untouched), as the '# end' line.
    end.status = "lost: " + why + fmt(" at r = %.1f mm, azimuth %.2f deg, turn %.3f", std::hypot(y[0], y[1]) * 1e3,
                                      wrap_deg(std::atan2(y[1], y[0])), (th - th0) / kTwoPi);
  };
  // OPAL-cycl 2022.1's gap handling (physics.md, "Single-gap cavity"): after a full step that
  // crossed a gap, restart from the step's start, advance by the straight-line estimate
  // dt1 = d_old / (beta_old c) of the time to the gap, kick at t + dt1, advance the rest of
  // the step; the step after a kick tests no gap. Returns false if the particle was lost.
  bool opal_skip_gaps = false;
  auto opal_gap_step = [&](const TState& y0) -> bool {
    if (opal_skip_gaps) {
      opal_skip_gaps = false;
      return true;
    }
    for (size_t gi = 0; gi < m.gaps.size(); ++gi) {
      const Gap& gp = m.gaps[gi];
      const double da = gp.distance(y0[0], y0[1]), db = gp.distance(y[0], y[1]);
      if (!(da > 0 && db <= 0)) continue;
      opal_skip_gaps = true;
      const double p2 = y0[3] * y0[3] + y0[4] * y0[4] + y0[5] * y0[5];
      const double beta0 = std::sqrt(p2) / std::sqrt(1 + p2);
      const double dt1 = da / (beta0 * kSpeedOfLight), dt2 = dt - dt1;
      y = y0;
      // OPAL leaves out sub-steps shorter than 1e-9 of a step (its test dt / dt_i < 1e9).
      if (dt / dt1 < 1e9 && !rk4_t(f, dt1, y)) {
        lose("left the field map");
        return false;
      }
      // The straight-line estimate stops short of the gap line; OPAL places the particle on
      // the gap by its radius, rho = sqrt(r^2 - PDIS^2), i.e. where the circle through the
      // particle meets the gap line.
      const double r = std::hypot(y[0], y[1]), thc = gp.crossing_azimuth(r);
      KickRecord kr;
      kr.gap = static_cast<int>(gi);
      kr.turn = ++gap_count[gi];
      kr.theta_deg = std::atan2(y[1], y[0]) * 180 / kPi;
      double px = y[3], py = y[4];
      kr.kick = gp.kick(r * std::cos(thc), r * std::sin(thc), t + dt1, mass, m.charge_e, st.gap_physics, px, py,
                        y[5]);
      if (kr.kick.stopped) {
        if (kicks) kicks->push_back(kr);
        lose("stopped by gap '" + gp.name() + "'");
        return false;
      }
      if (kr.kick.active) {
        y[3] = px;
        y[4] = py;
      }
      if (kicks) kicks->push_back(kr);
      if (dt / dt2 < 1e9 && !rk4_t(f, dt2, y)) {
        lose("left the field map");
        return false;
      }
      break;  // one gap per step (steps are far shorter than the gap spacing)
    }
    return true;
  };
  TState d0, d1;
  while (th < th_end) {
    const TState y0 = y;
    if (!rk4_t(f, dt, y)) {
      lose("left the field map");
      break;
    }
    if (st.opal_compat) {
      if (!opal_gap_step(y0)) break;
    } else {
      // Gap crossings: find the exact crossing time in the step, integrate to it, kick, finish.
      for (size_t gi = 0; gi < m.gaps.size(); ++gi) {
        const Gap& gp = m.gaps[gi];
        const double da = gp.distance(y0[0], y0[1]), db = gp.distance(y[0], y[1]);
        if (!(da > 0 && db <= 0)) continue;
        // The direction test (positive to negative distance) picks the crossing on the gap's
        // own half of the line; the particle crosses the other half the other way.
        if (!f(y0, d0) || !f(y, d1)) break;
        // The Hermite path locates the crossing to O(dt^4); a partial RK4 step from the start
        // of the step then puts the particle there (physics.md: exact gap time, not OPAL's
        // straight-line estimate).
        const double u = crossing_fraction(y0, d0, y, d1, dt, [&](double x, double yy) { return gp.distance(x, yy); });
        TState yc = y0;
        if (!rk4_t(f, u * dt, yc)) {
          lose("left the field map");
          break;
        }
        const double tc = t + u * dt;
        KickRecord kr;
        kr.gap = static_cast<int>(gi);
        kr.turn = ++gap_count[gi];
        kr.theta_deg = std::atan2(yc[1], yc[0]) * 180 / kPi;
        double px = yc[3], py = yc[4];
        kr.kick = gp.kick(yc[0], yc[1], tc, mass, m.charge_e, st.gap_physics, px, py, yc[5]);
        if (kr.kick.stopped) {
          y = yc;  // the particle ends at the gap
          if (kicks) kicks->push_back(kr);
          lose("stopped by gap '" + gp.name() + "'");
          break;
        }
        if (kr.kick.active) {
          yc[3] = px;
          yc[4] = py;
        }
        if (kicks) kicks->push_back(kr);
        y = yc;
        if (!rk4_t(f, (1 - u) * dt, y)) {
          lose("left the field map");
          break;
        }
        break;  // one gap per step (steps are far shorter than the gap spacing)
      }
    }
    if (end.lost) break;
    // Probe crossings, interpolated between the step ends.
    for (size_t pi = 0; pi < m.probes.size(); ++pi) {
      const ProbeLine& pl = m.probes[pi];
      const double da = pl.distance(y0[0], y0[1]), db = pl.distance(y[0], y[1]);
      if (!(da > 0 && db <= 0)) continue;
      if (pl.along(y[0], y[1]) < 0) continue;  // the other half of the line
      if (!f(y0, d0) || !f(y, d1)) break;
      const double u = crossing_fraction(y0, d0, y, d1, dt, [&](double x, double yy) { return pl.distance(x, yy); });
      double xc, yc;
      hermite_pos(y0, d0, y, d1, dt, u, xc, yc);
      ++probe_count[pi];
      const double s = pl.along(xc, yc);
      if (s >= pl.s_min_m + pl.shift_m && s <= pl.s_max_m + pl.shift_m) {
        TurnRecord tr;
        tr.probe = static_cast<int>(pi);
        tr.turn = probe_count[pi];
        tr.r_mm = pl.recorded_r(std::hypot(xc, yc), s) * 1e3;
        tr.s_mm = (s - pl.shift_m) * 1e3;
        const double tcr = t + u * dt;
        tr.t_ns = tcr * 1e9;
        tr.energy_MeV = energy(y);
        tr.phase_deg = wrap_deg(kTwoPi * m.rf_MHz * 1e6 * tcr);
        turns.push_back(tr);
      }
    }
    t += dt;
    const double thn = std::atan2(y[1], y[0]);
    th += std::remainder(thn - std::remainder(th, kTwoPi), kTwoPi);
    if (path) {
      const double r = std::hypot(y[0], y[1]), P = std::sqrt(y[3] * y[3] + y[4] * y[4] + y[5] * y[5]);
      path->push_back({th * 180 / kPi, r * 1e3, y[2] * 1e3, (y[0] * y[3] + y[1] * y[4]) / (r * P) * 1e3, t * 1e9, energy(y)});
    }
  }
  if (!end.lost) end.status = "turn limit";
  end.turns = (th - th0) / kTwoPi;
  end.energy_MeV = energy(y);
  end.r_mm = std::hypot(y[0], y[1]) * 1e3;
  end.theta_deg = wrap_deg(th);
  end.t_ns = t * 1e9;
  return end;
}

}  // namespace turnfit::detail
