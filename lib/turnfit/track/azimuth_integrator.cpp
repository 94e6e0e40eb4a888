// Fifth-order Runge-Kutta (Dormand-Prince) in azimuth with steps of whole map cells; gap and
// probe crossings landed on exactly (the default integrator). Two drivers share one particle
// (AzParticle: its state, its gap and probe events, what it records): the reference stepper
// takes one particle with every field sample through TrackModel::field; the group stepper
// takes up to kMaxLanes particles that start at one azimuth through the same grid steps
// together, sampling the main field from precomputed rows (FieldRowTable) at the stage
// azimuths, which every grid step repeats. The particles of a group may each have a model of
// their own (an optimizer's designs), as long as the models share the map.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/physics/azimuth_eom.hpp"
#include "turnfit/track/integrators.hpp"
#include "turnfit/track/lane_clones.hpp"

namespace turnfit::detail {
namespace {

/// Unwrapped azimuth closest above `after` (within one turn) for an azimuth in (-pi, pi].
double next_after(double th, double after) {
  double k = std::ceil((after - th) / kTwoPi);
  double v = th + k * kTwoPi;
  if (v <= after) v += kTwoPi;
  return v;
}

/// th in [0, 2 pi): the fast steppers hand the field's effects azimuths within a turn, once
/// per stage for every lane (the effects' own reductions then take no floor).
double within_turn(double th) {
  const double a = th - kTwoPi * std::floor(th * (1 / kTwoPi));
  return a >= 0 && a < kTwoPi ? a : 0.0;
}

/// Unwrapped representative of th nearest to ref.
double nearest(double th, double ref) { return th + kTwoPi * std::round((ref - th) / kTwoPi); }

// ---------------------------------------------------------------------------------------------
// Azimuth integrator. State: r [m], x = p_r/p, z [m], xz = p_z/p, t [s]; p constant between gaps;
// equations in physics/azimuth_eom.hpp.
using AzState = std::array<double, 5>;

// The fifth-order Dormand-Prince solution (Hairer, Norsett, Wanner, Solving ODEs I, Table
// II.5.2) used as a fixed-step method: on the PSI Ring map it reaches RK4's accuracy with steps
// twice as long, and a fixed grid-aligned step keeps turn radii smooth functions of the design
// variables (an adaptive step would not).
constexpr int kStages = 6;
constexpr double kC[kStages] = {0, 1.0 / 5, 3.0 / 10, 4.0 / 5, 8.0 / 9, 1};
constexpr double kA[kStages][5] = {{0, 0, 0, 0, 0},
                                   {1.0 / 5, 0, 0, 0, 0},
                                   {3.0 / 40, 9.0 / 40, 0, 0, 0},
                                   {44.0 / 45, -56.0 / 15, 32.0 / 9, 0, 0},
                                   {19372.0 / 6561, -25360.0 / 2187, 64448.0 / 6561, -212.0 / 729, 0},
                                   {9017.0 / 3168, -355.0 / 33, 46732.0 / 5247, 49.0 / 176, -5103.0 / 18656}};
constexpr double kB[kStages] = {35.0 / 384, 0, 500.0 / 1113, 125.0 / 192, -2187.0 / 6784, 11.0 / 84};

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

/// One step of h from th; false (y untouched) when a stage left the map.
bool step_az(AzRhs& f, double th, double h, AzState& y) {
  AzState k[kStages], t;
  for (int st = 0; st < kStages; ++st) {
    for (int i = 0; i < 5; ++i) {
      double acc = y[i];
      for (int j = 0; j < st; ++j) acc += h * kA[st][j] * k[j][i];
      t[i] = acc;
    }
    if (!f(th + kC[st] * h, t, k[st])) return false;
  }
  for (int i = 0; i < 5; ++i) {
    double acc = 0;
    for (int st = 0; st < kStages; ++st) acc += kB[st] * k[st][i];
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

/// One particle of the azimuth integrator: state, events, records.
struct AzParticle {
  const TrackModel& m;
  const TrackSettings& st;
  std::vector<TurnRecord>* turns;
  std::vector<KickRecord>* kicks;
  std::vector<PathPoint>* path;
  AzRhs f;
  AzState y{};
  double P = 0;  // beta gamma
  double th = 0, th0 = 0, th_end = 0;
  double dnode = 0, node0 = 0;
  std::vector<Event> events;
  /// The soonest e.next as next_event last saw them all (-inf: not known); see next_event.
  double soonest = -std::numeric_limits<double>::infinity();
  TrackEnd end;
  /// How close land_and_act lands on an element's line [rad]: the reference stepper 1e-14, the
  /// group stepper 1e-12 (3e-12 m along a 3 m orbit), which saves it a step at most crossings.
  double landing_tol = 1e-14;
  int cell = -1;  // radial map cell of the last row-table sample (PolarFieldMap::sample_row_near)
  TrackModel::CoilHints coil_hints;  // its places in the summed coil tables

  AzParticle(const TrackModel& model, const ParticleState& s0, const TrackSettings& settings,
             std::vector<TurnRecord>* t, std::vector<KickRecord>* k, std::vector<PathPoint>* p)
      : m(model), st(settings), turns(t), kicks(k), path(p), f{model} {
    P = std::sqrt(s0.px * s0.px + s0.py * s0.py + s0.pz * s0.pz);
    th = start_azimuth(s0);
    th0 = th;
    th_end = th0 + kTwoPi * st.turns;
    y[0] = std::hypot(s0.x, s0.y);
    y[1] = (s0.px * std::cos(th) + s0.py * std::sin(th)) / P;
    y[2] = s0.z;
    y[3] = s0.pz / P;
    y[4] = s0.t;
    set_momentum();
    for (size_t g = 0; g < m.gaps.size(); ++g) events.push_back({0, static_cast<int>(g), 0.0});
    for (size_t q = 0; q < m.probes.size(); ++q) events.push_back({1, static_cast<int>(q), 0.0});
    for (auto& e : events) {
      const double c = crossing_of(m, e, y[0]);
      e.next = std::isnan(c) ? std::numeric_limits<double>::infinity() : next_after(c, th + 1e-12);
    }
    const PolarGrid& g = m.map.grid();
    dnode = azimuth_step(g.dtheta_rad(), st.step_deg);
    node0 = g.theta_min_rad();
  }

  /// The azimuth a particle starts from (the group stepper groups particles by it).
  static double start_azimuth(const ParticleState& s) { return std::atan2(s.y, s.x); }

  void set_momentum() {
    const double sign = m.charge_e >= 0 ? 1.0 : -1.0;
    const double gamma = std::sqrt(1 + P * P);
    const double brho = P * m.mass_MeV * 1e6 / (kSpeedOfLight * std::fabs(m.charge_e));
    f.inv_brho = sign / brho;
    f.inv_v = gamma / (P * kSpeedOfLight);
  }
  double energy() const { return (std::sqrt(1 + P * P) - 1) * m.mass_MeV; }
  bool running() const { return !end.lost && th < th_end - 1e-13; }

  /// The next grid node after th, or the end when a node is within rounding of it (else the
  /// run would stop a hair short and miss an element on the last azimuth).
  double node_stop(double from) const {
    const double node = node0 + dnode * (std::floor((from - node0) / dnode + 1e-9) + 1);
    return node > th_end - 1e-9 ? th_end : node;
  }

  /// The earliest event before `stop` (which it then becomes), or -1. Events close to th are
  /// refreshed from the current radius first.
  int next_event(double& stop) {
    // Nothing to refresh and nothing before stop while the soonest event is 4 steps ahead and
    // not before stop (the loop below would find so, event by event: e.next - th is no smaller
    // for a later e.next); most grid steps of a turn. (A step to the run's end goes the whole
    // way: an element at the last azimuth.)
    if (soonest - th >= 4 * dnode && stop <= soonest && stop < th_end) return -1;
    int which = -1;
    soonest = std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < events.size(); ++i) {
      Event& e = events[i];
      if (e.next - th < 4 * dnode) {
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
      soonest = std::min(soonest, e.next);
    }
    return which;
  }

  // Losses are reported at the particle's last state (y, th), which the '# end' line repeats.
  void lose(const std::string& why) {
    end.lost = true;
    end.status = "lost: " + why + fmt(" at r = %.1f mm, azimuth %.2f deg, turn %.3f", y[0] * 1e3, wrap_deg(th),
                                      (th - th0) / kTwoPi);
  }
  /// A step of h left the map: advance by the largest part of it that stays inside (bisection),
  /// so the loss is reported where the particle reaches the edge, not a step earlier.
  void to_edge(double h) {
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
  }
  /// After a step of h that left the map (y untouched): the loss.
  void left_map(double h) {
    to_edge(h);
    lose("left the field map");
  }
  /// Steps to `stop` (when ahead) with the reference field; false (and lost) if it left the map.
  bool step_to(double stop) {
    if (stop > th && !step_az(f, th, stop - th, y)) {
      left_map(stop - th);
      return false;
    }
    th = std::max(th, stop);
    record_path();
    return true;
  }
  void record_path() {
    if (path) path->push_back({th * 180 / kPi, y[0] * 1e3, y[2] * 1e3, y[1] * 1e3, y[4] * 1e9, energy()});
  }

  /// Lands exactly on event `which`'s line (its azimuth depends on r, so iteratively) and acts:
  /// a gap kicks, a probe records. False when the particle was lost.
  bool land_and_act(int which) {
    Event& e = events[static_cast<size_t>(which)];
    for (int it = 0; it < 8; ++it) {
      const double c = crossing_of(m, e, y[0]);
      if (std::isnan(c)) break;
      double d = nearest(c, th) - th;
      // The line is met where g(theta) = c(r(theta)) - theta = 0. Newton's step d / (1 - c' r')
      // (c' by a difference, r' = r x / s) leaves an error of about 1e-3 d^2, and d is a few
      // 1e-5 rad after the step to the estimate for a particle near its orbit: one or two
      // steps. The plain iteration theta <- c(r) contracts only by c' r', which a particle far
      // off its orbit (r' ~ 1) takes to -0.3: after 8 steps it was still 1e-6 rad (6e-4 mm)
      // off the line.
      const double dr = 1e-7 * y[0];
      const double c2 = crossing_of(m, e, y[0] + dr);
      const double s2 = 1 - y[1] * y[1] - y[3] * y[3];
      if (!std::isnan(c2) && s2 > 0) {
        const double slope = remainder_two_pi(c2 - c) / dr * (y[0] * y[1] / std::sqrt(s2));
        if (std::fabs(1 - slope) > 0.25) d /= 1 - slope;  // (near 1 the line is met tangentially)
      }
      if (std::fabs(d) < landing_tol) break;
      if (!step_az(f, th, d, y)) {
        left_map(d);
        return false;
      }
      th += d;
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
      kr.kick = m.gaps[e.index].kick(r * cth, r * sth, y[4], m.mass_MeV, m.charge_e, st.gap_physics, px, py, pz);
      if (kr.kick.stopped) {
        if (kicks) kicks->push_back(kr);
        lose("stopped by gap '" + m.gaps[e.index].name() + "'");
        return false;
      }
      if (kr.kick.active) {
        P = std::sqrt(px * px + py * py + pz * pz);
        y[1] = (px * cth + py * sth) / P;
        y[3] = pz / P;
        set_momentum();
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
        turns->push_back(tr);
      }
    }
    e.next = th + kTwoPi;  // refreshed from r when it comes close
    soonest = -std::numeric_limits<double>::infinity();  // next_event looks at every event again
    return true;
  }

  TrackEnd finish() {
    if (!end.lost) end.status = "turn limit";
    end.turns = (th - th0) / kTwoPi;
    end.energy_MeV = energy();
    end.r_mm = y[0] * 1e3;
    end.theta_deg = wrap_deg(th);
    end.t_ns = y[4] * 1e9;
    return end;
  }
};

/// Where each stage of a grid step of `cells` whole cells samples: the cell offset from the
/// step's first cell and the slot of its sub-cell offset in the row table.
struct StageCells {
  int dj[kStages];
  int slot[kStages];
  std::vector<double> v;  // the table's offsets
};

StageCells stage_cells(int cells) {
  StageCells s;
  for (int st = 0; st < kStages; ++st) {
    const double pos = kC[st] * cells;
    double whole = std::floor(pos + 1e-12);
    double v = pos - whole;
    if (v < 1e-12) v = 0;
    s.dj[st] = static_cast<int>(whole);
    auto it = std::find(s.v.begin(), s.v.end(), v);
    s.slot[st] = static_cast<int>(it - s.v.begin());
    if (it == s.v.end()) s.v.push_back(v);
  }
  return s;
}

/// Whether two models' azimuth_terms are the same at every azimuth (the same n and phase of
/// each harmonic that has terms; no harmonics, or effects off, in both).
bool same_azimuth_terms(const TrackModel& a, const TrackModel& b) {
  const bool ha = a.effects.active && !a.effects.harmonics.empty();
  const bool hb = b.effects.active && !b.effects.harmonics.empty();
  if (!ha || !hb) return ha == hb;
  const size_t na = std::min(a.effects.harmonics.size(), TrackModel::kAzimuthHarmonics);
  const size_t nb = std::min(b.effects.harmonics.size(), TrackModel::kAzimuthHarmonics);
  if (na != nb) return false;
  for (size_t k = 0; k < na; ++k)
    if (a.effects.harmonics[k].n != b.effects.harmonics[k].n ||
        a.effects.harmonics[k].phase_rad != b.effects.harmonics[k].phase_rad)
      return false;
  return true;
}

/// The azimuth's part of the field (TrackModel::azimuth_terms) at the stage azimuths of each
/// grid step of a turn, computed on first use: every turn repeats them.
struct TermCache {
  bool used = false;
  long long steps = 0;  // grid steps per turn
  double node0 = 0, dnode = 0;
  std::vector<TrackModel::AzimuthTerms> terms;
  std::vector<char> known;
  TermCache(const TrackModel& m, double node0_, double dnode_) : node0(node0_), dnode(dnode_) {
    if (!m.effects.active || m.effects.harmonics.empty()) return;
    const double per_turn = kTwoPi / dnode;
    steps = std::llround(per_turn);
    if (steps < 1 || std::fabs(per_turn - static_cast<double>(steps)) > 1e-9 || steps > 1000000) return;
    used = true;
    terms.resize(static_cast<size_t>(steps) * kStages);
    known.assign(terms.size(), 0);
  }
  /// The terms of stage st of the grid step from grid node `node`; nullptr without a cache.
  const TrackModel::AzimuthTerms* at(const TrackModel& m, long long node, int st) {
    if (!used) return nullptr;
    long long k = node % steps;
    if (k < 0) k += steps;
    const size_t i = static_cast<size_t>(k) * kStages + static_cast<size_t>(st);
    if (!known[i]) {
      // From the node's place in the turn and the nominal step, not from this step's th and h
      // (which carry the rounding of the unwrapped azimuth): whichever turn, and whichever
      // particle of a group, comes first, the terms are the same, so a particle's numbers do
      // not depend on its group.
      m.azimuth_terms(node0 + static_cast<double>(k) * dnode + kC[st] * dnode, terms[i]);
      known[i] = 1;
    }
    return &terms[i];
  }
};

/// The equations of motion of physics/azimuth_eom.hpp for the fast steppers, arranged so that
/// the field enters last (r / (B rho) and the other factors are ready before it: a single
/// particle's step is one dependency chain through the field samples). The same numbers as
/// azimuth_eom to rounding. s2 = 1 - x^2 - xz^2 <= 0 (no azimuthal momentum left) is the
/// caller's to test: it gives finite numbers here, to be dropped.
inline void fast_eom(double r, double x, double z, double xz, double bz, double br, double bt, double inv_brho,
                     double inv_v, double& dr, double& dx, double& dz, double& dxz, double& dt) {
  // The chain that bounds a single track runs x -> s -> dx -> x (the next stage's x): the
  // vertical part is subtracted first and the field's part added to s last, so that the chain
  // holds one product, one subtraction, the square root and one addition. (In the midplane,
  // xz = z = 0, the numbers are those of the order before, (1 - x^2) - xz^2 and
  // (s + zt bt) - rib bz, bit for bit; off it they differ by rounding.)
  const double s2 = (1 - xz * xz) - x * x;
  const double s = std::sqrt(std::fabs(s2));
  const double r_s = r / s, inv_s = 1 / s;
  const double rib = r * inv_brho, zt = xz * inv_s * z * inv_brho;
  dr = r_s * x;
  dx = s + (zt * bt - rib * bz);
  dz = r_s * xz;
  dxz = z * (rib * br - x * inv_s * inv_brho * bt);
  dt = r_s * inv_v;
}

/// One particle through a grid step (group_step's case n = 1): step_az with the main field
/// from the row table. A single track is one long dependency chain, which the lane loops
/// below only lengthen.
bool lane_step(AzParticle& p, double th, double h, int j0, const StageCells& sc, const FieldRowTable& tab,
               TermCache& cache, long long node) {
  const TrackModel& m = p.m;
  const bool rest = !m.main_field_only();
  const int nt = tab.ntheta;
  AzState k[kStages], t;
  const AzState& y = p.y;
  for (int st = 0; st < kStages; ++st) {
    for (int i = 0; i < 5; ++i) {
      double acc = y[i];
      for (int q = 0; q < st; ++q) acc += h * kA[st][q] * k[q][i];
      t[i] = acc;
    }
    FieldSample f;
    if (!m.map.sample_row_near(tab, t[0], (j0 + sc.dj[st]) % nt, sc.slot[st], p.cell, f)) return false;
    // (add_to_main_lanes' expressions are add_to_main's, so a lane gets these numbers in a
    // group; the loops over lanes would only lengthen a lone particle's chain.)
    if (rest) m.add_to_main(t[0], within_turn(th + kC[st] * h), f, cache.at(m, node, st), &p.coil_hints);
    if (!(1 - t[1] * t[1] - t[3] * t[3] > 0)) return false;
    fast_eom(t[0], t[1], t[2], t[3], f.bz_T, f.dbz_dr_T_m, f.dbz_dth_T, p.f.inv_brho, p.f.inv_v, k[st][0], k[st][1],
             k[st][2], k[st][3], k[st][4]);
  }
  for (int i = 0; i < 5; ++i) {
    double acc = 0;
    for (int st = 0; st < kStages; ++st) acc += kB[st] * k[st][i];
    p.y[i] += h * acc;
  }
  return true;
}

/// One grid step of h from the node th (in cell j0) for the lanes L[0..n), main field from the
/// row table; ok[l] false for a lane a stage of which left the map or lost its azimuthal
/// momentum (its state untouched). The arithmetic is step_az's, lane by lane.
TURNFIT_LANE_CLONES
void group_step(AzParticle* const* L, int n, double th, double h, int j0, const StageCells& sc,
                const FieldRowTable& tab, TermCache* const* cache, long long node, bool* ok) {
  if (n == 1) {
    ok[0] = lane_step(*L[0], th, h, j0, sc, tab, *cache[0], node);
    return;
  }
  // Structure of arrays over the lanes: the stage states and the equations of motion are loops
  // over lanes that the compiler vectorizes; the map's samples go eight lanes at a time with
  // AVX-512 (PolarFieldMap::sample_rows_near), the effects lane by lane. The
  // expressions are lane_step's, term for term (so a lane's numbers do not depend on whether it
  // stepped alone or in a group).
  // The lanes' models share the map (track_azimuth_group); their coils and effects may differ
  // (an optimizer's designs), and then each lane adds its own as lane_step does.
  const TrackModel& m = L[0]->m;
  bool one_model = true;
  for (int l = 1; l < n; ++l) one_model = one_model && &L[l]->m == &m;
  const bool rest = !one_model || !m.main_field_only();
  const int nt = tab.ntheta;
  double y[5][kMaxLanes], k[kStages][5][kMaxLanes], t[5][kMaxLanes];
  double ib[kMaxLanes], iv[kMaxLanes], bz[kMaxLanes], br[kMaxLanes], bt[kMaxLanes];
  unsigned char good[kMaxLanes], noaz[kMaxLanes];
  TrackModel::CoilHints* hints[kMaxLanes];
  int cell[kMaxLanes];
  for (int l = 0; l < n; ++l) {
    for (int i = 0; i < 5; ++i) y[i][l] = L[l]->y[static_cast<size_t>(i)];
    cell[l] = L[l]->cell;
    ib[l] = L[l]->f.inv_brho;
    iv[l] = L[l]->f.inv_v;
    good[l] = 1;
    noaz[l] = 0;
    hints[l] = &L[l]->coil_hints;
  }
  for (int st = 0; st < kStages; ++st) {
    // t = y + sum_q (h a_q) k_q, summed in step_az's order.
    for (int i = 0; i < 5; ++i)
      for (int l = 0; l < n; ++l) t[i][l] = y[i][l];
    for (int q = 0; q < st; ++q) {
      const double ha = h * kA[st][q];
      for (int i = 0; i < 5; ++i)
        for (int l = 0; l < n; ++l) t[i][l] += ha * k[q][i][l];
    }
    const double ths = within_turn(th + kC[st] * h);
    const int j = (j0 + sc.dj[st]) % nt;
    const int slot = sc.slot[st];
    const TrackModel::AzimuthTerms* terms = rest && one_model ? cache[0]->at(m, node, st) : nullptr;
    // The cell guess as lane_step keeps it: a lane's numbers do not depend on its group.
    m.map.sample_rows_near(tab, n, t[0], j, slot, cell, bz, br, bt, good);
    if (rest) {
      // A lane off the map (its radius may not even be finite) is given the map's inner edge
      // instead: the effects get a radius they can take, and the lane drops what they give.
      double r[kMaxLanes];
      for (int l = 0; l < n; ++l) r[l] = good[l] ? t[0][l] : m.map.grid().r_min_m();
      if (one_model) {
        m.add_to_main_lanes(n, r, ths, bz, br, bt, terms, hints);
      } else {
        const TrackModel* ms[kMaxLanes];
        const TrackModel::AzimuthTerms* lane_terms[kMaxLanes];
        for (int l = 0; l < n; ++l) {
          ms[l] = &L[l]->m;
          lane_terms[l] = ms[l]->main_field_only() ? nullptr : cache[l]->at(*ms[l], node, st);
        }
        TrackModel::add_to_main_models(n, ms, r, ths, bz, br, bt, lane_terms, hints);
      }
    }
    for (int l = 0; l < n; ++l) noaz[l] |= !(1 - t[1][l] * t[1][l] - t[3][l] * t[3][l] > 0);
    // (A lane without azimuthal momentum left is dropped below, as step_az drops it.)
    for (int l = 0; l < n; ++l)
      fast_eom(t[0][l], t[1][l], t[2][l], t[3][l], bz[l], br[l], bt[l], ib[l], iv[l], k[st][0][l], k[st][1][l],
               k[st][2][l], k[st][3][l], k[st][4][l]);
  }
  for (int l = 0; l < n; ++l) {
    L[l]->cell = cell[l];
    ok[l] = good[l] != 0 && noaz[l] == 0;
    if (!ok[l]) continue;
    AzState& yl = L[l]->y;
    for (int i = 0; i < 5; ++i) {
      double acc = 0;
      for (int st = 0; st < kStages; ++st) acc += kB[st] * k[st][i][l];
      yl[static_cast<size_t>(i)] += h * acc;
    }
  }
}


/// The group stepper's run over up to kMaxLanes particles that start at one azimuth on one map,
/// a grid node at a time (step_node), so that a caller may act on the lanes between nodes (the
/// space-charge driver kicks them there). Run node by node to the end, it is the group stepper.
struct GroupRun {
  std::vector<std::unique_ptr<AzParticle>> lane;
  GroupOutput* out;
  std::shared_ptr<const FieldRowTable> tab;
  StageCells sc{};
  long long cells_per_step = 1;
  int nt = 0;
  double dnode = 0, node0 = 0;
  std::vector<std::unique_ptr<TermCache>> caches;
  TermCache* lane_cache[kMaxLanes];
  double th = 0, th_end = 0;

  GroupRun(const TrackModel* const* ms, const ParticleState* s0, size_t n, const TrackSettings& st, GroupOutput* o)
      : out(o) {
    const TrackModel& m = *ms[0];
    for (size_t l = 0; l < n; ++l) {
      lane.push_back(std::make_unique<AzParticle>(*ms[l], s0[l], st, out[l].turns, out[l].kicks, out[l].path));
      lane.back()->landing_tol = 1e-12;
    }
    const PolarGrid& g = m.map.grid();
    const double cell = g.dtheta_rad();
    dnode = lane[0]->dnode;
    node0 = lane[0]->node0;
    const double cells = dnode / cell;
    // The row table serves steps of whole cells of the spline map (OPAL's bilinear map and
    // fractions of a cell sample the reference way).
    if (!m.opal_map && cells > 0.5 && std::fabs(cells - std::round(cells)) < 1e-9) {
      cells_per_step = static_cast<int>(std::round(cells));
      sc = stage_cells(static_cast<int>(cells_per_step));
      tab = m.map.row_table(sc.v);
    }
    nt = g.ntheta;
    // One cache of azimuth terms per set of harmonic azimuths: the terms depend only on each
    // harmonic's n and phase, so models that share them (an optimizer's designs that differ in
    // anything else) share one cache, computed once and kept in cache once.
    std::vector<const TrackModel*> cached;
    for (size_t l = 0; l < n; ++l) {
      const auto same = [&](const TrackModel* c) { return same_azimuth_terms(*c, *ms[l]); };
      const size_t c = static_cast<size_t>(std::find_if(cached.begin(), cached.end(), same) - cached.begin());
      if (c == cached.size()) {
        cached.push_back(ms[l]);
        caches.push_back(std::make_unique<TermCache>(*ms[l], node0, dnode));
      }
      lane_cache[l] = caches[c].get();
    }
    th = lane[0]->th;
    th_end = lane[0]->th_end;
  }

  bool running() const { return th < th_end - 1e-13; }

  /// Takes every lane to the next grid node (or the end); false when the run had ended.
  bool step_node() {
    if (!running()) return false;
    TermCache* group_cache[kMaxLanes];
    AzParticle* group[kMaxLanes];
    bool ok[kMaxLanes];
    const double stop = lane[0]->node_stop(th);
    // A whole grid step from a node: the row table's azimuths.
    const bool grid_step = tab && std::fabs(stop - th - dnode) < 1e-9 * dnode;
    int ng = 0;
    // Each lane runs the reference's iterations (AzParticle::node_stop, next_event, a step,
    // landing) up to this node; the whole grid step from the group's node, without an element
    // in it, it takes with the group. A lane that landed within rounding of the node or past
    // it goes on from there next time, as alone it would.
    for (auto& p : lane) {
      while (p->running()) {
        // (A lane on the group's node stops where the group does: node_stop depends only on
        // the grid, the settings and the start azimuth, which the lanes share.)
        double s = p->th == th ? stop : p->node_stop(p->th);
        if (s > stop) break;
        const int which = p->next_event(s);
        if (which < 0 && grid_step && p->th == th) {
          group_cache[ng] = lane_cache[&p - lane.data()];
          group[ng++] = p.get();
          break;
        }
        if (!p->step_to(s) || (which >= 0 && !p->land_and_act(which))) break;
      }
    }
    if (ng > 0) {
      // The node's index, and the cell it starts (th is within rounding of a node).
      const long long node = static_cast<long long>(std::floor((th - node0) / dnode + 0.5));
      int j0 = static_cast<int>((node * cells_per_step) % nt);
      if (j0 < 0) j0 += nt;
      group_step(group, ng, th, stop - th, j0, sc, *tab, group_cache, node, ok);
      for (int l = 0; l < ng; ++l) {
        AzParticle& p = *group[l];
        if (!ok[l]) {
          p.left_map(stop - th);
          continue;
        }
        p.th = stop;
        p.record_path();
      }
    }
    th = stop;
    return true;
  }

  void finish() {
    for (size_t l = 0; l < lane.size(); ++l) *out[l].end = lane[l]->finish();
  }
};

}  // namespace

TrackEnd track_azimuth(const TrackModel& m, const ParticleState& s0, const TrackSettings& st,
                       std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                       std::vector<PathPoint>* path) {
  AzParticle p(m, s0, st, &turns, kicks, path);
  while (p.th < p.th_end - 1e-13) {
    double stop = p.node_stop(p.th);
    const int which = p.next_event(stop);
    if (!p.step_to(stop)) break;
    if (which >= 0 && !p.land_and_act(which)) break;
  }
  return p.finish();
}

void track_azimuth_group(const TrackModel& m, const ParticleState* s0, size_t n, const TrackSettings& st,
                         GroupOutput* out) {
  std::vector<const TrackModel*> models(n, &m);
  track_azimuth_group(models.data(), s0, n, st, out);
}

namespace {
/// Whether two models' main fields are one map (copies share its values and row tables), so
/// their particles can go through grid steps together.
bool same_main_field(const TrackModel& a, const TrackModel& b) {
  return &a == &b || (!a.opal_map && !b.opal_map && &a.map.values() == &b.map.values() &&
                      a.map.grid().dtheta_rad() == b.map.grid().dtheta_rad() &&
                      a.map.grid().theta_min_rad() == b.map.grid().theta_min_rad());
}
}  // namespace

void track_azimuth_group(const TrackModel* const* ms, const ParticleState* s0, size_t n, const TrackSettings& st,
                         GroupOutput* out) {
  if (n == 0) return;
  if (n > static_cast<size_t>(kMaxLanes)) {
    for (size_t b = 0; b < n; b += kMaxLanes)
      track_azimuth_group(ms + b, s0 + b, std::min<size_t>(kMaxLanes, n - b), st, out + b);
    return;
  }
  const TrackModel& m = *ms[0];
  // Lanes go through the same grid steps only from one azimuth (AzParticle's start th) and on
  // one map: otherwise the lanes that can go together (an optimizer's designs that move the
  // injection azimuth do not) go as groups of their own.
  const double th0 = AzParticle::start_azimuth(s0[0]);
  std::vector<size_t> with_first, rest;
  for (size_t l = 0; l < n; ++l)
    (AzParticle::start_azimuth(s0[l]) == th0 && same_main_field(*ms[l], m) ? with_first : rest).push_back(l);
  if (!rest.empty()) {
    for (const auto* part : {&with_first, &rest}) {
      std::vector<const TrackModel*> pm;
      std::vector<ParticleState> ps;
      std::vector<GroupOutput> po;
      for (size_t l : *part) {
        pm.push_back(ms[l]);
        ps.push_back(s0[l]);
        po.push_back(out[l]);
      }
      track_azimuth_group(pm.data(), ps.data(), pm.size(), st, po.data());
    }
    return;
  }
  GroupRun run(ms, s0, n, st, out);
  while (run.step_node()) {
  }
  run.finish();
}

struct AzimuthGroupRun::Impl {
  std::vector<const TrackModel*> models;
  GroupRun run;
  Impl(const TrackModel& m, const ParticleState* s0, size_t n, const TrackSettings& st, GroupOutput* out)
      : models(n, &m), run(models.data(), s0, n, st, out) {}
};

AzimuthGroupRun::AzimuthGroupRun(const TrackModel& m, const ParticleState* s0, size_t n, const TrackSettings& st,
                                 GroupOutput* out) {
  if (n == 0 || n > static_cast<size_t>(kMaxLanes))
    throw Error(ExitCode::software, "AzimuthGroupRun: " + std::to_string(n) + " lanes (1 to " +
                                 std::to_string(kMaxLanes) + ")");
  const double th0 = AzParticle::start_azimuth(s0[0]);
  for (size_t l = 1; l < n; ++l)
    if (AzParticle::start_azimuth(s0[l]) != th0)
      throw Error(ExitCode::software, "AzimuthGroupRun: particles that start at different azimuths");
  impl_ = std::make_unique<Impl>(m, s0, n, st, out);
}
AzimuthGroupRun::~AzimuthGroupRun() = default;
AzimuthGroupRun::AzimuthGroupRun(AzimuthGroupRun&&) noexcept = default;
AzimuthGroupRun& AzimuthGroupRun::operator=(AzimuthGroupRun&&) noexcept = default;

bool AzimuthGroupRun::advance(long nodes) {
  bool any = false;
  for (long k = 0; k < nodes && impl_->run.step_node(); ++k) any = true;
  return any;
}
bool AzimuthGroupRun::running() const { return impl_->run.running(); }
double AzimuthGroupRun::azimuth() const { return impl_->run.th; }
double AzimuthGroupRun::end_azimuth() const { return impl_->run.th_end; }
double AzimuthGroupRun::azimuth_after(long nodes) const {
  // step_node's stops, without the steps.
  const GroupRun& r = impl_->run;
  double th = r.th;
  for (long k = 0; k < nodes && th < r.th_end - 1e-13; ++k) th = r.lane[0]->node_stop(th);
  return th;
}
size_t AzimuthGroupRun::size() const { return impl_->run.lane.size(); }

bool AzimuthGroupRun::lane(size_t l, LaneState& s) const {
  const AzParticle& p = *impl_->run.lane[l];
  if (!p.running()) return false;
  const double r = p.y[0], c = std::cos(p.th), sn = std::sin(p.th);
  const double sxy = std::sqrt(std::max(0.0, 1 - p.y[1] * p.y[1] - p.y[3] * p.y[3]));
  s.s.x = r * c;
  s.s.y = r * sn;
  s.s.z = p.y[2];
  s.s.px = p.P * (p.y[1] * c - sxy * sn);
  s.s.py = p.P * (p.y[1] * sn + sxy * c);
  s.s.pz = p.P * p.y[3];
  s.s.t = p.y[4];
  s.dt_dtheta = sxy > 0 ? r / sxy * p.f.inv_v : 0.0;
  return true;
}

void AzimuthGroupRun::kick(size_t l, double dpx, double dpy, double dpz) {
  AzParticle& p = *impl_->run.lane[l];
  // (No kick leaves the state untouched, bit for bit: a run without a force is the group stepper's.)
  if (!p.running() || (dpx == 0 && dpy == 0 && dpz == 0)) return;
  // As a gap's kick (AzParticle::land_and_act): the new momentum's magnitude and its radial and
  // vertical parts at the lane's azimuth.
  const double c = std::cos(p.th), sn = std::sin(p.th);
  const double sxy = std::sqrt(std::max(0.0, 1 - p.y[1] * p.y[1] - p.y[3] * p.y[3]));
  const double px = p.P * (p.y[1] * c - sxy * sn) + dpx, py = p.P * (p.y[1] * sn + sxy * c) + dpy,
               pz = p.P * p.y[3] + dpz;
  p.P = std::sqrt(px * px + py * py + pz * pz);
  p.y[1] = (px * c + py * sn) / p.P;
  p.y[3] = pz / p.P;
  p.set_momentum();
}

void AzimuthGroupRun::finish() { impl_->run.finish(); }

}  // namespace turnfit::detail
