// The paper's coordinate-wise local search on a turn-pattern problem (see coordinate_search.hpp).
#include "turnfit/optimize/coordinate_search.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"

namespace turnfit {

CoordinateNorms coordinate_norms(const TurnPatternResult& r, const TurnTable& measured) {
  CoordinateNorms c;
  double top[3] = {0, 0, 0};  // the three largest |dr|, largest first
  double sum_probe_ms = 0;    // sum over probes with matched turns of their mean dr^2
  int probes = 0;
  for (size_t q = 0; q < measured.probes.size(); ++q) {
    const auto [b, e] = measured.probe_range(static_cast<int>(q));
    double ss = 0;
    size_t m = 0;
    for (size_t i = b; i < e && i < r.delta_mm.size(); ++i) {
      if (!r.matched[i]) continue;
      const double a = std::fabs(r.delta_mm[i]);
      ss += a * a;
      ++m;
      if (a > top[2]) {
        top[2] = a;
        if (top[2] > top[1]) std::swap(top[1], top[2]);
        if (top[1] > top[0]) std::swap(top[0], top[1]);
      }
    }
    if (m > 0) {
      sum_probe_ms += ss / static_cast<double>(m);
      ++probes;
    }
  }
  c.linf_mm = top[0];
  c.second_mm = top[1];
  c.third_mm = top[2];
  c.wl2_mm = probes > 0 ? std::sqrt(sum_probe_ms / probes) : 0;
  return c;
}

bool coordinate_accepts(const CoordinateNorms& current, const CoordinateNorms& trial, double tolerance_mm,
                        double improvement_mm) {
  const double cur[4] = {current.linf_mm, current.second_mm, current.third_mm, current.wl2_mm};
  const double tri[4] = {trial.linf_mm, trial.second_mm, trial.third_mm, trial.wl2_mm};
  bool improves = false;
  for (int k = 0; k < 4; ++k) {
    if (!(tri[k] <= cur[k] + tolerance_mm)) return false;  // worsens one significantly (or NaN)
    if (tri[k] < cur[k] - improvement_mm) improves = true;
  }
  return improves;
}

namespace {

std::string fmt(double v, int digits = 3) {
  char b[48];
  std::snprintf(b, sizeof b, "%.*g", digits, v);
  return b;
}

/// What the rule needs of one simulated design.
struct Point {
  bool ok = false;
  size_t missing = 0;    // measured turns without a simulated partner
  size_t violation = 0;  // missing plus extra turns
  CoordinateNorms norms;
};

Point point_of(const TurnPatternResult& r, const TurnTable& measured) {
  Point pt;
  pt.ok = r.ok;
  if (!r.ok) return pt;
  for (size_t i = 0; i < r.matched.size(); ++i) pt.missing += r.matched[i] ? 0 : 1;
  pt.violation = r.violation;
  pt.norms = coordinate_norms(r, measured);
  return pt;
}

/// Lexicographic: lower l_inf, then lower weighted l2.
bool better(const CoordinateNorms& a, const CoordinateNorms& b) {
  return a.linf_mm < b.linf_mm || (a.linf_mm == b.linf_mm && a.wl2_mm < b.wl2_mm);
}

void check_settings(const CoordinateSettings& s) {
  auto bad = [](const std::string& what) { throw usage_error("coordinate search: " + what); };
  if (s.max_sweeps_without_gain < 1) bad("max_sweeps_without_gain must be at least 1");
  if (!(s.initial_step > 0 && s.initial_step <= 1)) bad("initial_step must lie in (0, 1] (a fraction of the range)");
  if (!(s.min_step > 0 && s.min_step <= s.initial_step)) bad("min_step must lie in (0, initial_step]");
  if (!(s.max_step >= s.initial_step && s.max_step <= 1)) bad("max_step must lie in [initial_step, 1]");
  if (!(s.grow >= 1)) bad("grow must be at least 1");
  if (!(s.shrink > 0 && s.shrink < 1)) bad("shrink must lie in (0, 1)");
  if (!(s.tolerance_mm >= 0)) bad("tolerance_mm must not be negative");
  if (!(s.improvement_mm >= 0)) bad("improvement_mm must not be negative");
  if (s.lookahead < 1) bad("lookahead must be at least 1");
}

}  // namespace

CoordinateResult coordinate_search(const TurnPatternProblem& p, const std::vector<double>& x0,
                                   const CoordinateSettings& s) {
  const auto wall0 = std::chrono::steady_clock::now();
  const std::clock_t cpu0 = std::clock();
  check_settings(s);
  const size_t n = p.n_variables();
  if (x0.size() != n) throw Error(ExitCode::software, "coordinate_search: a start of the wrong size");
  const std::vector<double>& lo = p.lower();
  const std::vector<double>& hi = p.upper();
  for (size_t j = 0; j < n; ++j)
    if (!(x0[j] >= lo[j] && x0[j] <= hi[j]))
      throw usage_error("the start's " + p.variables()[j].name + " = " + fmt(x0[j], 10) + " lies outside its bounds [" +
                        fmt(lo[j], 10) + ", " + fmt(hi[j], 10) + "]");
  const unsigned threads = resolve_thread_count(s.threads);
  const TurnTable& meas = p.measured();

  CoordinateResult out;
  const TurnPatternResult start = p.simulate(x0);
  out.evaluations = 1;
  if (!start.ok) throw Error(ExitCode::data, p.file() + ": the start cannot be simulated: " + start.reason);
  out.before = summarize(start, p.sigma_mm());
  if (out.before.matched == 0)
    throw Error(ExitCode::data, p.file() + ": the start reaches no measured turn (" + start.end.status + ")");

  std::vector<double> x = x0;
  Point cur = point_of(start, meas);
  std::vector<double> best_x = x;
  CoordinateNorms best = cur.norms;
  TurnPatternResult best_r = start;
  out.norms_before = cur.norms;
  out.step.assign(n, s.initial_step);
  out.effect_linf_mm.assign(n, 0);
  out.effect_wl2_mm.assign(n, 0);

  // Variables that can move at all (a zero range has no trial).
  std::vector<double> range(n);
  bool any = false;
  for (size_t j = 0; j < n; ++j) {
    range[j] = hi[j] - lo[j];
    any = any || range[j] > 0;
  }

  struct Trial {
    size_t var = 0;
    std::vector<double> x;
    TurnPatternResult r;
    Point pt;
  };
  int no_gain = 0;
  out.termination = any ? "" : "nothing to vary (no variable has a bound range)";
  while (out.termination.empty()) {
    const int sweep = static_cast<int>(++out.sweeps);
    bool sweep_accepted = false, sweep_gain = false;
    size_t j = 0;
    while (j < n) {
      if (s.max_evaluations > 0 && out.evaluations >= s.max_evaluations) {
        out.termination = "max_evaluations";
        break;
      }
      // The block's trials, all from the current point: +h then -h per variable, clamped to
      // the bounds; a trial that would not move (at a bound) is left out.
      const size_t jend = std::min(n, j + s.lookahead);
      std::vector<Trial> trials;
      for (size_t k = j; k < jend; ++k) {
        if (!(range[k] > 0)) continue;
        const double h = out.step[k] * range[k];
        for (double sign : {1.0, -1.0}) {
          Trial t;
          t.var = k;
          t.x = x;
          t.x[k] = std::min(std::max(x[k] + sign * h, lo[k]), hi[k]);
          if (t.x[k] != x[k]) trials.push_back(std::move(t));
        }
      }
      // Independent designs: simulated at once, results by index (the same for any thread count).
      parallel_for(trials.size(), threads,
                   [&](size_t i, unsigned) {
                     trials[i].r = p.simulate(trials[i].x);
                     trials[i].pt = point_of(trials[i].r, meas);
                   });
      out.evaluations += trials.size();

      size_t next = jend;
      for (size_t k = j; k < jend; ++k) {
        // The rule (paper, Sec. IV.D "Local search"): the design must simulate and keep its
        // turns; then one norm improves and none worsens by more than tolerance_mm.
        const Trial* pick = nullptr;
        for (const Trial& t : trials) {
          if (t.var != k) continue;
          const bool feasible = t.pt.ok && t.pt.missing <= cur.missing && t.pt.violation <= cur.violation;
          if (!feasible) {
            ++out.refused_failed;
            continue;
          }
          if (!coordinate_accepts(cur.norms, t.pt.norms, s.tolerance_mm, s.improvement_mm)) continue;
          if (!pick || better(t.pt.norms, pick->pt.norms)) pick = &t;
        }
        if (!pick) {
          out.step[k] = std::max(out.step[k] * s.shrink, s.min_step);
          continue;
        }
        out.effect_linf_mm[k] += pick->pt.norms.linf_mm - cur.norms.linf_mm;
        out.effect_wl2_mm[k] += pick->pt.norms.wl2_mm - cur.norms.wl2_mm;
        x[k] = pick->x[k];
        cur = pick->pt;
        out.step[k] = std::min(out.step[k] * s.grow, s.max_step);
        ++out.accepted;
        sweep_accepted = true;
        out.trace.push_back({out.evaluations, sweep, k, x[k], cur.norms});
        if (cur.norms.linf_mm < best.linf_mm - s.improvement_mm) sweep_gain = true;
        if (better(cur.norms, best)) {
          best = cur.norms;
          best_x = x;
          best_r = pick->r;
        }
        // Later trials of the block were made from the old point.
        for (const Trial& t : trials) out.discarded += t.var > k ? 1 : 0;
        next = k + 1;
        break;
      }
      j = next;
    }
    if (s.progress) s.progress(sweep, best.linf_mm);
    if (!out.termination.empty()) break;
    if (sweep_gain) {
      no_gain = 0;
    } else if (sweep_accepted && ++no_gain >= s.max_sweeps_without_gain) {
      out.termination = "no gain in " + std::to_string(no_gain) + " sweeps";
    }
    if (!sweep_accepted) {
      bool floor = true;
      for (size_t k = 0; k < n; ++k) floor = floor && (!(range[k] > 0) || out.step[k] <= s.min_step);
      if (floor) out.termination = "converged (no step of min_step kept in a sweep)";
    }
  }

  out.x = best_x;
  out.norms_after = best;
  out.after = summarize(best_r, p.sigma_mm());
  out.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
  out.cpu_s = static_cast<double>(std::clock() - cpu0) / CLOCKS_PER_SEC;
  return out;
}

}  // namespace turnfit
