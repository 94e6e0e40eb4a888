// Local search on a turn-pattern problem (see localsearch.hpp).
#include "turnfit/optimize/localsearch.hpp"

#include <ceres/ceres.h>

#include <algorithm>
#include <functional>
#include <map>
#include <optional>
#include <tuple>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <ctime>
#include <memory>
#include <mutex>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/optimize/ceres_logging.hpp"
#include "turnfit/optimize/coordinate_search.hpp"

namespace turnfit {

FitSummary summarize(const TurnPatternResult& r, const std::vector<double>& sigma_mm) {
  FitSummary f;
  f.ok = r.ok;
  f.reason = r.reason;
  if (!r.ok) return f;
  f.violation = r.violation;
  for (const auto& o : r.objectives) f.objectives.push_back(o.value);
  ErrorAccumulator acc;
  for (size_t i = 0; i < r.delta_mm.size(); ++i) {
    if (!r.matched[i]) continue;
    acc.add(r.delta_mm[i], i);
    if (!sigma_mm.empty()) f.chi2 += (r.delta_mm[i] / sigma_mm[i]) * (r.delta_mm[i] / sigma_mm[i]);
  }
  const ErrorStats st = acc.stats();
  f.matched = st.n;
  f.linf_mm = st.linf_mm;
  f.mae_mm = st.mae_mm;
  f.rms_mm = st.rms_mm;
  return f;
}

FitSummary summarize(const TurnPatternResult& r, const std::vector<double>& sigma_mm, const TurnTable& measured,
                     const ScanNoise& scan) {
  FitSummary f = summarize(r, sigma_mm);
  if (!r.ok || sigma_mm.empty() || !scan.active()) return f;
  // chi2 with the turns' covariance: the matched turns' residuals whitened.
  std::vector<size_t> pts;
  for (size_t i = 0; i < r.delta_mm.size(); ++i)
    if (r.matched[i]) pts.push_back(i);
  f.chi2 = Whitener(measured, pts, sigma_mm, scan).whitened(r.delta_mm).squaredNorm();
  return f;
}

namespace {

/// One design's residuals (weighted, priors after the data) and which measured turns it matched.
struct Point {
  std::vector<double> u, res;
  std::vector<unsigned char> matched;
};

/// The residuals of the fit and their finite-difference Jacobian, in variables scaled to
/// their bounds (u = (x - lower) / range, u in [0, 1]).
struct Residuals {
  const TurnPatternProblem& p;
  size_t n = 0, nmeas = 0, nres = 0;
  std::vector<double> lo, range;
  std::vector<double> inv_sigma;   // per measured point: 1 / sigma times the stage weight (white: the stage weight)
  /// The problem's scan noise (when active): the data residuals are L^-1 e over all measured
  /// points, each then times inv_sigma (the stage weight alone). Null: e / sigma, point by point.
  std::unique_ptr<Whitener> white;
  std::vector<double> prior_x0, prior_sigma_x;  // problem priors (sigma > 0)
  std::vector<double> weak_u0;     // weak prior centre (the start, or settings.weak_prior_centre), scaled
  double weak = 1;
  double miss_mm = 10;
  unsigned threads = 1;
  double h = 1e-6;
  bool central = false;
  std::vector<int> prior_kind;     // per variable: 0 none, 1 problem prior, 2 weak
  mutable std::atomic<size_t> evaluations{0}, failed{0};
  mutable std::mutex mu;
  // The kept Jacobian d r / d u and the point it was formed at (Ceres may ask for that point
  // again, and the final statistics and the next pass reuse it).
  mutable Point kept;
  mutable Eigen::MatrixXd jac;
  mutable size_t jacobians = 0;
  // The last residual-only evaluation (Ceres' trial point; if it is accepted, the Jacobian is
  // asked for at the same point next).
  mutable Point trial;
  // Ceres' current design (where it last asked for the Jacobian), for the trace.
  mutable Point current;
  int max_frozen = 0;           // consecutive steps on one Jacobian (LocalSearchSettings::frozen_steps)
  bool broyden = true;          // update the kept Jacobian on frozen steps (LocalSearchSettings::broyden)
  mutable bool stale = false;   // the kept Jacobian was formed at an earlier design (frozen steps)
  mutable int frozen_run = 0;   // frozen steps since the last Jacobian formed
  mutable size_t frozen_steps = 0;

  explicit Residuals(const TurnPatternProblem& problem) : p(problem) {}

  std::vector<double> x_of(const double* u) const {
    std::vector<double> x(n);
    for (size_t j = 0; j < n; ++j) x[j] = std::min(std::max(lo[j] + u[j] * range[j], p.lower()[j]), p.upper()[j]);
    return x;
  }

  /// The residuals of the design at u (one design simulated).
  Point evaluate(const std::vector<double>& u) const {
    const TurnPatternResult r = p.simulate(x_of(u.data()));
    ++evaluations;
    if (!r.ok) ++failed;
    return point_of(u, r);
  }

  /// The residuals of the design at u from its simulation r.
  Point point_of(const std::vector<double>& u, const TurnPatternResult& r) const {
    Point pt;
    pt.u = u;
    pt.res.resize(nres);
    pt.matched.assign(nmeas, 0);
    const std::vector<double> x = x_of(u.data());
    for (size_t i = 0; i < nmeas; ++i) {
      pt.matched[i] = r.ok && r.matched[i];
      pt.res[i] = (pt.matched[i] ? r.delta_mm[i] : miss_mm) * (white ? 1.0 : inv_sigma[i]);
    }
    if (white) {
      Eigen::Map<Eigen::VectorXd> z(pt.res.data(), static_cast<Eigen::Index>(nmeas));
      white->whiten(z);
      for (size_t i = 0; i < nmeas; ++i) pt.res[i] *= inv_sigma[i];
    }
    size_t k = nmeas;
    for (size_t j = 0; j < n; ++j) {
      if (prior_kind[j] == 1) pt.res[k++] = (x[j] - prior_x0[j]) / prior_sigma_x[j];
      else if (prior_kind[j] == 2) pt.res[k++] = (u[j] - weak_u0[j]) / weak;
    }
    return pt;
  }

  /// The finite-difference Jacobian d r / d u at `at.u`, its columns evaluated in parallel;
  /// at's residuals are evaluated with them unless already there. A forward step that would
  /// leave [0, 1] goes backward instead (and a central difference becomes one-sided there).
  Eigen::MatrixXd fd_jacobian(Point& at) const {
    const std::vector<double>& u = at.u;
    const size_t ncols = central ? 2 * n : n;
    std::vector<Point> out(ncols + 1);
    const bool known = at.res.size() == nres;
    if (known) out[0] = at;
    std::vector<double> step(n);
    for (size_t j = 0; j < n; ++j) step[j] = u[j] + h <= 1 ? h : -h;
    const size_t first = known ? 1 : 0;
    // The designs' reference particles tracked together in chunks (simulate_many); a design's
    // residuals do not depend on its chunk.
    std::vector<std::vector<double>> us, xs;
    for (size_t k = first; k <= ncols; ++k) {
      std::vector<double> v = u;
      if (k > 0) {
        const size_t j = (k - 1) % n;
        v[j] += k - 1 < n ? step[j] : -step[j];
      }
      xs.push_back(x_of(v.data()));
      us.push_back(std::move(v));
    }
    const std::vector<TurnPatternResult> rs = p.simulate_many(xs, threads);
    for (size_t k = first; k <= ncols; ++k) {
      ++evaluations;
      if (!rs[k - first].ok) ++failed;
      out[k] = point_of(us[k - first], rs[k - first]);
    }
    at = out[0];
    Eigen::MatrixXd J(nres, n);
    for (size_t j = 0; j < n; ++j) {
      // Central only where both sides lie inside the bounds; one-sided at a bound.
      const bool two = central && u[j] + h <= 1 && u[j] - h >= 0;
      for (size_t i = 0; i < nres; ++i)
        J(i, j) = two ? (out[1 + j].res[i] - out[1 + n + j].res[i]) / (2 * step[j])
                      : (out[1 + j].res[i] - out[0].res[i]) / step[j];
    }
    return J;
  }

