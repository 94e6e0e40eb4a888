// Tracking integrators: RK4 in azimuth on the map grid (default) and RK4 in time (OPAL's).
#include "turnfit/track/tracker.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>

#include "turnfit/physics/azimuth_eom.hpp"
#include "turnfit/physics/hermite.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kTwoPi = 2 * kPi;

std::string fmt(const char* f, double a, double b = 0, double c = 0) {
  char buf[160];
  std::snprintf(buf, sizeof buf, f, a, b, c);
  return buf;
}

/// Unwrapped azimuth closest above `after` (within one turn) for an azimuth in (-pi, pi].
double next_after(double th, double after) {
  double k = std::ceil((after - th) / kTwoPi);
  double v = th + k * kTwoPi;
  if (v <= after) v += kTwoPi;
  return v;
}

/// Unwrapped representative of th nearest to ref.
double nearest(double th, double ref) { return th + kTwoPi * std::round((ref - th) / kTwoPi); }

// ---------------------------------------------------------------------------------------------
// Azimuth integrator. State: r [m], x = p_r/p, z [m], xz = p_z/p, t [s]; p constant between gaps;
// equations in physics/azimuth_eom.hpp.
using AzState = std::array<double, 5>;

struct AzRhs {
  const TrackModel& m;
  double inv_brho = 0;  // sign(q) / (B rho)
  double inv_v = 0;
  double lost_r = 0;
  bool operator()(double th, const AzState& y, AzState& dy) {
    const double r = y[0], x = y[1], z = y[2], xz = y[3];
    FieldSample f;
    if (!m.field(r, th, f)) {
      lost_r = r;
      return false;
    }
    AzimuthDerivs d;
    if (!azimuth_eom(r, x, z, xz, f, inv_brho, inv_v, d)) {
      lost_r = r;
      return false;
    }
    dy = {d.dr, d.dx, d.dz, d.dxz, d.dt};
    return true;
  }
};

bool rk4_az(AzRhs& f, double th, double h, AzState& y) {
  AzState k1, k2, k3, k4, t;
  if (!f(th, y, k1)) return false;
  for (int i = 0; i < 5; ++i) t[i] = y[i] + 0.5 * h * k1[i];
  if (!f(th + 0.5 * h, t, k2)) return false;
  for (int i = 0; i < 5; ++i) t[i] = y[i] + 0.5 * h * k2[i];
  if (!f(th + 0.5 * h, t, k3)) return false;
  for (int i = 0; i < 5; ++i) t[i] = y[i] + h * k3[i];
  if (!f(th + h, t, k4)) return false;
  for (int i = 0; i < 5; ++i) y[i] += h / 6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]);
  return true;
}

struct Event {
  int kind;  // 0 gap, 1 probe
  int index;
  double next;  // unwrapped azimuth of the next crossing
  int count = 0;
};

double crossing_of(const TrackModel& m, const Event& e, double r) {
  return e.kind == 0 ? m.gaps[e.index].crossing_azimuth(r) : m.probes[e.index].crossing_azimuth(r);
}

