// The paper's local search (seed, Sec. IV.D "Local search"; the issue calls it IV.B): one design
// variable changed at a time, a step kept when one of four norms of the turn residuals improves
// and none worsens by more than 0.01 mm. There for comparison with the paper (turnfit-localsearch
// --method coordinate); Levenberg-Marquardt (localsearch.hpp) needs far fewer evaluations.
//
// What the paper says and what turnfit chose where it is silent:
// - paper: the norms are l_inf, the 2nd and 3rd largest error and an l2 in which RRI2's turns
//   weigh as much as RRL's; a change is allowed when any norm improves and the others do not
//   worsen significantly (0.01 mm for l_inf); it stopped after 30000 iterations without l_inf
//   gain, and l_inf "occasionally increases" on the way.
// - turnfit: the 0.01 mm for all four norms; the l2 as the RMS of per-probe RMS (mm, so the
//   tolerance means the same); variables in problem order (for "paper", the appendix table's);
//   per variable a +h and a -h trial, h its own step, doubled after a kept step (up to
//   max_step), halved after two refusals (down to min_step); the best point (not the last) is
//   returned; stop after N sweeps that moved without l_inf gain, or a sweep at min_step that
//   keeps nothing.
// Measured (ring8, 48 variables, noiseless truth with each moved by up to 2 % of its range,
// 2 threads on a loaded 2-core VM): 3.08 mm -> 0.30 mm worst turn, then "no gain in 3 sweeps"
// after 23 sweeps, 2210 evaluations, 134 s; it never reached 0.1 mm. LM reaches the noise on
// 5 % truths in 400-2000 evaluations (bench/RESULTS.md).
#pragma once

#include <cstddef>
#include <functional>
#include <string>
#include <vector>

#include "turnfit/optimize/localsearch.hpp"
#include "turnfit/optimize/turn_problem.hpp"