  /// The Jacobian at u, formed (u's residuals from Ceres' trial point when it is u: Ceres asks
  /// for the Jacobian at a trial point it accepted) and kept.
  void form_jacobian(const std::vector<double>& u) const {
    Point at;
    {
      std::lock_guard<std::mutex> lock(mu);
      if (trial.u == u) at = trial;
      else if (kept.u == u) at = kept;  // a stale Jacobian's design: its residuals are known
    }
    at.u = u;
    Eigen::MatrixXd J = fd_jacobian(at);
    std::lock_guard<std::mutex> lock(mu);
    kept = std::move(at);
    jac = std::move(J);
    ++jacobians;
    stale = false;
    frozen_run = 0;
  }

  /// At Ceres' accepted trial point u: keep the last Jacobian (frozen, u's residuals from the
  /// trial: one design for the step) when the step to u lowered the cost by at least half of
  /// what that Jacobian predicted, at most max_frozen times in a row. True if it did; else a
  /// Jacobian is formed at u. Steps along a curved valley are short and well predicted, and the
  /// Jacobian changes little from one to the next: a fresh one for each costs n designs for
  /// nothing (the trace: rho 0.5-1 over tens of iterations of 49 designs each).
  bool freeze_at(const std::vector<double>& u) const {
    std::lock_guard<std::mutex> lock(mu);
    if (frozen_run >= max_frozen || trial.u != u || kept.res.size() != nres || trial.res.size() != nres) return false;
    Eigen::VectorXd r0 = Eigen::Map<const Eigen::VectorXd>(kept.res.data(), static_cast<Eigen::Index>(nres));
    Eigen::VectorXd r1 = Eigen::Map<const Eigen::VectorXd>(trial.res.data(), static_cast<Eigen::Index>(nres));
    Eigen::VectorXd du(static_cast<Eigen::Index>(n));
    for (size_t j = 0; j < n; ++j) du(static_cast<Eigen::Index>(j)) = u[j] - kept.u[j];
    const double pred = r0.squaredNorm() - (r0 + jac * du).squaredNorm();
    const double act = r0.squaredNorm() - r1.squaredNorm();
    if (!(pred > 0) || act < 0.5 * pred) return false;
    if (broyden) {
      // Broyden's rank-one update: the kept Jacobian learns the step it just took (J du = dr
      // along du), so the next frozen step follows a curved valley instead of the old tangent.
      const double du2 = du.squaredNorm();
      if (du2 > 0) jac += ((r1 - r0) - jac * du) * du.transpose() / du2;
    }
    kept = trial;
    stale = true;
    ++frozen_run;
    ++frozen_steps;
    return true;
  }

  /// A new sigma pass at the design u the last pass ended on, after the weights changed from
  /// old_inv_sigma to inv_sigma: u's residuals are evaluated anew (one design; the model's
  /// residuals may change between passes, not only their weights), and the kept Jacobian, when
  /// it was formed at u, is kept with its data rows rescaled by inv_sigma / old_inv_sigma (u did
  /// not move, so d delta / du did not either; the priors' rows keep theirs). Returns whether it
  /// was kept; if not, Ceres forms one at u (from these residuals). `known`: u's simulation
  /// under the current model when the caller has it (then no design is simulated here).
  bool restart_at(const std::vector<double>& u, const std::vector<double>& old_inv_sigma,
                  const TurnPatternResult* known = nullptr) const {
    Point at = known ? point_of(u, *known) : evaluate(u);
    std::lock_guard<std::mutex> lock(mu);
    current = at;
    trial = Point();
    if (kept.u != u || jac.rows() != static_cast<Eigen::Index>(nres)) {
      kept = Point();
      trial = std::move(at);
      return false;
    }
    for (size_t i = 0; i < nmeas; ++i) jac.row(static_cast<Eigen::Index>(i)) *= inv_sigma[i] / old_inv_sigma[i];
    kept = std::move(at);
    return true;
  }

  /// The Newton decrement at the current design, when its Jacobian was formed there: the chi2
  /// decrease of the Gauss-Newton step, ||r||^2 - min ||r + J du||^2 (the part of r in J's
  /// column space), over the current chi2 per degree of freedom. NaN on a frozen Jacobian.
  double decrement() const {
    std::lock_guard<std::mutex> lock(mu);
    if (stale || kept.u != current.u || kept.res.size() != nres || jac.rows() != static_cast<Eigen::Index>(nres))
      return std::nan("");
    const Eigen::Map<const Eigen::VectorXd> r(kept.res.data(), static_cast<Eigen::Index>(nres));
    const Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(jac);
    const Eigen::VectorXd qtr = qr.householderQ().transpose() * r;
    const double explained = qtr.head(qr.rank()).squaredNorm();
    const double dof = std::max(1.0, static_cast<double>(nmeas) - static_cast<double>(n));
    const double per_dof = r.squaredNorm() / dof;
    return per_dof > 0 ? explained / per_dof : 0.0;
  }

  /// The current design's data residuals in mm over the turns it matched: RMS, worst, count.
  void current_norms(double& rms_mm, double& linf_mm, size_t& matched) const {
    std::lock_guard<std::mutex> lock(mu);
    double ss = 0;
    rms_mm = linf_mm = std::nan("");
    matched = 0;
    if (current.res.size() != nres) return;
    linf_mm = 0;
    Eigen::VectorXd e(static_cast<Eigen::Index>(nmeas));
    for (size_t i = 0; i < nmeas; ++i) e[static_cast<Eigen::Index>(i)] = current.res[i] / inv_sigma[i];
    if (white) white->color(e);
    for (size_t i = 0; i < nmeas; ++i) {
      if (!current.matched[i]) continue;
      const double d = e[static_cast<Eigen::Index>(i)];
      ss += d * d;
      linf_mm = std::max(linf_mm, std::fabs(d));
      ++matched;
    }
    rms_mm = matched ? std::sqrt(ss / static_cast<double>(matched)) : std::nan("");
  }
};

/// The cost in unbounded angles theta, u = (sin theta + 1) / 2 (MINUIT's transform for a
/// bounded variable). Ceres' own bounds would run a projected line search whose every trial
/// point costs a whole Jacobian; the transform keeps the problem unconstrained, so a rejected
/// step costs one design. The fit's state between passes is theta, so that u, and with it the
/// kept Jacobian's key, is bit for bit the u Ceres asks for next.
class TurnCost final : public ceres::CostFunction {
 public:
  explicit TurnCost(const Residuals& r) : r_(r) {
    set_num_residuals(static_cast<int>(r.nres));
    mutable_parameter_block_sizes()->push_back(static_cast<int>(r.n));
  }
  bool Evaluate(double const* const* params, double* res, double** jac) const override {
    std::vector<double> u(r_.n);
    for (size_t j = 0; j < r_.n; ++j) u[j] = u_of_theta(params[0][j]);
    const bool want = jac && jac[0];
    bool cached = false;
    {
      // Ceres may ask for a point again (the final statistics too): answer from the kept Jacobian's.
      std::lock_guard<std::mutex> lock(r_.mu);
      if (r_.kept.u == u && r_.kept.res.size() == r_.nres) {
        std::copy(r_.kept.res.begin(), r_.kept.res.end(), res);
        if (want) r_.current = r_.kept;
        cached = true;
      }
    }
    if (!cached) {
      if (want) {
        if (!r_.freeze_at(u)) r_.form_jacobian(u);
        std::lock_guard<std::mutex> lock(r_.mu);
        std::copy(r_.kept.res.begin(), r_.kept.res.end(), res);
        r_.current = r_.kept;
      } else {
        Point pt = r_.evaluate(u);
        std::copy(pt.res.begin(), pt.res.end(), res);
        std::lock_guard<std::mutex> lock(r_.mu);
        r_.trial = std::move(pt);
      }
    }
    if (want) {
      std::lock_guard<std::mutex> lock(r_.mu);
      for (size_t j = 0; j < r_.n; ++j) {
        const double du = 0.5 * std::cos(params[0][j]);  // chain rule: dr/dtheta = dr/du du/dtheta
        for (size_t i = 0; i < r_.nres; ++i)
          jac[0][i * r_.n + j] = r_.jac(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) * du;
      }
    }
    return true;
  }
  static double u_of_theta(double t) { return 0.5 * (std::sin(t) + 1); }
  static double theta_of_u(double u) { return std::asin(2 * std::min(std::max(u, 1e-6), 1 - 1e-6) - 1); }

