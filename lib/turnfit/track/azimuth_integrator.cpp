// Fifth-order Runge-Kutta (Dormand-Prince) in azimuth with steps of whole map cells; gap and
// probe crossings landed on exactly (the default integrator).
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "turnfit/physics/azimuth_eom.hpp"
#include "turnfit/track/integrators.hpp"

namespace turnfit::detail {
namespace {

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
  bool operator()(double th, const AzState& y, AzState& dy) {
    const double r = y[0], x = y[1], z = y[2], xz = y[3];
    FieldSample f;
    if (!m.field(r, th, f)) {
      return false;
    }
    AzimuthDerivs d;
    if (!azimuth_eom(r, x, z, xz, f, inv_brho, inv_v, d)) {
      return false;
    }
    dy = {d.dr, d.dx, d.dz, d.dxz, d.dt};
    return true;
  }
};

/// One step of the fifth-order Dormand-Prince solution (Hairer, Norsett, Wanner, Solving ODEs I,
/// Table II.5.2) used as a fixed-step method: on the PSI Ring map it reaches RK4's accuracy with
/// steps twice as long, and a fixed grid-aligned step keeps turn radii smooth functions of the
/// design variables (an adaptive step would not).
bool step_az(AzRhs& f, double th, double h, AzState& y) {
  static const double c[6] = {0, 1.0 / 5, 3.0 / 10, 4.0 / 5, 8.0 / 9, 1};
  static const double a[6][5] = {{0, 0, 0, 0, 0},
                                 {1.0 / 5, 0, 0, 0, 0},
                                 {3.0 / 40, 9.0 / 40, 0, 0, 0},
                                 {44.0 / 45, -56.0 / 15, 32.0 / 9, 0, 0},
                                 {19372.0 / 6561, -25360.0 / 2187, 64448.0 / 6561, -212.0 / 729, 0},
                                 {9017.0 / 3168, -355.0 / 33, 46732.0 / 5247, 49.0 / 176, -5103.0 / 18656}};
  static const double b[6] = {35.0 / 384, 0, 500.0 / 1113, 125.0 / 192, -2187.0 / 6784, 11.0 / 84};
  AzState k[6], t;
  for (int st = 0; st < 6; ++st) {
    for (int i = 0; i < 5; ++i) {
      double acc = y[i];
      for (int j = 0; j < st; ++j) acc += h * a[st][j] * k[j][i];
      t[i] = acc;
    }
    if (!f(th + c[st] * h, t, k[st])) return false;
  }
  for (int i = 0; i < 5; ++i) {
    double acc = 0;
    for (int st = 0; st < 6; ++st) acc += b[st] * k[st][i];
    y[i] += h * acc;
  }
  return true;
}
/// The step [rad]: the largest whole number of cells within `step_deg`, or the cell divided
/// by the smallest whole number that brings it within `step_deg`.
double azimuth_step(double cell, double step_deg) {
  const double want = (step_deg > 0 ? step_deg : kDefaultStepDeg) * kPi / 180;
  if (want >= cell) return cell * std::floor(want / cell + 1e-9);
  return cell / std::ceil(cell / want - 1e-9);
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

}  // namespace

TrackEnd track_azimuth(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                       std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path) {
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
  const double dnode = azimuth_step(g.dtheta_rad(), st.step_deg);
  const double node0 = g.theta_min_rad();
  const double mass = m.mass_MeV;
  auto energy = [&] { return (std::sqrt(1 + P * P) - 1) * mass; };
  // Losses are reported at the particle's last state (y, th), which the '# end' line repeats.
  auto lose = [&](const std::string& why) {
    end.lost = true;
    end.status = "lost: " + why + fmt(" at r = %.1f mm, azimuth %.2f deg, turn %.3f", y[0] * 1e3, wrap_deg(th),
                                      (th - th0) / kTwoPi);
  };
  // A step of h left the map: advance by the largest part of it that stays inside (bisection),
  // so the loss is reported where the particle reaches the edge, not a step earlier.
  auto to_edge = [&](double h) {
    double lo = 0, hi = h;
    AzState inside = y;
    for (int k = 0; k < 48; ++k) {
      const double mid = 0.5 * (lo + hi);
      AzState t = y;
      if (step_az(f, th, mid, t)) {
        lo = mid;
        inside = t;
      } else {
        hi = mid;
      }
    }
    th += lo;
    y = inside;
  };

  while (th < th_end - 1e-13) {
    double node = node0 + dnode * (std::floor((th - node0) / dnode + 1e-9) + 1);
    // A grid node within rounding of the end is the end (else the run would stop a hair
    // short and miss an element on the last azimuth).
    double stop = node > th_end - 1e-9 ? th_end : node;
    int which = -1;
    for (size_t i = 0; i < events.size(); ++i) {
      Event& e = events[i];
      if (e.next - th < 4 * dnode) {  // close: refresh with the current radius
        const double c = crossing_of(m, e, y[0]);
        if (!std::isnan(c)) e.next = nearest(c, e.next);
      }
      // An element exactly at the last azimuth (a probe at the injection azimuth after whole
      // turns) is crossed within the run: allow rounding of the unwrapped azimuths.
      const bool at_end = stop >= th_end && e.next <= th_end + 1e-9;
      if (e.next < stop || at_end) {
        stop = e.next;
        which = static_cast<int>(i);
      }
    }
    if (stop > th && !step_az(f, th, stop - th, y)) {
      to_edge(stop - th);
      lose("left the field map");
      break;
    }
    th = std::max(th, stop);
    if (path) path->push_back({th * 180 / kPi, y[0] * 1e3, y[2] * 1e3, y[1] * 1e3, y[4] * 1e9, energy()});
    if (which < 0) continue;
    Event& e = events[static_cast<size_t>(which)];
    // Land exactly on the element's line: its azimuth depends on r, so iterate.
    bool ok = true;
    for (int it = 0; it < 8; ++it) {
      const double c = crossing_of(m, e, y[0]);
      if (std::isnan(c)) break;
      const double d = nearest(c, th) - th;
      if (std::fabs(d) < 1e-14) break;
      if (!step_az(f, th, d, y)) {
        to_edge(d);
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
      kr.theta_deg = wrap_deg(th);
      kr.kick = m.gaps[e.index].kick(r * cth, r * sth, y[4], mass, m.charge_e, st.gap_physics, px, py, pz);
      if (kr.kick.stopped) {
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
        tr.r_mm = pl.recorded_r(r, s) * 1e3;
        tr.s_mm = (s - pl.shift_m) * 1e3;
        tr.t_ns = y[4] * 1e9;
        tr.energy_MeV = energy();
        tr.phase_deg = m.rf_MHz > 0 ? wrap_deg(kTwoPi * m.rf_MHz * 1e6 * y[4]) : kNaN;
        turns.push_back(tr);
      }
    }
    e.next = th + kTwoPi;  // refreshed from r when it comes close
  }
  if (!end.lost) end.status = "turn limit";
  end.turns = (th - th0) / kTwoPi;
  end.energy_MeV = energy();
  end.r_mm = y[0] * 1e3;
  end.theta_deg = wrap_deg(th);
  end.t_ns = y[4] * 1e9;
  return end;
}

}  // namespace turnfit::detail
