// Local search on a turn-pattern problem: bounded Levenberg-Marquardt (Ceres) on every turn's
// residual with a finite-difference Jacobian evaluated in parallel, uncertainties, correlations
// and what the data do not determine.
#pragma once

#include <Eigen/Dense>
#include <functional>
#include <string>
#include <vector>

#include "turnfit/optimize/turn_problem.hpp"

namespace turnfit {

/// How the local search runs.
struct LocalSearchSettings {
  unsigned threads = 0;        ///< designs evaluated at once (0: every hardware thread)
  int max_iterations = 60;     ///< Levenberg-Marquardt iterations per pass
  /// Finite-difference step, as a fraction of each variable's bound range. Tracking is
  /// deterministic and smooth in its inputs to ~1e-12 relative, so small steps are safe.
  double fd_step = 1e-6;
  bool central = false;        ///< central differences (twice the evaluations per Jacobian)
  /// Steps taken with the last Jacobian (frozen: one design a step instead of n + 1) while each
  /// lowers the cost by at least half of what that Jacobian predicts, at most this many in a
  /// row; a pass always ends on a Jacobian formed at its result. 0: a new Jacobian every step.
  int frozen_steps = 8;
  /// Broyden's rank-one update of the kept Jacobian after each frozen step (no designs): the
  /// model learns the direction it just moved along, so frozen steps follow a curved valley.
  /// On blind case truth1 it cut the least-squares designs from 1786 to 1021 at the same chi2.
  bool broyden = true;
  /// Pass 1 by turn continuation: the first stage fits the turns up to 1/stages of the measured
  /// turn range (the others weighed 1e-3), each next one a further 1/stages, from where the last
  /// ended. 1: all turns at once.
  int stages = 3;
  /// A pass stops at a Jacobian formed at its current design when the Gauss-Newton step from
  /// there would lower chi2 by less than this, in units of the current chi2 per degree of
  /// freedom (the Newton decrement: the linearized optimum is then within sqrt(tol) sigma of the
  /// design in every direction, far inside the 1-sigma region, and further steps move the result
  /// by a fraction of its uncertainty at n designs a Jacobian). 0: Ceres' tolerances alone.
  double decrement_tolerance = 0.05;
  /// The weak prior toward the start for variables without a sigma: one residual
  /// (u - u_start) / weak_prior_range, u the variable scaled to its bounds. Directions the
  /// data do not determine then stay put instead of drifting to a bound; a determined
  /// direction's residuals outweigh it. 0: none.
  double weak_prior_range = 0.1;
  /// The weak prior's centre for the first weak_prior_centre.size() variables (the rest: the
  /// start). Empty: the start, so the prior holds a fit near where it began. A caller that
  /// compares fits from different starts (turnfit-diagnose: a candidate's refit from the
  /// linear step against the model refitted as it is) gives them one centre, so that they
  /// minimize the same objective and differ only by the model; a fit taken on from where an
  /// earlier one stopped passes the earlier one's centre, or each continuation would move it.
  std::vector<double> weak_prior_centre;
  /// Outlying turns, when sigma is estimated: a turn whose converged residual lies beyond
  /// huber_k of its sigma is down-weighted as Huber's loss does (its sigma times
  /// sqrt(|z| / huber_k), z the residual in sigmas) and left out of the scatter's estimate, so
  /// one bad peak (a turn peakfind merged with a neighbour it did not see) can neither pull the
  /// fit nor inflate every turn's sigma; the report names each. 0: none.
  double huber_k = 3;
  /// The residual [mm] given to a measured turn the design does not reach (or reaches under
  /// another number): finite, so a failed design steers the fit away instead of stopping it.
  /// 0: 10 mm or twice the start's worst turn, whichever is larger.
  double miss_penalty_mm = 0;
  /// Minimax polish after the least-squares fit: steps that lower the worst turn while neither
  /// the 2nd nor the 3rd largest error nor the probe-weighted l2 rises by more than
  /// minimax_tolerance_mm (the acceptance rule of the paper's local search, whose goal is the
  /// max error; 0.01 mm is its tolerance). At most minimax_steps accepted steps.
  bool minimax = true;
  double minimax_tolerance_mm = 0.01;
  int minimax_steps = 10;
  /// Called after each Levenberg-Marquardt iteration with (pass, iteration, cost); may be empty.
  std::function<void(int, int, double)> progress;
  /// For tests: at each new sigma pass, also form the Jacobian anew at the design where the kept
  /// (reweighted) one stands, and report the largest difference (costs a Jacobian a pass).
  bool check_kept_jacobian = false;
};

/// One Levenberg-Marquardt iteration (Ceres' iteration summary and the design it stands on),
/// for the report's trace: how many evaluations a given RMS took, and where they went.
struct LocalSearchIteration {
  int pass = 1;             ///< sigma pass (1-5)
  int iteration = 0;        ///< Ceres' iteration in the pass (0: the pass's start)
  size_t evaluations = 0;   ///< designs simulated so far, all passes (the start's and this design's Jacobian included)
  double cost = 0;          ///< Ceres' cost, chi2 / 2 with this pass's sigma, priors included
  double rms_mm = 0, linf_mm = 0;  ///< the current design's turns (matched ones) against the measurement [mm]
  size_t matched = 0;       ///< measured turns the current design matched
  bool accepted = true;     ///< the iteration's step was taken (a rejected one costs one design)
  double relative_decrease = 0;     ///< actual / predicted cost decrease of the iteration's step
  double trust_region_radius = 0;   ///< Ceres' radius after the iteration
  bool fresh = true;        ///< the Jacobian at the current design was formed there (not frozen)
  /// With a fresh Jacobian: the chi2 decrease the Gauss-Newton step predicts from here, in
  /// units of chi2 per degree of freedom (LocalSearchSettings::decrement_tolerance); else NaN.
  double decrement = 0;
};

/// The turn residuals of one design, summarized.
struct FitSummary {
  std::vector<double> objectives;  ///< the problem's objectives [mm]
  double linf_mm = 0, mae_mm = 0, rms_mm = 0;
  double chi2 = 0;                 ///< sum of (delta / sigma)^2 over matched turns
  size_t matched = 0;              ///< turns with a simulated partner
  size_t violation = 0;            ///< missing plus extra turns
  bool ok = false;                 ///< the design could be simulated
  std::string reason;
};

/// One variable after the fit.
struct FittedVariable {
  std::string name, unit;
  double start = 0, value = 0;
  double sigma = 0;       ///< 1-sigma uncertainty from the fit (priors included)
  /// The same, robust to residuals that neighbouring turns share (LocalSearchResult::robust):
  /// never below sigma.
  double sigma_robust = 0;
  double lower = 0, upper = 0;
  bool determined = false;  ///< the data fix it to better than a tenth of its bound range
  bool at_bound = false;    ///< the fit ended on a bound (within 1e-6 of its range)
};

/// What the local search found.
struct LocalSearchResult {
  std::vector<double> x;              ///< the least-squares result
  FitSummary before, after;
  std::vector<FittedVariable> variables;
  Eigen::MatrixXd correlation;        ///< of the variables (priors included)
  /// The uncertainties when the residual is not white: a sandwich covariance (heteroskedasticity
  /// and autocorrelation consistent, Newey and West's Bartlett kernel over each probe's turns in
  /// order, each variable's bandwidth by Andrews' AR(1) rule: hac_covariance). A model
  /// error that neighbouring turns share (a missing effect, the centre of a finite bunch) biases
  /// the variables where the statistical sigma assumes independent turns; this widens them by
  /// what the residual shows of it. It cannot see a bias the variables absorbed entirely.
  struct Robust {
    std::vector<double> lag1;       ///< per probe (sigma_probes' order): the whitened residual's lag-1 correlation
    std::vector<double> bandwidth;  ///< per probe: the median of the variables' kernel bandwidths [turns]
    Eigen::MatrixXd correlation;    ///< of the variables, from the sandwich
  } robust;
  std::vector<double> singular_values;  ///< of the data's Jacobian, variables scaled to their bounds
  std::vector<std::string> identifiability;  ///< what the data do not determine, in words
  std::vector<std::string> sigma_probes;     ///< probes, in measured order
  /// Peak-position uncertainty used per probe: the problem's; or, estimated, the per-turn
  /// scatter that adds in quadrature to each peak's own uncertainty (the peaks' r_err_mm).
  std::vector<double> sigma_mm;
  size_t peak_uncertainties = 0;             ///< measured turns whose peaks carry their own uncertainty
  /// Per probe: the trust c_p in the peaks' own uncertainties, sigma_i^2 = s_p^2 + c_p^2 e_i^2
  /// (estimated with the scatter; 0 without peak uncertainties or with the problem's sigma_mm).
  std::vector<double> peak_trust;
  /// Turns down-weighted as outliers (settings.huber_k) in the last pass: measured-point index,
  /// residual [mm], sigma before down-weighting [mm] and after.
  struct Outlier {
    size_t point = 0;
    double residual_mm = 0, sigma_mm = 0, weighted_sigma_mm = 0;
  };
  std::vector<Outlier> outliers;
  std::string sigma_source;                  ///< "problem file" or how it was estimated
  int sigma_passes = 1;                      ///< fit passes (each estimate of sigma, or of the centroid shift, adds one)
  /// The bunch's centroid shift (TurnPatternProblem, "centroid" mode): recomputed at the start
  /// and before each pass; its last change [mm], its rms and largest value [mm] as used for
  /// the result, and the particles tracked for it (counted in `evaluations`, one design each).
  int centroid_updates = 0;
  double centroid_change_mm = 0;
  double centroid_rms_mm = 0, centroid_max_mm = 0;
  size_t centroid_tracks = 0;
  double chi2_dof = 0;                ///< after the fit (measured turns, less the variables)
  size_t evaluations = 0;             ///< designs simulated
  size_t jacobians = 0;               ///< finite-difference Jacobians formed
  int iterations = 0;                 ///< Levenberg-Marquardt iterations, all passes
  std::string termination;            ///< Ceres' word for how the last pass ended
  size_t failed_evaluations = 0;      ///< designs that could not be simulated (penalized)
  double wall_s = 0, cpu_s = 0;       ///< time taken (CPU: every thread of the process)
  std::vector<LocalSearchIteration> trace;  ///< every Levenberg-Marquardt iteration, all passes
  size_t minimax_held = 0;            ///< turns the polish held: outliers and doubtful peaks (sigma > 3 x the probe's median)
  int kept_jacobians = 0;             ///< passes and pass-1 stages that began from the last one's Jacobian, reweighted
  size_t frozen_steps = 0;            ///< steps taken on a frozen Jacobian (settings.frozen_steps)
  /// With settings.check_kept_jacobian: the largest |kept - fresh| entry over the largest |fresh|.
  double kept_jacobian_difference = 0;
  /// The minimax polish (settings.minimax): its design (x when it found nothing better), its
  /// summary, accepted steps and the designs it simulated (included in `evaluations`).
  std::vector<double> x_minimax;
  FitSummary minimax;
  int minimax_steps = 0;
  size_t minimax_evaluations = 0;
  std::string minimax_termination;
};

/// The step delta minimizing max_i |r_i + (J delta)_i| + ridge: Lawson's iteratively reweighted
/// least squares (weights w_i <- w_i |e_i| / sum_k w_k |e_k|, `sweeps` times), each solving
/// min sum_i w_i (r_i + J_i delta)^2 + mu |delta|^2, mu = ridge * trace(J^T W J) / n. Exposed for
/// its test: on a linear model it converges to the minimax (Chebyshev) solution.
Eigen::VectorXd lawson_minimax_step(const Eigen::MatrixXd& J, const Eigen::VectorXd& r, double ridge, int sweeps = 200);

/// The sandwich covariance of a least-squares fit whose residual rows may be correlated along
/// each block (a probe's turns, in order): C the fit's covariance (the pseudo-inverse of J^T J),
/// h_i = (J C)_i z_i row i's influence on the variables, and cov(a, c) = sum over each block's
/// rows i, j of k(|i - j|) h_ia h_jc plus C J_p^T J_p C over the rows from `ndata` on (priors:
/// their information, not resampled). k is Bartlett's kernel, 1 - |i - j| / (b + 1), with each
/// variable's bandwidth by Andrews' AR(1) rule from its influence series' lag-1 correlation rho,
/// b = 1.1447 (m a)^(1/3), a = 4 rho^2 / ((1 - rho)^2 (1 + rho)^2) (b = 0 when rho <= 0; rho at
/// most 0.97, b below the block's length m); a pair at the larger of its two. lag1 gets each
/// block's residual lag-1 correlation, bandwidth the median of its variables' bandwidths. With
/// white residuals it averages C; a residual that neighbouring rows share (or one that
/// oscillates with a variable's column) widens it by what that residual does to the fit.
Eigen::MatrixXd hac_covariance(const Eigen::MatrixXd& cov, const Eigen::MatrixXd& J, const std::vector<double>& z,
                               size_t ndata, const std::vector<std::pair<size_t, size_t>>& blocks,
                               std::vector<double>& lag1, std::vector<double>& bandwidth);

/// What the turns do not determine, in words: variables that share directions the data fix to
/// worse than a tenth of a bound range form groups ("A, B and C: only their sum (in bound
/// ranges) is determined", "D: not determined by the turns"), then the pairs correlated above
/// 0.95, strongest first. Jd: the data rows of the Jacobian, variables scaled to their bounds
/// (residuals in units of sigma); correlation: of the fitted variables.
std::vector<std::string> describe_identifiability(const std::vector<std::string>& names, const Eigen::MatrixXd& Jd,
                                                  const Eigen::MatrixXd& correlation);

/// Summarizes one design against the measurement (sigma per measured point for chi2).
FitSummary summarize(const TurnPatternResult& r, const std::vector<double>& sigma_mm);
/// The same with the turns' covariance under the scan noise (chi2 of the whitened residuals
/// of the matched turns; the plain one when `scan` is inactive or sigma_mm empty).
FitSummary summarize(const TurnPatternResult& r, const std::vector<double>& sigma_mm, const TurnTable& measured,
                     const ScanNoise& scan);

/// Fits the problem's variables from x0 by bounded Levenberg-Marquardt on the residuals
/// (model - measured) / sigma of every measured turn, with the problem's priors and the weak
/// prior. Without the problem's sigma_mm, sigma_i^2 = s_p^2 + e_i^2: e_i the peak's own
/// uncertainty (the peaks file's r_err_mm, which turnfit-peakfind makes large for merged and
/// other doubtful peaks; 0 without the column) and s_p a per-turn scatter per probe, in a first
/// pass the wire step / sqrt(12) (the readout's resolution), then estimated from the converged
/// residuals (chi2 per degree of freedom 1); a second pass fits with it, and again (at most 5
/// passes) while a sigma moves by more than 10 %.
/// Then, with settings.minimax, the minimax polish: from the least-squares result, steps that
/// minimize the largest |residual| [mm] of the model linearized by the Jacobian (Lawson's
/// iteratively reweighted least squares, with a ridge toward the current design that acts as a
/// trust region), each kept by the paper's rule (see LocalSearchSettings::minimax).
/// In the problem's "centroid" mode the centroid shift is recomputed at x0 and before each
/// pass, and passes go on (at most 5 in all) while it moves by more than a tenth of the
/// smallest sigma; the problem keeps the last one.
/// EX_DATAERR if x0 cannot be simulated; EX_USAGE if x0 lies outside the bounds.
LocalSearchResult local_search(TurnPatternProblem& p, const std::vector<double>& x0,
                               const LocalSearchSettings& s);

}  // namespace turnfit