 private:
  const Residuals& r_;
};

std::vector<double> u_of(const std::vector<double>& theta) {
  std::vector<double> u(theta.size());
  for (size_t j = 0; j < theta.size(); ++j) u[j] = TurnCost::u_of_theta(theta[j]);
  return u;
}

/// After each iteration: the trace (where the evaluations go) and the progress line.
class TraceCallback final : public ceres::IterationCallback {
 public:
  TraceCallback(const LocalSearchSettings& s, const Residuals& r, int pass, std::function<size_t()> count,
                std::vector<LocalSearchIteration>& trace, std::function<bool()> reweigh = {})
      : s_(s), r_(r), pass_(pass), count_(std::move(count)), trace_(trace), reweigh_(std::move(reweigh)) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& it) override {
    LocalSearchIteration t;
    t.pass = pass_;
    t.iteration = it.iteration;
    t.evaluations = count_();
    t.cost = it.cost;
    t.accepted = it.iteration == 0 || it.step_is_successful;
    t.relative_decrease = it.relative_decrease;
    t.trust_region_radius = it.trust_region_radius;
    r_.current_norms(t.rms_mm, t.linf_mm, t.matched);
    t.fresh = !r_.stale;
    t.decrement = t.accepted ? r_.decrement() : std::nan("");
    trace_.push_back(t);
    if (s_.progress) s_.progress(pass_, it.iteration, it.cost);
    // Converged in the statistical sense: the best step the current Jacobian knows would move
    // chi2 by less than decrement_tolerance (in chi2 per degree of freedom). On a curved valley
    // the linear model over-promises (a few tenths where a cycle of n designs delivers a few
    // hundredths), so this never stops a fit that is still moving; stopping on the small gain
    // of a cycle instead left vchange 13 of its sigmas along such a valley (blind case truth1).
    if (s_.decrement_tolerance > 0 && t.decrement < s_.decrement_tolerance) return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    // This pass's weights are already known to be off (see local_search): end it here.
    if (std::isfinite(t.decrement) && reweigh_ && reweigh_()) return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    return ceres::SOLVER_CONTINUE;
  }

 private:
  const LocalSearchSettings& s_;
  const Residuals& r_;
  int pass_;
  std::function<size_t()> count_;
  std::vector<LocalSearchIteration>& trace_;
  std::function<bool()> reweigh_;
};

/// One Levenberg-Marquardt pass from theta (updated in place).
ceres::Solver::Summary lm_pass(const Residuals& res, std::vector<double>& theta, const LocalSearchSettings& s, int pass,
                               const std::function<size_t()>& count, std::vector<LocalSearchIteration>& trace,
                               const std::function<bool()>& reweigh = {}) {
  ceres::Problem problem;
  problem.AddResidualBlock(new TurnCost(res), nullptr, theta.data());
  ceres::Solver::Options o;
  o.minimizer_type = ceres::TRUST_REGION;
  o.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  o.linear_solver_type = ceres::DENSE_QR;
  o.max_num_iterations = s.max_iterations;
  // Stop when an iteration lowers chi2 by less than 1e-3 of its value per degree of freedom
  // (chi2 = 2 cost): far below anything the noise can tell apart, and the tail of tiny steps
  // beyond it is finite-difference noise.
  o.function_tolerance = 1e-3 / std::max(1.0, static_cast<double>(res.nmeas) - static_cast<double>(res.n));
  o.parameter_tolerance = 1e-9;
  o.gradient_tolerance = 1e-12;
  o.logging_type = ceres::SILENT;
  o.minimizer_progress_to_stdout = false;
  o.num_threads = 1;  // the cost function runs its own evaluations in parallel
  TraceCallback cb(s, res, pass, count, trace, reweigh);
  o.callbacks.push_back(&cb);
  ceres::Solver::Summary summary;
  ceres::Solve(o, &problem, &summary);
  return summary;
}

/// The minimax polish (see local_search); u, J (the fit's residual Jacobian at u, rows
/// weighted by inv_sigma, priors after the data) and cur (its simulation) are the
/// least-squares result's.
void minimax_polish(const TurnPatternProblem& p, const Residuals& res, std::vector<double> u, Eigen::MatrixXd J,
                    TurnPatternResult cur, const std::vector<double>& sigma, const std::vector<unsigned char>& outlier,
                    const LocalSearchSettings& s, LocalSearchResult& out) {
  const size_t n = res.n, nmeas = res.nmeas;
  // The turns held (outliers and doubtful peaks, see local_search) take no part in the polish (it
  // would chase a bad peak): its decisions see them as unmatched, its summary counts them again;
  // a held turn may not grow beyond the larger of its least-squares |residual| and the polished
  // worst turn, so the worst turn over all turns never rises.
  auto masked = [&](TurnPatternResult r) {
    for (size_t i = 0; i < nmeas && i < r.matched.size(); ++i)
      if (outlier[i]) r.matched[i] = 0;
    return r;
  };
  const FitSummary ls = summarize(masked(cur), sigma);
  const TurnPatternResult at_ls = cur;
  FitSummary best = ls;
  out.x_minimax = out.x;
  out.minimax = out.after;
  out.minimax_termination = "no step lowered the worst turn";
  while (out.minimax_steps < s.minimax_steps) {
    // The matched data rows, in mm per unit of scaled variable.
    std::vector<Eigen::Index> rows;
    for (size_t i = 0; i < nmeas; ++i)
      if (cur.matched[i] && !outlier[i]) rows.push_back(static_cast<Eigen::Index>(i));
    Eigen::MatrixXd Jm(static_cast<Eigen::Index>(rows.size()), static_cast<Eigen::Index>(n));
    Eigen::VectorXd r(static_cast<Eigen::Index>(rows.size()));
    Eigen::MatrixXd Je;  // whitened fit: the data rows back in mm (stage weights are 1 here)
    if (res.white) {
      Je = J.topRows(static_cast<Eigen::Index>(nmeas));
      res.white->color_columns(Je);
    }
    for (size_t k = 0; k < rows.size(); ++k) {
      const auto i = rows[k];
      Jm.row(static_cast<Eigen::Index>(k)) = res.white ? Eigen::RowVectorXd(Je.row(i)) : Eigen::RowVectorXd(J.row(i) * sigma[static_cast<size_t>(i)]);
      r(static_cast<Eigen::Index>(k)) = cur.delta_mm[static_cast<size_t>(i)];
    }
    const Eigen::VectorXd d = lawson_minimax_step(Jm, r, 1e-4);
    // Along the linearized minimax step, halved until the paper's rule accepts: the worst turn
    // falls linearly with the step length, the l2 (at its least-squares minimum) rises only
    // quadratically, so a short enough step passes unless the linear model is wrong.
    bool ok = false;
    std::vector<double> v(n), x;
    TurnPatternResult tr;
    FitSummary f;
    for (double t = 1; t >= 1.0 / 64 && !ok; t /= 2) {
      for (size_t j = 0; j < n; ++j) v[j] = std::min(std::max(u[j] + t * d(static_cast<Eigen::Index>(j)), 0.0), 1.0);
      x = res.x_of(v.data());
      tr = p.simulate(x);
      ++out.minimax_evaluations;
      f = summarize(masked(tr), sigma);
      ok = f.ok && f.violation <= ls.violation && f.matched >= ls.matched && f.linf_mm < best.linf_mm - 1e-6;
      if (ok) {
        const CoordinateNorms now = coordinate_norms(masked(cur), p.measured()),
                              trial = coordinate_norms(masked(tr), p.measured());
        ok = coordinate_accepts(now, trial, s.minimax_tolerance_mm, 1e-6);
      }
      for (size_t i = 0; i < nmeas && ok; ++i)
        if (outlier[i] && at_ls.matched[i])
          ok = tr.matched[i] && std::fabs(tr.delta_mm[i]) <= std::max(std::fabs(at_ls.delta_mm[i]), f.linf_mm) + 1e-9;
    }
    if (!ok) {
      out.minimax_termination = out.minimax_steps ? "converged (no step along the minimax direction passes the rule)"
                                                  : "no step lowered the worst turn";
      break;
    }
    u = v;
    cur = tr;
    best = f;
    out.x_minimax = x;
    out.minimax = summarize(tr, sigma);
    ++out.minimax_steps;
    out.minimax_termination = "step limit";
    if (out.minimax_steps == s.minimax_steps) break;
    res.form_jacobian(u);
    std::lock_guard<std::mutex> lock(res.mu);
    J = res.jac;
  }
}

/// The per-turn scatter s >= 0 beyond the peaks' own uncertainties e_i that makes
/// sum r_i^2 / (s^2 + e_i^2) = dof (chi2 per degree of freedom 1): the sum falls as s grows, so
/// bisection on s^2 between 0 and sum r^2 / dof finds it; 0 when the peaks' uncertainties alone
/// already leave chi2 below dof.
double scatter_beyond(const std::vector<double>& r2, const std::vector<double>& e2, double dof) {
  auto chi2 = [&](double s2) {
    double c = 0;
    for (size_t i = 0; i < r2.size(); ++i) c += r2[i] / (s2 + e2[i]);
    return c;
  };
  double hi = 0;
  for (double v : r2) hi += v;
  hi /= dof;
  if (!(hi > 0)) return 0;
  double lo = 0;
  bool zero_ok = true;
  for (double e : e2) zero_ok = zero_ok && e > 0;
  if (zero_ok && chi2(0) <= dof) return 0;
  for (int it = 0; it < 200 && hi - lo > 1e-12 * hi; ++it) {
    const double mid = 0.5 * (lo + hi);
    (chi2(mid) > dof ? lo : hi) = mid;
  }
  return std::sqrt(0.5 * (lo + hi));
}

/// The scatter s and the trust c in the peaks' own uncertainties e_i (sigma_i^2 = s^2 +
/// c^2 e_i^2) that the residuals favour: for each c of a grid (0, and 2^(k/2) from 1/64 to 4),
/// s from scatter_beyond so that chi2 = dof; of those that reach it, the one of largest Gaussian
/// likelihood, i.e. the smallest sum of log sigma_i^2 (chi2 being the same). A c at which the
/// peaks' uncertainties alone leave chi2 below dof is too large and not taken. Without peak
/// uncertainties: c = 0 and s as scatter_beyond gives it.
void estimate_scatter(const std::vector<double>& r2, const std::vector<double>& e2, double dof, double& s, double& c) {
  bool any = false;
  for (double e : e2) any = any || e > 0;
  if (!any) {
    s = scatter_beyond(r2, e2, dof);
    c = 0;
    return;
  }
  double best = std::numeric_limits<double>::infinity();
  std::vector<double> ce2(e2.size());
  for (int k = -13; k <= 4; ++k) {
    const double ck = k < -12 ? 0 : std::pow(2.0, 0.5 * k);
    for (size_t i = 0; i < e2.size(); ++i) ce2[i] = ck * ck * e2[i];
    const double sk = scatter_beyond(r2, ce2, dof);
    double chi2 = 0, logdet = 0;
    for (size_t i = 0; i < r2.size(); ++i) {
      const double v = sk * sk + ce2[i];
      if (!(v > 0)) {
        logdet = std::numeric_limits<double>::infinity();
        break;
      }
      chi2 += r2[i] / v;
      logdet += std::log(v);
    }
    if (chi2 < 0.99 * dof) continue;  // the peaks' uncertainties alone over-explain the residuals
    if (logdet < best) {
      best = logdet;
      s = sk;
      c = ck;
    }
  }
}

std::string fmt(double v, int digits = 3) {
  char b[48];
  std::snprintf(b, sizeof b, "%.*g", digits, v);
  return b;
}

}  // namespace