TrackEnd track_azimuth(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                       std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks) {
  TrackEnd end;
  double P = std::sqrt(s0.px * s0.px + s0.py * s0.py + s0.pz * s0.pz);  // beta gamma
  double th = std::atan2(s0.y, s0.x);
  const double th0 = th;
  const double th_end = th0 + kTwoPi * st.turns;
  AzState y;
  y[0] = std::hypot(s0.x, s0.y);
  y[1] = (s0.px * std::cos(th) + s0.py * std::sin(th)) / P;
  y[2] = s0.z;
  y[3] = s0.pz / P;
  y[4] = s0.t;
  const double sign = m.charge_e >= 0 ? 1.0 : -1.0;
  auto set_momentum = [&](AzRhs& f) {
    const double gamma = std::sqrt(1 + P * P);
    const double brho = P * m.mass_MeV * 1e6 / (kSpeedOfLight * std::fabs(m.charge_e));
    f.inv_brho = sign / brho;
    f.inv_v = gamma / (P * kSpeedOfLight);
  };
  AzRhs f{m};
  set_momentum(f);

  std::vector<Event> events;
  for (size_t g = 0; g < m.gaps.size(); ++g) events.push_back({0, static_cast<int>(g), 0.0});
  for (size_t p = 0; p < m.probes.size(); ++p) events.push_back({1, static_cast<int>(p), 0.0});
  for (auto& e : events) {
    const double c = crossing_of(m, e, y[0]);
    e.next = std::isnan(c) ? std::numeric_limits<double>::infinity() : next_after(c, th + 1e-12);
  }
  const PolarGrid& g = m.map.grid();
  const double dnode = g.dtheta_rad() / std::max(1, st.steps_per_cell);
  const double node0 = g.theta_min_rad();
  const double mass = m.mass_MeV;
  auto energy = [&] { return (std::sqrt(1 + P * P) - 1) * mass; };
  auto lose = [&](const std::string& why) {
    end.lost = true;
    end.status = "lost: " + why + fmt(" at r = %.1f mm, azimuth %.2f deg, turn %.3f", f.lost_r * 1e3,
                                      std::remainder(th, kTwoPi) * 180 / kPi, (th - th0) / kTwoPi);
  };

  while (th < th_end - 1e-13) {
    double node = node0 + dnode * (std::floor((th - node0) / dnode + 1e-9) + 1);
    double stop = std::min(node, th_end);
    int which = -1;
    for (size_t i = 0; i < events.size(); ++i) {
      Event& e = events[i];
      if (e.next - th < 4 * dnode) {  // close: refresh with the current radius
        const double c = crossing_of(m, e, y[0]);
        if (!std::isnan(c)) e.next = nearest(c, e.next);
      }
      if (e.next < stop) {
        stop = e.next;
        which = static_cast<int>(i);
      }
    }
    if (stop > th && !rk4_az(f, th, stop - th, y)) {
      lose("left the field map");
      break;
    }
    th = std::max(th, stop);
    if (which < 0) continue;
    Event& e = events[static_cast<size_t>(which)];
    // Land exactly on the element's line: its azimuth depends on r, so iterate.
    bool ok = true;
    for (int it = 0; it < 8; ++it) {
      const double c = crossing_of(m, e, y[0]);
      if (std::isnan(c)) break;
      const double d = nearest(c, th) - th;
      if (std::fabs(d) < 1e-14) break;
      if (!rk4_az(f, th, d, y)) {
        ok = false;
        break;
      }
      th += d;
    }
    if (!ok) {
      lose("left the field map");
      break;
    }
    const double r = y[0], cth = std::cos(th), sth = std::sin(th);
    ++e.count;
    if (e.kind == 0) {
      const double sxy = std::sqrt(std::max(0.0, 1 - y[1] * y[1] - y[3] * y[3]));
      double px = P * (y[1] * cth - sxy * sth), py = P * (y[1] * sth + sxy * cth);
      const double pz = P * y[3];
      KickRecord kr;
      kr.gap = e.index;
      kr.turn = e.count;
      kr.theta_deg = std::remainder(th, kTwoPi) * 180 / kPi;
      kr.kick = m.gaps[e.index].kick(r * cth, r * sth, y[4], mass, m.charge_e, st.gap_physics, px, py, pz);
      if (kr.kick.stopped) {
        f.lost_r = r;
        if (kicks) kicks->push_back(kr);
        lose("stopped by gap '" + m.gaps[e.index].name() + "'");
        break;
      }
      if (kr.kick.active) {
        P = std::sqrt(px * px + py * py + pz * pz);
        y[1] = (px * cth + py * sth) / P;
        y[3] = pz / P;
        set_momentum(f);
      }
      if (kicks) kicks->push_back(kr);
    } else {
      const ProbeLine& pl = m.probes[e.index];
      const double s = pl.along(r * cth, r * sth);
      if (s >= pl.s_min_m + pl.shift_m && s <= pl.s_max_m + pl.shift_m) {
        TurnRecord tr;
        tr.probe = e.index;
        tr.turn = e.count;
        tr.r_mm = (r - pl.shift_m) * 1e3;
        tr.s_mm = (s - pl.shift_m) * 1e3;
        tr.t_ns = y[4] * 1e9;
        tr.energy_MeV = energy();
        tr.phase_deg = m.rf_MHz > 0 ? std::remainder(kTwoPi * m.rf_MHz * 1e6 * y[4], kTwoPi) * 180 / kPi : kNaN;
        turns.push_back(tr);
      }
    }
    e.next = th + kTwoPi;  // refreshed from r when it comes close
  }
  if (!end.lost) end.status = "turn limit";
  end.turns = (th - th0) / kTwoPi;
  end.energy_MeV = energy();
  end.r_mm = y[0] * 1e3;
  end.theta_deg = std::remainder(th, kTwoPi) * 180 / kPi;
  end.t_ns = y[4] * 1e9;
  return end;
}