namespace turnfit {

/// The four norms the paper's local search watches, over the matched turns of one design [mm].
struct CoordinateNorms {
  double linf_mm = 0;    ///< the largest |dr| (the paper's l_inf-error, its Eq. of matching quality)
  double second_mm = 0;  ///< the second largest |dr| (0 with fewer than two matched turns)
  double third_mm = 0;   ///< the third largest |dr| (0 with fewer than three)
  /// Weighted l2: sqrt of the mean over probes of each probe's mean dr^2, so every probe weighs
  /// the same however many turns it has (the paper: "the RRI2 turns were weighted equally to
  /// the RRL turns"; RRI2 has 16, RRL 174). One probe: the RMS.
  double wl2_mm = 0;
};

/// The norms of a simulated design; the measured table gives the probes (the points of
/// `r` are in measured().points order). Unmatched points are left out.
CoordinateNorms coordinate_norms(const TurnPatternResult& r, const TurnTable& measured);

/// The paper's acceptance rule: true when at least one norm of `trial` is lower than the same
/// norm of `current` by more than `improvement_mm`, and no norm is higher by more than
/// `tolerance_mm`. (The paper names 0.01 mm for the l_inf-error; the same tolerance is used for
/// all four, as issue "--method coordinate" asks.)
bool coordinate_accepts(const CoordinateNorms& current, const CoordinateNorms& trial, double tolerance_mm,
                        double improvement_mm);

/// How the coordinate search runs. Steps are fractions of each variable's bound range
/// (upper - lower); the paper gives no step sizes, these are turnfit's choices.
struct CoordinateSettings {
  unsigned threads = 0;  ///< designs simulated at once (0: every hardware thread); never changes the result
  /// Stop after this many consecutive sweeps that accepted a step but did not lower the best
  /// worst turn (l_inf) by more than improvement_mm. A sweep that accepts nothing only shrinks
  /// the steps and does not count: a start within a step of its optimum must get to try
  /// smaller steps. The paper stopped after 30000 evaluations without l_inf gain. This is what
  /// ends a search whose norms are within a few tolerance_mm of each other: the rule then lets
  /// l_inf and l2 trade places and can walk in a cycle (seen on ring8 with phiinit and prinit
  /// both free, stalled near 0.05 mm). 3 can stop a slow crawl: on 48 variables l_inf was
  /// still dropping ~0.006 mm a sweep when it stopped.
  int max_sweeps_without_gain = 3;
  double initial_step = 0.05;  ///< every variable's first step, fraction of its range, in (0, 1]
  /// Smallest step, fraction of the range: a step is never shrunk below it, and a sweep that
  /// accepts nothing while every step is at this floor ends the search ("converged").
  double min_step = 1e-6;
  double max_step = 0.25;   ///< largest step a variable's step may grow to, fraction of the range
  double grow = 2.0;        ///< a variable's step is multiplied by this after one of its steps is kept (>= 1)
  double shrink = 0.5;      ///< ... and by this after both of its trials are refused, in (0, 1)
  double tolerance_mm = 0.01;  ///< how much any norm may worsen in a kept step (the paper's 0.01 mm)
  /// A norm "improves" when it drops by more than this [mm]: far below any peak resolution,
  /// far above the tracking's rounding (~1e-12 of a 2 m radius), so rounding noise is no gain.
  double improvement_mm = 1e-6;
  /// Stop once this many designs were simulated (checked before each block of trials, so a run
  /// may end up to 2 x lookahead beyond it; 0: no limit).
  size_t max_evaluations = 100000;
  /// Variables whose trials are simulated at once from the same point (their +step and -step
  /// trials: 2 x lookahead designs). Trials after a variable whose step is kept were made from
  /// the old point; they are discarded and made again, so the path (x, accepted, sweeps) is the
  /// same for every lookahead and only the evaluations (wasted ones included) grow. 1 is the
  /// paper's one variable at a time; more keeps more than two threads busy late in a search,
  /// when steps are rarely kept. The result never depends on `threads`.
  unsigned lookahead = 1;
  /// Called after every sweep with (sweep number from 1, best worst turn so far [mm]); may be empty.
  std::function<void(int sweep, double linf_mm)> progress;
};

/// One kept step (the paper's Fig. of the l_inf-error during the search can be drawn from these).
struct CoordinateStep {
  size_t evaluation = 0;  ///< designs simulated when it was kept (start included)
  int sweep = 0;          ///< sweep number from 1
  size_t variable = 0;    ///< index into the problem's variables
  double value = 0;       ///< the variable's new value
  CoordinateNorms norms;  ///< at the new point
};

/// What the coordinate search found.
struct CoordinateResult {
  /// The best point visited: lowest worst turn (l_inf), then lowest weighted l2. The rule lets
  /// l_inf rise by up to tolerance_mm per kept step (the paper: "the error occasionally
  /// increases"), so the last point need not be the best.
  std::vector<double> x;
  FitSummary before, after;            ///< at x0 and at x (chi2 with the problem's sigma_mm, 0 without)
  CoordinateNorms norms_before, norms_after;  ///< the rule's four norms at x0 and at x
  size_t evaluations = 0;              ///< designs simulated: the start and every trial (discarded ones included)
  size_t discarded = 0;                ///< lookahead trials made from a point that had since moved
  size_t refused_failed = 0;           ///< trials refused because they could not be simulated or lost turns
  size_t accepted = 0;                 ///< steps kept
  size_t sweeps = 0;                   ///< sweeps begun (a sweep visits every variable once, in problem order)
  std::vector<double> step;            ///< each variable's step at the end, fraction of its range
  /// Per variable, the total change of l_inf and of weighted l2 over its kept steps [mm]
  /// (negative: it lowered the norm), as in the paper's Figs. of the total effect per variable.
  std::vector<double> effect_linf_mm, effect_wl2_mm;
  std::vector<CoordinateStep> trace;   ///< every kept step, in order
  double wall_s = 0, cpu_s = 0;        ///< time taken (CPU: every thread of the process)
  /// Why it stopped: "converged (...)", "no gain in N sweeps", "max_evaluations", "nothing to vary".
  std::string termination;
};

/// The paper's coordinate-wise local search from x0 (see CoordinateSettings for the steps).
/// Each variable in turn (problem order) gets a trial at x_j + h_j and one at x_j - h_j (clamped
/// to its bounds), simulated together; a trial that fails, misses more measured turns than the
/// current point or has a larger turn-count violation is refused; of the trials the rule
/// (coordinate_accepts) accepts, the lower l_inf (then weighted l2, then +h) is kept. EX_USAGE
/// if x0 lies outside the bounds or a setting is out of range; EX_DATAERR, naming the problem
/// file, if x0 cannot be simulated or reaches no measured turn.
CoordinateResult coordinate_search(const TurnPatternProblem& p, const std::vector<double>& x0,
                                   const CoordinateSettings& s);

}  // namespace turnfit