Eigen::VectorXd lawson_minimax_step(const Eigen::MatrixXd& J, const Eigen::VectorXd& r, double ridge, int sweeps) {
  const Eigen::Index m = J.rows(), n = J.cols();
  Eigen::VectorXd w = Eigen::VectorXd::Constant(m, 1.0 / static_cast<double>(std::max<Eigen::Index>(m, 1)));
  Eigen::VectorXd d = Eigen::VectorXd::Zero(n);
  for (int k = 0; k < sweeps; ++k) {
    const Eigen::MatrixXd A = J.transpose() * w.asDiagonal() * J;
    const double mu = ridge * std::max(A.trace() / static_cast<double>(std::max<Eigen::Index>(n, 1)), 1e-300);
    const Eigen::VectorXd b = -(J.transpose() * w.asDiagonal() * r);
    d = (A + mu * Eigen::MatrixXd::Identity(n, n)).ldlt().solve(b);
    const Eigen::VectorXd e = (r + J * d).cwiseAbs();
    const double total = w.dot(e);
    if (!(total > 0)) break;  // every residual zero: nothing left to balance
    w = w.cwiseProduct(e) / total;
  }
  return d;
}

namespace {

/// Andrews' AR(1) bandwidth for Bartlett's kernel from a series' lag-1 correlation rho over m
/// terms (0 when rho <= 0; rho at most 0.97, the bandwidth below m).
double andrews_bandwidth(double rho, Eigen::Index m) {
  if (!(rho > 0) || m < 2) return 0;
  rho = std::min(rho, 0.97);
  const double a = 4 * rho * rho / ((1 - rho) * (1 - rho) * (1 + rho) * (1 + rho));
  return std::min(1.1447 * std::cbrt(static_cast<double>(m) * a), static_cast<double>(m - 1));
}

/// sum_ij k(|i - j|) x_i y_j over a block, Bartlett's weights at bandwidth b.
double bartlett_sum(const Eigen::Ref<const Eigen::VectorXd>& x, const Eigen::Ref<const Eigen::VectorXd>& y, double b) {
  const Eigen::Index m = x.size();
  double s = x.dot(y);
  for (Eigen::Index k = 1; k < m && static_cast<double>(k) < b + 1; ++k) {
    const double w = 1 - static_cast<double>(k) / (b + 1);
    s += w * (x.head(m - k).dot(y.tail(m - k)) + x.tail(m - k).dot(y.head(m - k)));
  }
  return s;
}

double lag1_of(const Eigen::Ref<const Eigen::VectorXd>& h) {
  const Eigen::Index m = h.size();
  const double hh = h.squaredNorm();
  return hh > 0 && m > 1 ? h.head(m - 1).dot(h.tail(m - 1)) / hh : 0.0;
}

}  // namespace