// ---------------------------------------------------------------------------------------------
// Time integrator: Cartesian RK4 with a fixed step dt = h / (steps_per_turn f_rf), as OPAL-cycl.
using TState = std::array<double, 6>;  // x, y, z [m], px, py, pz [beta gamma]

struct TimeRhs {
  const TrackModel& m;
  double k;  // q c^2 / (m c^2) [1 / (T s)] times sign: d(beta gamma)/dt = k (p/gamma) x B
  double lost_r = 0;
  bool operator()(const TState& s, TState& d) {
    const double r = std::hypot(s[0], s[1]);
    const double th = std::atan2(s[1], s[0]);
    FieldSample f;
    if (!m.field(r, th, f)) {
      lost_r = r;
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

TrackEnd track_time(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                    std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks) {
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
    end.status = "lost: " + why + fmt(" at r = %.1f mm, azimuth %.2f deg, turn %.3f", f.lost_r * 1e3,
                                      std::remainder(th, kTwoPi) * 180 / kPi, (th - th0) / kTwoPi);
  };
  TState d0, d1;
  while (th < th_end) {
    const TState y0 = y;
    if (!rk4_t(f, dt, y)) {
      lose("left the field map");
      break;
    }
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
        f.lost_r = std::hypot(yc[0], yc[1]);
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
        tr.r_mm = (std::hypot(xc, yc) - pl.shift_m) * 1e3;
        tr.s_mm = (s - pl.shift_m) * 1e3;
        const double tcr = t + u * dt;
        tr.t_ns = tcr * 1e9;
        tr.energy_MeV = energy(y);
        tr.phase_deg = std::remainder(kTwoPi * m.rf_MHz * 1e6 * tcr, kTwoPi) * 180 / kPi;
        turns.push_back(tr);
      }
    }
    t += dt;
    const double thn = std::atan2(y[1], y[0]);
    th += std::remainder(thn - std::remainder(th, kTwoPi), kTwoPi);
  }
  if (!end.lost) end.status = "turn limit";
  end.turns = (th - th0) / kTwoPi;
  end.energy_MeV = energy(y);
  end.r_mm = std::hypot(y[0], y[1]) * 1e3;
  end.theta_deg = std::remainder(th, kTwoPi) * 180 / kPi;
  end.t_ns = t * 1e9;
  return end;
}

}  // namespace

std::vector<std::pair<std::string, std::string>> list_integrators() {
  return {{"azimuth", "RK4 in azimuth, steps aligned with the field map grid, exact gap and probe crossings (default)"},
          {"rk4", "RK4 in time with --steps-per-turn fixed steps (OPAL-cycl's scheme), crossings interpolated"}};
}

ParticleState injection_state(const Injection& inj, double mass_MeV) {
  ParticleState s;
  const double gamma = 1 + inj.energy_MeV / mass_MeV;
  const double P = std::sqrt(gamma * gamma - 1);
  const double pr = inj.pr_betagamma, pz = inj.pz_betagamma;
  const double pt = std::sqrt(std::max(0.0, P * P - pr * pr - pz * pz));
  const double th = inj.phi_deg * kPi / 180, r = inj.r_mm * 1e-3;
  s.x = r * std::cos(th);
  s.y = r * std::sin(th);
  s.z = inj.z_mm * 1e-3;
  s.px = pr * std::cos(th) - pt * std::sin(th);
  s.py = pr * std::sin(th) + pt * std::cos(th);
  s.pz = pz;
  s.t = inj.t_ns * 1e-9;
  return s;
}

double kinetic_energy(const ParticleState& s, double mass_MeV) {
  return (std::sqrt(1 + s.px * s.px + s.py * s.py + s.pz * s.pz) - 1) * mass_MeV;
}

TrackEnd track_particle(const TrackModel& model, const ParticleState& start, const TrackSettings& settings,
                        std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks) {
  if (settings.integrator == "rk4") return track_time(model, start, settings, turns, kicks);
  return track_azimuth(model, start, settings, turns, kicks);
}

}  // namespace turnfit