Eigen::MatrixXd hac_covariance(const Eigen::MatrixXd& cov, const Eigen::MatrixXd& J, const std::vector<double>& z,
                               size_t ndata, const std::vector<std::pair<size_t, size_t>>& blocks,
                               std::vector<double>& lag1, std::vector<double>& bandwidth) {
  using Eigen::Index;
  const Index n = J.cols(), rows = J.rows(), nd = static_cast<Index>(ndata);
  if (cov.rows() != n || cov.cols() != n || static_cast<Index>(z.size()) != rows || nd > rows)
    throw Error(ExitCode::software, "hac_covariance: sizes do not agree");
  for (const auto& [b, e] : blocks)
    if (e > ndata || e < b) throw Error(ExitCode::software, "hac_covariance: a block outside the data rows");
  lag1.clear();
  bandwidth.clear();
  // The priors' part: their information, C J_p^T J_p C.
  const Eigen::MatrixXd JpC = J.bottomRows(rows - nd) * cov;
  Eigen::MatrixXd out = JpC.transpose() * JpC;
  // Each data row's influence on each variable: H(i, a) = (J C)(i, a) z_i.
  Eigen::MatrixXd H = J.topRows(nd) * cov;
  for (Index i = 0; i < nd; ++i) H.row(i) *= z[static_cast<size_t>(i)];
  for (const auto& [b, e] : blocks) {
    const Index m = static_cast<Index>(e - b);
    // The residual's own lag-1 correlation and bandwidth, reported per probe.
    Eigen::Map<const Eigen::VectorXd> zb(z.data() + b, m);
    const double rho = lag1_of(zb);
    lag1.push_back(rho);
    if (m == 0) {
      bandwidth.push_back(0);
      continue;
    }
    const auto Hb = H.middleRows(static_cast<Index>(b), m);
    // Each variable's own bandwidth, from its influence series' lag-1 correlation: the series
    // that matters for its variance (a residual that oscillates with a signature's column
    // demodulates into a slow influence even where the residual's lag-1 correlation is negative).
    std::vector<double> bw(static_cast<size_t>(n));
    for (Index a = 0; a < n; ++a) bw[static_cast<size_t>(a)] = andrews_bandwidth(lag1_of(Hb.col(a)), m);
    std::vector<double> sorted = bw;
    std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
    bandwidth.push_back(sorted.empty() ? 0.0 : sorted[sorted.size() / 2]);
    // A pair at the larger of its two bandwidths (one kernel per pair: every 2 x 2 block stays
    // positive semidefinite).
    for (Index a = 0; a < n; ++a)
      for (Index c = a; c < n; ++c) {
        const double v =
            bartlett_sum(Hb.col(a), Hb.col(c), std::max(bw[static_cast<size_t>(a)], bw[static_cast<size_t>(c)]));
        out(a, c) += v;
        if (c != a) out(c, a) += v;
      }
  }
  return out;
}

std::vector<std::string> describe_identifiability(const std::vector<std::string>& names, const Eigen::MatrixXd& Jd,
                                                  const Eigen::MatrixXd& correlation) {
  std::vector<std::string> out;
  const size_t n = names.size();
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(Jd, Eigen::ComputeFullV);
  const Eigen::VectorXd sv = svd.singularValues();
  // Weak directions: the turns fix them to worse than a tenth of a bound range (directions
  // beyond the rank have no singular value: not fixed at all).
  std::vector<Eigen::VectorXd> weak;
  std::vector<double> width;
  for (Eigen::Index k = 0; k < static_cast<Eigen::Index>(n); ++k) {
    const double s = k < sv.size() ? sv(k) : 0.0;
    const double w = s > 1e-12 * std::max(sv.size() ? sv(0) : 1.0, 1e-300) ? 1 / s : std::numeric_limits<double>::infinity();
    if (w < 0.1) continue;
    weak.push_back(svd.matrixV().col(k));
    width.push_back(w);
  }
  // The projector on the weak subspace (independent of how its basis was chosen): a variable
  // with at least 30 % of its unit vector in it is involved, and two involved variables whose
  // weak parts overlap (|P_jk| >= 0.3 sqrt(P_jj P_kk)) belong to one group.
  Eigen::MatrixXd P = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(n));
  for (const auto& v : weak) P += v * v.transpose();
  std::vector<size_t> parent(n);
  for (size_t j = 0; j < n; ++j) parent[j] = j;
  std::function<size_t(size_t)> root = [&](size_t j) { return parent[j] == j ? j : parent[j] = root(parent[j]); };
  auto Pe = [&](size_t j, size_t k) { return P(static_cast<Eigen::Index>(j), static_cast<Eigen::Index>(k)); };
  std::vector<char> involved(n, 0);
  for (size_t j = 0; j < n; ++j) involved[j] = Pe(j, j) >= 0.09;
  for (size_t j = 0; j < n; ++j)
    for (size_t k = j + 1; k < n; ++k)
      if (involved[j] && involved[k] && std::fabs(Pe(j, k)) >= 0.3 * std::sqrt(Pe(j, j) * Pe(k, k)))
        parent[root(k)] = root(j);
  std::map<size_t, std::vector<size_t>> groups;
  for (size_t j = 0; j < n; ++j)
    if (involved[j]) groups[root(j)].push_back(j);
  auto list = [&](const std::vector<size_t>& g) {
    std::string t;
    for (size_t k = 0; k < g.size(); ++k) {
      if (k == 6) return t + " and " + std::to_string(g.size() - 6) + " more";
      t += (k == 0 ? "" : (k + 1 == g.size() ? " and " : ", ")) + names[g[k]];
    }
    return t;
  };
  for (const auto& [r, g] : groups) {
    // The group's share of the weak subspace: its trace counts the free directions in it.
    const Eigen::Index gs = static_cast<Eigen::Index>(g.size());
    Eigen::MatrixXd Pg(gs, gs);
    for (Eigen::Index a = 0; a < gs; ++a)
      for (Eigen::Index b = 0; b < gs; ++b) Pg(a, b) = Pe(g[static_cast<size_t>(a)], g[static_cast<size_t>(b)]);
    // How loosely: the largest spread of the group's variables over the weak directions with a
    // width (sqrt of the top eigenvalue of sum_k width_k^2 v_k v_k^T on the group); infinite when
    // directions the turns do not depend on at all hold half a unit vector of the group.
    Eigen::MatrixXd Cg = Eigen::MatrixXd::Zero(gs, gs);
    double unfixed = 0;
    for (size_t k = 0; k < weak.size(); ++k) {
      Eigen::VectorXd vg(gs);
      for (Eigen::Index a = 0; a < gs; ++a) vg(a) = weak[k](static_cast<Eigen::Index>(g[static_cast<size_t>(a)]));
      if (std::isfinite(width[k])) Cg += width[k] * width[k] * vg * vg.transpose();
      else unfixed += vg.squaredNorm();
    }
    const double loosest = unfixed >= 0.5 ? std::numeric_limits<double>::infinity()
                                          : std::sqrt(std::max(0.0, Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(Cg).eigenvalues().maxCoeff()));
    const long free_dirs = std::lround(Pg.trace());
    const long fixed = static_cast<long>(g.size()) - free_dirs;
    const std::string how = std::isfinite(loosest) ? "the loosest combination to +-" + fmt(loosest, 2) + " of a bound range"
                                                   : "some combination not at all";
    if (g.size() == 1) {
      out.push_back(names[g[0]] + ": not determined by the turns (" +
                    (std::isfinite(loosest) ? "+-" + fmt(loosest, 2) + " of its bound range" : "they do not depend on it") + ")");
    } else if (fixed == 1) {
      // The one determined combination: the group's direction least in the weak subspace.
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(Pg);
      Eigen::VectorXd d = es.eigenvectors().col(0);  // smallest eigenvalue first
      Eigen::Index big = 0;
      d.cwiseAbs().maxCoeff(&big);
      if (d(big) < 0) d = -d;  // the largest coefficient 1
      const bool sum = d.minCoeff() > 0 && d.maxCoeff() < 1.5 * d.minCoeff();
      std::string combo;
      for (size_t a = 0; a < g.size(); ++a) {
        const double cf = d(static_cast<Eigen::Index>(a)) / d(big);
        combo += (a == 0 ? (cf < 0 ? "-" : "") : (cf < 0 ? " - " : " + ")) + fmt(std::fabs(cf), 2) + " " + names[g[a]];
      }
      out.push_back(list(g) + ": only " + (sum ? "their sum (in bound ranges) is determined" : combo + " is determined") +
                    "; the turns fix " + how);
    } else if (fixed <= 0) {
      out.push_back(list(g) + ": not determined by the turns, alone or together (" + how + ")");
    } else {
      out.push_back(list(g) + ": only " + std::to_string(fixed) + " combinations of these " + std::to_string(g.size()) +
                    " are determined; the turns fix " + how);
    }
  }
  // Strongly correlated pairs, strongest first (at most 12).
  std::vector<std::tuple<double, size_t, size_t>> pairs;
  for (size_t j = 0; j < n; ++j)
    for (size_t k = j + 1; k < n; ++k)
      if (std::fabs(correlation(static_cast<Eigen::Index>(j), static_cast<Eigen::Index>(k))) >= 0.95)
        pairs.emplace_back(-std::fabs(correlation(static_cast<Eigen::Index>(j), static_cast<Eigen::Index>(k))), j, k);
  std::sort(pairs.begin(), pairs.end());
  for (size_t q = 0; q < pairs.size() && q < 12; ++q) {
    const auto [c, j, k] = pairs[q];
    char cbuf[32];
    std::snprintf(cbuf, sizeof cbuf, "%.3f", correlation(static_cast<Eigen::Index>(j), static_cast<Eigen::Index>(k)));
    out.push_back(names[j] + " and " + names[k] + ": " + cbuf + " correlated");
  }
  if (pairs.size() > 12) out.push_back("and " + std::to_string(pairs.size() - 12) + " more pairs correlated above 0.95");
  return out;
}

LocalSearchResult local_search(TurnPatternProblem& p, const std::vector<double>& x0,
                               const LocalSearchSettings& s) {
  quiet_ceres_logging();
  const auto wall0 = std::chrono::steady_clock::now();
  const std::clock_t cpu0 = std::clock();
  const size_t n = p.n_variables();
  if (x0.size() != n) throw Error(ExitCode::software, "local_search: a start of the wrong size");
  if (s.weak_prior_centre.size() > n) throw Error(ExitCode::software, "local_search: a weak prior centre of the wrong size");
  for (size_t j = 0; j < n; ++j)
    if (!(x0[j] >= p.lower()[j] && x0[j] <= p.upper()[j]))
      throw usage_error("the start's " + p.variables()[j].name + " = " + fmt(x0[j], 10) + " lies outside its bounds [" +
                        fmt(p.lower()[j], 10) + ", " + fmt(p.upper()[j], 10) + "]");

  LocalSearchResult out;
  const TurnTable& meas = p.measured();
  const size_t nmeas = meas.points.size();

  // Peak-position uncertainty: the problem's; else a per-turn scatter s_p and each peak's own
  // uncertainty e_i (peakfind's r_err_mm, 0 when the peaks have none) times a trust c_p per
  // probe, in quadrature: first the wire step / sqrt(12) and c_p = 0, then both estimated from
  // the converged residuals.
  std::vector<double> sigma = p.sigma_mm();
  const bool estimate = sigma.empty();
  std::vector<double> peak_e2(nmeas, 0);  // peakfind's uncertainty squared
  std::vector<double> scatter;            // per probe
  std::vector<double> trust;              // per probe: c_p
  std::vector<double> outlier_factor(nmeas, 1);  // Huber's down-weighting: sigma times this
  auto sigma_from_scatter = [&] {
    for (size_t q = 0; q < meas.probes.size(); ++q) {
      auto [b, e] = meas.probe_range(static_cast<int>(q));
      for (size_t i = b; i < e; ++i)
        sigma[i] = outlier_factor[i] * std::sqrt(scatter[q] * scatter[q] + trust[q] * trust[q] * peak_e2[i]);
    }
  };
  if (estimate) {
    sigma.assign(nmeas, 0);
    for (size_t i = 0; i < nmeas; ++i) {
      const double e = meas.points[i].r_err_mm;
      if (std::isfinite(e) && e > 0) {
        peak_e2[i] = e * e;
        ++out.peak_uncertainties;
      }
    }
    for (size_t q = 0; q < meas.probes.size(); ++q) {
      double step = 0;
      for (const auto& pr : p.machine().probes)
        if (pr.name == meas.probes[q]) step = pr.step_mm;
      scatter.push_back((step > 0 ? step : 0.5) / std::sqrt(12.0));
      trust.push_back(0);
    }
    sigma_from_scatter();
  }

  size_t own_evaluations = 0;  // designs simulated here, outside the fit's residuals
  auto simulate = [&](const std::vector<double>& x) {
    ++own_evaluations;
    return p.simulate(x);
  };
  // The bunch's centroid shift at x (centroid mode): the largest change [mm].
  const unsigned threads = resolve_thread_count(s.threads);
  auto update_centroid = [&](const std::vector<double>& x) {
    if (p.bunch_nodes().empty()) return 0.0;
    const double change = p.update_centroid_shift(x, threads);
    out.centroid_tracks += p.bunch_nodes().size() + 1;
    ++out.centroid_updates;
    out.centroid_change_mm = change;
    return change;
  };
  if (p.current_centroid_shift().x != x0) update_centroid(x0);
  const TurnPatternResult start = simulate(x0);
  if (!start.ok) throw Error(ExitCode::data, p.file() + ": the start cannot be simulated: " + start.reason);
  if (p.scan_noise().active() && estimate)
    throw Error(ExitCode::data, p.file() + ": scan_noise needs sigma_mm, the turns' independent uncertainty (a fit "
                                           "cannot estimate it beside the correlated drive error; turnfit-diagnose does)");
  out.before = summarize(start, sigma, meas, p.scan_noise());
  if (out.before.matched == 0)
    throw Error(ExitCode::data, p.file() + ": the start reaches no measured turn (" + start.end.status + ")");

  Residuals res(p);
  res.n = n;
  res.nmeas = nmeas;
  res.threads = threads;
  res.h = s.fd_step;
  res.central = s.central;
  res.weak = s.weak_prior_range;
  res.miss_mm = s.miss_penalty_mm > 0 ? s.miss_penalty_mm : std::max(10.0, 2 * out.before.linf_mm);
  std::vector<double> u(n);
  for (size_t j = 0; j < n; ++j) {
    res.lo.push_back(p.lower()[j]);
    res.range.push_back(p.upper()[j] - p.lower()[j]);
    u[j] = (x0[j] - res.lo[j]) / res.range[j];
    const TurnVariable& v = p.variables()[j];
    res.prior_x0.push_back(v.start);
    res.prior_sigma_x.push_back(v.sigma);
    res.prior_kind.push_back(v.sigma > 0 ? 1 : (s.weak_prior_range > 0 ? 2 : 0));
  }
  res.weak_u0 = u;
  for (size_t j = 0; j < s.weak_prior_centre.size(); ++j)
    res.weak_u0[j] = (s.weak_prior_centre[j] - res.lo[j]) / res.range[j];
  res.nres = nmeas;
  for (int k : res.prior_kind) res.nres += k ? 1 : 0;
  res.inv_sigma.resize(nmeas);
  std::vector<size_t> all_points(nmeas);
  for (size_t i = 0; i < nmeas; ++i) all_points[i] = i;
  if (p.scan_noise().active()) res.white = std::make_unique<Whitener>(meas, all_points, sigma, p.scan_noise());
  // A point's row weight: 1 / sigma (whitened: the whitener has it), times the stage weight.
  auto row_weight = [&](size_t i, double stage) { return res.white ? stage : stage / sigma[i]; };
  for (size_t i = 0; i < nmeas; ++i) res.inv_sigma[i] = row_weight(i, 1.0);
  res.max_frozen = std::max(0, s.frozen_steps);
  res.broyden = s.broyden;

  // The fit's state is theta (see TurnCost); u follows it.
  std::vector<double> theta(n);
  for (size_t j = 0; j < n; ++j) theta[j] = TurnCost::theta_of_u(u[j]);
  const std::function<size_t()> count = [&] { return res.evaluations + own_evaluations; };
  // A pass that ended on a frozen Jacobian ended by that Jacobian's model, not by the cost's: it
  // goes on from a fresh one (at most 10 times) until it ends on a fresh Jacobian.
  auto settle = [&](ceres::Solver::Summary& sm, int pass) {
    for (int k = 0; res.stale && k < 10; ++k) {
      res.form_jacobian(u_of(theta));
      sm = lm_pass(res, theta, s, pass, count, out.trace);
      out.iterations += static_cast<int>(sm.iterations.size());
    }
  };
  // Pass 1 by turn continuation: first the turns up to a third of the measured turn range, then
  // up to two thirds, then all (s.stages), the turns beyond weighed 1e-3 of theirs. A turn's
  // radius carries every error before it, so a far design misplaces the outer turns by whole
  // turn separations in ways the inner ones do not: fitted all at once from nominal ring8, the
  // shipped measurement's 190 turns led the 48 variables into a false minimum (0.945 mm worst,
  // rrlphi on its bound, tc13-16mb 40-67 sigma off) where a start near the answer reached 0.164.
  // Each stage starts on the last one's Jacobian, its rows reweighted.
  ceres::Solver::Summary sum;
  {
    int t_lo = std::numeric_limits<int>::max(), t_hi = std::numeric_limits<int>::min();
    for (const auto& pt : meas.points) {
      t_lo = std::min(t_lo, pt.turn);
      t_hi = std::max(t_hi, pt.turn);
    }
    const int stages = std::max(1, s.stages);
    for (int st = 1; st <= stages; ++st) {
      const double last = t_lo + (t_hi - t_lo) * static_cast<double>(st) / stages;
      const std::vector<double> old_inv_sigma = res.inv_sigma;
      for (size_t i = 0; i < nmeas; ++i)
        res.inv_sigma[i] = row_weight(i, st == stages || meas.points[i].turn <= last ? 1.0 : 1e-3);
      if (st > 1 && res.restart_at(u_of(theta), old_inv_sigma)) ++out.kept_jacobians;
      sum = lm_pass(res, theta, s, 1, count, out.trace);
      out.iterations += static_cast<int>(sum.iterations.size());
      settle(sum, 1);
    }
  }
  out.sigma_probes = meas.probes;
  // Then, at the converged design: the centroid shift again (centroid mode), and the per-turn
  // scatter per probe with chi2 per degree of freedom 1 (when the problem gives no sigma), from
  // the converged residuals, with dof = N_p - n N_p / N; a pass with them; again while the shift
  // moves by more than a tenth of the smallest sigma or a turn's sigma by more than 10 % (a
  // first pass far from the optimum over-estimates it), at most 5 passes in all.
  for (int pass = 2; pass <= 5 && (estimate || !p.bunch_nodes().empty()); ++pass) {
    u = u_of(theta);
    const double shift_change = update_centroid(res.x_of(u.data()));
    const bool shift_moved = shift_change > 0.1 * *std::min_element(sigma.begin(), sigma.end());
    bool moved = false;
    std::vector<double> est;
    std::vector<double> factor(nmeas, 1), est_trust;
    std::optional<TurnPatternResult> at_u;  // u's simulation under the new shift, when made here
    if (estimate) {
      const TurnPatternResult& r1 = at_u.emplace(simulate(res.x_of(u.data())));
      size_t nmatched = 0;
      for (size_t i = 0; i < nmeas; ++i) nmatched += r1.ok && r1.matched[i];
      for (size_t q = 0; q < meas.probes.size(); ++q) {
        auto [b, e] = meas.probe_range(static_cast<int>(q));
        // The scatter and the trust in the peaks' own uncertainties from the turns within huber_k
        // of their sigma (all at first), then the outliers by those, until the set stops changing.
        std::vector<unsigned char> out_of(e - b, 0);
        double sp = scatter[q], cp = trust[q];
        for (int round = 0; round < 10; ++round) {
          std::vector<double> r2, e2;
          for (size_t i = b; i < e; ++i)
            if (r1.ok && r1.matched[i] && !out_of[i - b]) {
              r2.push_back(r1.delta_mm[i] * r1.delta_mm[i]);
              e2.push_back(peak_e2[i]);
            }
          const double np = static_cast<double>(r2.size());
          const double dof = np - static_cast<double>(n) * np / static_cast<double>(std::max<size_t>(nmatched, 1));
          if (np > 0 && dof > 0.5) estimate_scatter(r2, e2, dof, sp, cp);
          if (!(s.huber_k > 0)) break;
          bool changed = false;
          for (size_t i = b; i < e; ++i) {
            const bool o = r1.ok && r1.matched[i] &&
                           std::fabs(r1.delta_mm[i]) > s.huber_k * std::sqrt(sp * sp + cp * cp * peak_e2[i]);
            changed = changed || o != static_cast<bool>(out_of[i - b]);
            out_of[i - b] = o;
          }
          if (!changed) break;
        }
        est.push_back(sp);
        est_trust.push_back(cp);
        for (size_t i = b; i < e; ++i)
          if (out_of[i - b])
            factor[i] = std::sqrt(std::fabs(r1.delta_mm[i]) / (s.huber_k * std::sqrt(sp * sp + cp * cp * peak_e2[i])));
      }
      // Moved: a turn's sigma changes by more than 10 %.
      for (size_t q = 0; q < meas.probes.size(); ++q) {
        auto [b, e] = meas.probe_range(static_cast<int>(q));
        for (size_t i = b; i < e && !moved; ++i)
          moved = std::fabs(factor[i] * std::sqrt(est[q] * est[q] + est_trust[q] * est_trust[q] * peak_e2[i]) - sigma[i]) >
                  0.1 * sigma[i];
      }
    }
    // The last pass's weights are within 10 % of these and its shift within a tenth of sigma: keep them.
    if (!shift_moved && (!estimate || (pass > 2 && !moved))) break;
    if (estimate) {
      scatter = est;
      trust = est_trust;
      out.peak_trust = trust;
      outlier_factor = factor;
      sigma_from_scatter();
      out.sigma_mm = est;
    }
    const std::vector<double> old_inv_sigma = res.inv_sigma;
    for (size_t i = 0; i < nmeas; ++i) res.inv_sigma[i] = row_weight(i, 1.0);
    // The new pass starts where the last one ended: u's residuals evaluated anew (new weights,
    // new centroid shift), the Jacobian there kept with its rows reweighted (the shift hardly
    // depends on the design: its derivatives are left out).
    if (res.restart_at(u, old_inv_sigma, at_u ? &*at_u : nullptr)) {
      ++out.kept_jacobians;
      if (s.check_kept_jacobian) {
        Point at;
        at.u = u;
        const Eigen::MatrixXd fresh = res.fd_jacobian(at);
        std::lock_guard<std::mutex> lock(res.mu);
        const double scale = std::max(fresh.cwiseAbs().maxCoeff(), 1e-300);
        out.kept_jacobian_difference =
            std::max(out.kept_jacobian_difference, (fresh - res.jac).cwiseAbs().maxCoeff() / scale);
      }
    }
    // A pass whose weights came from an earlier pass's residuals ends as soon as some probe's chi2
    // per degree of freedom falls below 0.81 at a fresh Jacobian: chi2 only falls within a pass,
    // so its sigma will come out more than 10 % smaller and the next pass is certain; crawling on
    // to this pass's optimum under weights about to change cost blind case truths 400-700 designs.
    // Never in the last pass allowed: nothing would follow it.
    const std::function<bool()> reweigh = [&]() {
      if (!estimate || pass >= 5) return false;
      std::lock_guard<std::mutex> lock(res.mu);
      if (res.kept.res.size() != res.nres) return false;
      size_t nmatched = 0;
      for (size_t i = 0; i < nmeas; ++i) nmatched += res.kept.matched[i];
      for (size_t q = 0; q < meas.probes.size(); ++q) {
        auto [b, e] = meas.probe_range(static_cast<int>(q));
        double chi2 = 0, np = 0;
        for (size_t i = b; i < e; ++i)
          if (res.kept.matched[i]) {
            chi2 += res.kept.res[i] * res.kept.res[i];
            np += 1;
          }
        const double dof = np - static_cast<double>(n) * np / static_cast<double>(std::max<size_t>(nmatched, 1));
        if (dof > 0.5 && chi2 / dof < 0.81) return true;
      }
      return false;
    };
    sum = lm_pass(res, theta, s, pass, count, out.trace, reweigh);
    out.iterations += static_cast<int>(sum.iterations.size());
    settle(sum, pass);
    out.sigma_passes = pass;
  }
  if (estimate) {
    out.sigma_source = out.peak_uncertainties
                           ? "a per-turn scatter per probe and each peak's own uncertainty (the peaks' r_err_mm) "
                             "times a trust per probe, in quadrature, both estimated from the converged residuals "
                             "(chi2 per degree of freedom 1, the trust of largest likelihood), re-estimated until "
                             "sigma moves by less than 10 %; first pass: the wire step / sqrt(12)"
                           : "estimated per probe from the converged residuals (chi2 per degree of freedom 1), "
                             "re-estimated until it moves by less than 10 %; first pass weighted by each probe's wire "
                             "step / sqrt(12)";
  } else {
    for (size_t q = 0; q < meas.probes.size(); ++q) out.sigma_mm.push_back(sigma[meas.probe_range(static_cast<int>(q)).first]);
    out.sigma_source = "problem file (sigma_mm)";
  }
  u = u_of(theta);
  out.termination = ceres::TerminationTypeToString(sum.termination_type);
  out.x = res.x_of(u.data());
  const TurnPatternResult fin = simulate(out.x);
  out.after = summarize(fin, sigma, meas, p.scan_noise());
  for (size_t i = 0; i < nmeas; ++i)
    if (outlier_factor[i] > 1)
      out.outliers.push_back({i, fin.ok && fin.matched[i] ? fin.delta_mm[i] : std::nan(""), sigma[i] / outlier_factor[i],
                              sigma[i]});
  out.before = summarize(start, sigma, meas, p.scan_noise());  // chi2 with the final sigma, comparable with after's
  const double dof = static_cast<double>(out.after.matched) - static_cast<double>(n);
  out.chi2_dof = dof > 0 ? out.after.chi2 / dof : std::nan("");

  // Statistics at the result: the Jacobian there (reused when Ceres' last one was there).
  Eigen::MatrixXd J;
  Point at_u;  // the residual rows at u
  {
    std::lock_guard<std::mutex> lock(res.mu);
    if (res.kept.u == u && !res.stale) {
      J = res.jac;
      at_u = res.kept;
    }
  }
  if (J.size() == 0) {
    res.form_jacobian(u);
    std::lock_guard<std::mutex> lock(res.mu);
    J = res.jac;
    at_u = res.kept;
  }
  // A turn the design did not match carries a fixed miss (no slope): no part in the sandwich.
  std::vector<double> z_at = at_u.res;
  for (size_t i = 0; i < nmeas && i < at_u.matched.size(); ++i)
    if (!at_u.matched[i]) z_at[i] = 0;
  std::vector<std::pair<size_t, size_t>> probe_blocks;
  for (size_t q = 0; q < meas.probes.size(); ++q) probe_blocks.push_back(meas.probe_range(static_cast<int>(q)));
  const Eigen::MatrixXd Jd = J.topRows(static_cast<Eigen::Index>(nmeas));
  // Posterior (priors included): pseudo-inverse of J^T J.
  Eigen::JacobiSVD<Eigen::MatrixXd> svd_full(J, Eigen::ComputeThinV);
  const Eigen::VectorXd sf = svd_full.singularValues();
  Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(n, n);
  for (Eigen::Index k = 0; k < sf.size(); ++k)
    if (sf(k) > sf(0) * 1e-12) cov += svd_full.matrixV().col(k) * svd_full.matrixV().col(k).transpose() / (sf(k) * sf(k));
  // What the turns determine: the data with a reference prior of one whole bound range (not
  // the fit's weak prior: with --weak-prior 0.1 that prior alone would pass the tenth-of-a-range
  // test for every variable).
  const Eigen::MatrixXd cov_data = (Jd.transpose() * Jd + Eigen::MatrixXd::Identity(n, n)).inverse();
  const Eigen::MatrixXd cov_robust =
      hac_covariance(cov, J, z_at, nmeas, probe_blocks, out.robust.lag1, out.robust.bandwidth);
  out.correlation = Eigen::MatrixXd::Zero(n, n);
  out.robust.correlation = Eigen::MatrixXd::Zero(n, n);
  for (size_t j = 0; j < n; ++j) {
    FittedVariable v;
    const TurnVariable& tv = p.variables()[j];
    v.name = tv.name;
    v.unit = tv.unit;
    v.start = x0[j];
    v.value = out.x[j];
    v.sigma = std::sqrt(std::max(0.0, cov(j, j))) * res.range[j];
    v.sigma_robust = std::sqrt(std::max({0.0, cov(j, j), cov_robust(j, j)})) * res.range[j];
    v.lower = p.lower()[j];
    v.upper = p.upper()[j];
    v.determined = std::sqrt(std::max(0.0, cov_data(j, j))) < 0.1;
    v.at_bound = u[j] <= 1e-6 || u[j] >= 1 - 1e-6;  // the sine transform reaches a bound asymptotically
    out.variables.push_back(v);
    for (size_t k = 0; k < n; ++k) {
      const double d = std::sqrt(std::max(0.0, cov(j, j) * cov(k, k)));
      out.correlation(j, k) = d > 0 ? cov(j, k) / d : (j == k ? 1 : 0);
      const double dr = std::sqrt(std::max(0.0, cov_robust(j, j) * cov_robust(k, k)));
      out.robust.correlation(j, k) = dr > 0 ? cov_robust(j, k) / dr : (j == k ? 1 : 0);
    }
  }
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(Jd, Eigen::ComputeThinV);
  const Eigen::VectorXd sv = svd.singularValues();
  for (Eigen::Index k = 0; k < sv.size(); ++k) out.singular_values.push_back(sv(k));

  std::vector<std::string> names;
  for (const auto& v : p.variables()) names.push_back(v.name);
  out.identifiability = describe_identifiability(names, Jd, out.correlation);

  const size_t fit_evaluations = res.evaluations;
  // The polish holds (leaves out of its worst turn, and keeps from growing) the outliers and the
  // turns whose peaks are doubtful: sigma over 3 times its probe's median, a peak uncertainty
  // that dwarfs the scatter (a merged or cut turn). A worst turn made of such a peak is the
  // peak's error: on fresh blind truths the polish chased merged peaks 0.45-0.93 mm off and moved
  // 0.19-0.24 mm from the true centres, from least squares' 0.006-0.034.
  std::vector<unsigned char> held(nmeas, 0);
  for (const auto& o : out.outliers) held[o.point] = 1;
  for (size_t q = 0; q < meas.probes.size(); ++q) {
    auto [b, e] = meas.probe_range(static_cast<int>(q));
    if (e <= b) continue;
    std::vector<double> sq(sigma.begin() + static_cast<std::ptrdiff_t>(b), sigma.begin() + static_cast<std::ptrdiff_t>(e));
    std::nth_element(sq.begin(), sq.begin() + static_cast<std::ptrdiff_t>(sq.size() / 2), sq.end());
    const double median = sq[sq.size() / 2];
    for (size_t i = b; i < e; ++i)
      if (sigma[i] > 3 * median) held[i] = 1;
  }
  for (unsigned char h : held) out.minimax_held += h;
  if (s.minimax) minimax_polish(p, res, u, J, fin, sigma, held, s, out);  // counts its trial designs
  const size_t polish_jacobians = res.evaluations - fit_evaluations;
  out.evaluations = res.evaluations + own_evaluations + out.minimax_evaluations + out.centroid_tracks;
  out.centroid_rms_mm = p.current_centroid_shift().rms_mm;
  out.centroid_max_mm = p.current_centroid_shift().max_abs_mm;
  out.minimax_evaluations += polish_jacobians;
  out.jacobians = res.jacobians;
  out.frozen_steps = res.frozen_steps;
  out.failed_evaluations = res.failed;
  out.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
  out.cpu_s = static_cast<double>(std::clock() - cpu0) / CLOCKS_PER_SEC;
  return out;
}

}  // namespace turnfit
