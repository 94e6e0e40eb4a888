// Rational least-squares fits with Ceres (paper Sec. II.C, Eq. 2: delta sin(phi) ~ f(r)/g(r)).
#include "turnfit/trimcoil/rational_fit.hpp"

#include <ceres/ceres.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "turnfit/io/error.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

namespace turnfit {
namespace {

constexpr double kMinDenominator = 1e-9;  // g(0) = 1: a denominator this small is a pole
constexpr int kGuardPoints = 257;         // where g > 0 is enforced during the fit

double horner(const double* c, int deg, double x) {
  double p = 0;
  for (int k = deg; k >= 0; --k) p = p * x + c[k];
  return p;
}

/// g(x) = 1 + b_1 x + ... + b_m x^m from the parameter vector (a_0..a_n, b_1..b_m).
double denominator(const double* theta, int n, int m, double x) {
  double p = 0;
  for (int k = m; k >= 1; --k) p = (p + theta[n + k]) * x;
  return 1 + p;
}

/// Residuals q(x_i) - y_i of a rational function with b_0 = 1, analytic Jacobian. A trial point
/// whose denominator is not positive on the whole guard grid fails to evaluate: Ceres then
/// counts the step as infinitely bad and shrinks its trust region, so the iterates never cross
/// a pole into the window.
class RationalResiduals final : public ceres::CostFunction {
 public:
  RationalResiduals(const std::vector<double>& x, const std::vector<double>& y, int n, int m,
                    const std::vector<double>& guard)
      : x_(x), y_(y), n_(n), m_(m), guard_(guard) {
    set_num_residuals(static_cast<int>(x.size()));
    mutable_parameter_block_sizes()->push_back(n + 1 + m);
  }

  bool Evaluate(double const* const* params, double* res, double** jac) const override {
    const double* th = params[0];
    if (m_ > 0)
      for (double xg : guard_)
        if (!(denominator(th, n_, m_, xg) > kMinDenominator)) return false;
    const int p = n_ + 1 + m_;
    for (size_t i = 0; i < x_.size(); ++i) {
      const double x = x_[i];
      const double f = horner(th, n_, x), g = denominator(th, n_, m_, x);
      if (!(g > kMinDenominator)) return false;
      const double q = f / g;
      res[i] = q - y_[i];
      if (jac && jac[0]) {
        double* row = jac[0] + i * static_cast<size_t>(p);
        double xk = 1;
        for (int k = 0; k <= n_; ++k, xk *= x) row[k] = xk / g;
        xk = x;
        for (int k = 1; k <= m_; ++k, xk *= x) row[n_ + k] = -q * xk / g;
      }
    }
    return true;
  }

 private:
  const std::vector<double>& x_;
  const std::vector<double>& y_;
  int n_, m_;
  const std::vector<double>& guard_;
};

struct Trial {
  std::vector<double> theta;  // (a_0..a_n, b_1..b_m) for the scaled data
  double cost = std::numeric_limits<double>::infinity();
  int iterations = 0;
  bool converged = false;
  std::string start;
};

bool feasible(const std::vector<double>& theta, int n, int m, const std::vector<double>& guard) {
  if (m == 0) return true;
  for (double xg : guard)
    if (!(denominator(theta.data(), n, m, xg) > kMinDenominator)) return false;
  return true;
}

/// Linear least squares A t = rhs with row weights w (column-pivoting QR: rank-deficient safe).
Eigen::VectorXd weighted_lsq(const Eigen::MatrixXd& A, const Eigen::VectorXd& rhs, const Eigen::VectorXd& w) {
  const Eigen::MatrixXd Aw = w.asDiagonal() * A;
  const Eigen::VectorXd bw = w.asDiagonal() * rhs;
  return Aw.colPivHouseholderQr().solve(bw);
}

/// Polynomial least squares of degree n (g = 1), as a parameter vector padded for m.
std::vector<double> polynomial_start(const std::vector<double>& x, const std::vector<double>& y, int n, int m) {
  const size_t N = x.size();
  Eigen::MatrixXd A(N, n + 1);
  Eigen::VectorXd rhs(N);
  for (size_t i = 0; i < N; ++i) {
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= x[i]) A(static_cast<Eigen::Index>(i), k) = xk;
    rhs(static_cast<Eigen::Index>(i)) = y[i];
  }
  const Eigen::VectorXd t = weighted_lsq(A, rhs, Eigen::VectorXd::Ones(static_cast<Eigen::Index>(N)));
  std::vector<double> theta(static_cast<size_t>(n + 1 + m), 0.0);
  for (int k = 0; k <= n; ++k) theta[static_cast<size_t>(k)] = t(k);
  return theta;
}

/// The linearized problem f(x_i) - y_i g(x_i) = 0 (Levy), reweighted by 1/g of the previous
/// iterate so that it approaches the true least squares (Sanathanan-Koerner). Returns the
/// iterate with the smallest true residual among those with a root-free denominator (empty if
/// none was).
std::vector<double> linearized_start(const std::vector<double>& x, const std::vector<double>& y, int n, int m,
                                     const std::vector<double>& guard) {
  const size_t N = x.size();
  const int p = n + 1 + m;
  Eigen::MatrixXd A(N, p);
  Eigen::VectorXd rhs(N), w = Eigen::VectorXd::Ones(static_cast<Eigen::Index>(N));
  for (size_t i = 0; i < N; ++i) {
    const auto ii = static_cast<Eigen::Index>(i);
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= x[i]) A(ii, k) = xk;
    xk = x[i];
    for (int k = 1; k <= m; ++k, xk *= x[i]) A(ii, n + k) = -y[i] * xk;
    rhs(ii) = y[i];
  }
  std::vector<double> best;
  double best_cost = std::numeric_limits<double>::infinity();
  for (int it = 0; it < 8; ++it) {
    const Eigen::VectorXd t = weighted_lsq(A, rhs, w);
    if (!t.allFinite()) break;
    std::vector<double> theta(t.data(), t.data() + p);
    if (!feasible(theta, n, m, guard)) break;  // the reweighting needs a root-free g
    double cost = 0;
    for (size_t i = 0; i < N; ++i) {
      const double g = denominator(theta.data(), n, m, x[i]);
      const double r = horner(theta.data(), n, x[i]) / g - y[i];
      cost += r * r;
      w(static_cast<Eigen::Index>(i)) = 1 / g;
    }
    if (cost < best_cost) {
      best_cost = cost;
      best = theta;
    }
  }
  return best;
}

Trial solve(const std::vector<double>& x, const std::vector<double>& y, int n, int m,
            const std::vector<double>& guard, std::vector<double> theta, const std::string& start, int max_iterations) {
  Trial t;
  t.start = start;
  if (!feasible(theta, n, m, guard)) return t;
  ceres::Problem::Options po;
  ceres::Problem problem(po);
  problem.AddResidualBlock(new RationalResiduals(x, y, n, m, guard), nullptr, theta.data());
  ceres::Solver::Options o;
  o.minimizer_type = ceres::TRUST_REGION;
  o.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  o.linear_solver_type = ceres::DENSE_QR;
  o.max_num_iterations = max_iterations;
  o.function_tolerance = 1e-15;
  o.gradient_tolerance = 1e-16;
  o.parameter_tolerance = 1e-14;
  o.logging_type = ceres::SILENT;
  o.minimizer_progress_to_stdout = false;
  o.num_threads = 1;
  ceres::Solver::Summary s;
  ceres::Solve(o, &problem, &s);
  t.iterations = static_cast<int>(s.iterations.size());
  t.converged = s.termination_type == ceres::CONVERGENCE;
  if (s.termination_type == ceres::FAILURE || !std::isfinite(s.final_cost)) return t;
  t.cost = s.final_cost;
  t.theta = theta;
  return t;
}

std::vector<double> padded(const RationalFit& f, int n, int m, double scale) {
  std::vector<double> th(static_cast<size_t>(n + 1 + m), 0.0);
  for (int k = 0; k <= f.n; ++k) th[static_cast<size_t>(k)] = f.a[static_cast<size_t>(k)] / scale;
  for (int k = 1; k <= f.m; ++k) th[static_cast<size_t>(n + k)] = f.b[static_cast<size_t>(k)];
  return th;
}

}  // namespace

void RationalFit::eval(double r, double& q, double& dq, double& d2q) const {
  rational(a, b, x_of(r), q, dq, d2q);
  dq /= half_width;
  d2q /= half_width * half_width;
}

double RationalFit::value(double r) const {
  double q, dq, d2q;
  eval(r, q, dq, d2q);
  return q;
}

double RationalFit::value_sigma(double r) const {
  if (covariance.size() == 0) return 0;
  const double x = x_of(r);
  const double f = horner(a.data(), n, x), g = horner(b.data(), m, x), q = f / g;
  Eigen::VectorXd grad(parameters());
  double xk = 1;
  for (int k = 0; k <= n; ++k, xk *= x) grad(k) = xk / g;
  xk = x;
  for (int k = 1; k <= m; ++k, xk *= x) grad(n + k) = -q * xk / g;
  const double v = grad.dot(covariance * grad);
  return v > 0 ? std::sqrt(v) : 0;
}

Eigen::VectorXd RationalFit::slope_gradient(double r) const {
  // D = dq/dx = (f' g - f g') / g^2; d/da_k and d/db_k by the quotient rule, then / half_width.
  const double x = x_of(r);
  double f = 0, df = 0, g = 0, dg = 0;
  for (int k = n; k >= 0; --k) {
    df = df * x + f;
    f = f * x + a[static_cast<size_t>(k)];
  }
  for (int k = m; k >= 0; --k) {
    dg = dg * x + g;
    g = g * x + b[static_cast<size_t>(k)];
  }
  const double D = (df * g - f * dg) / (g * g);
  Eigen::VectorXd grad(parameters());
  for (int k = 0; k <= n; ++k) {
    const double xk = std::pow(x, k), xk1 = k > 0 ? k * std::pow(x, k - 1) : 0.0;
    grad(k) = (xk1 * g - xk * dg) / (g * g);
  }
  for (int k = 1; k <= m; ++k) {
    const double xk = std::pow(x, k), xk1 = k * std::pow(x, k - 1);
    grad(n + k) = (df * xk - f * xk1) / (g * g) - 2 * D * xk / g;
  }
  return grad / half_width;
}

std::vector<double> polynomial_in_r(const std::vector<double>& c_x, double centre, double half_width) {
  // p(x) with x = (r - c)/h = sum_k c_k h^-k (r - c)^k; (r - c)^k expanded by the binomial theorem.
  const size_t n = c_x.size();
  std::vector<long double> out(n, 0.0L);
  const long double c = centre, hinv = 1.0L / static_cast<long double>(half_width);
  for (size_t k = 0; k < n; ++k) {
    long double coef = static_cast<long double>(c_x[k]);
    for (size_t i = 0; i < k; ++i) coef *= hinv;
    long double binom = 1;  // C(k, j)
    for (size_t j = 0; j <= k; ++j) {
      long double pw = 1;  // (-c)^(k - j)
      for (size_t i = 0; i < k - j; ++i) pw *= -c;
      out[j] += coef * binom * pw;
      binom = binom * static_cast<long double>(k - j) / static_cast<long double>(j + 1);
    }
  }
  return std::vector<double>(out.begin(), out.end());
}

std::vector<double> real_roots_in(const std::vector<double>& c, double lo, double hi) {
  std::vector<double> roots;
  int deg = static_cast<int>(c.size()) - 1;
  while (deg > 0 && c[static_cast<size_t>(deg)] == 0) --deg;
  if (deg < 1) return roots;
  Eigen::MatrixXd comp = Eigen::MatrixXd::Zero(deg, deg);
  for (int i = 1; i < deg; ++i) comp(i, i - 1) = 1;
  for (int i = 0; i < deg; ++i) comp(i, deg - 1) = -c[static_cast<size_t>(i)] / c[static_cast<size_t>(deg)];
  const Eigen::VectorXcd ev = comp.eigenvalues();
  const double span = std::max(1.0, std::max(std::fabs(lo), std::fabs(hi)));
  for (Eigen::Index i = 0; i < ev.size(); ++i) {
    if (std::fabs(ev(i).imag()) > 1e-7 * span) continue;
    double x = ev(i).real();
    for (int it = 0; it < 4; ++it) {  // Newton polish
      double p = 0, dp = 0;
      for (int k = deg; k >= 0; --k) {
        dp = dp * x + p;
        p = p * x + c[static_cast<size_t>(k)];
      }
      if (dp == 0) break;
      x -= p / dp;
    }
    if (x >= lo && x <= hi) roots.push_back(x);
  }
  std::sort(roots.begin(), roots.end());
  return roots;
}

RationalFit fit_rational(const std::vector<double>& r, const std::vector<double>& y, double r_lo, double r_hi,
                         int n, int m, const std::vector<RationalFit>& starts, int max_iterations) {
  if (n < 0 || m < 0) throw Error(ExitCode::usage, "degrees must be non-negative");
  if (r.size() != y.size()) throw Error(ExitCode::software, "fit_rational: r and y differ in length");
  if (!(r_hi > r_lo)) throw Error(ExitCode::data, "the fit window is empty (rmax <= rmin)");
  RationalFit fit;
  fit.n = n;
  fit.m = m;
  fit.centre = 0.5 * (r_lo + r_hi);
  fit.half_width = 0.5 * (r_hi - r_lo);
  std::vector<double> x, ys;
  double yscale = 0;
  for (size_t i = 0; i < r.size(); ++i) {
    if (!std::isfinite(r[i]) || !std::isfinite(y[i])) throw Error(ExitCode::data, "a radius or value is not finite");
    if (r[i] < r_lo || r[i] > r_hi) continue;
    if (!x.empty() && !(fit.x_of(r[i]) > x.back()))
      throw Error(ExitCode::data, "radii must increase strictly (" + std::to_string(r[i]) + " follows a radius not below it)");
    x.push_back(fit.x_of(r[i]));
    ys.push_back(y[i]);
    yscale = std::max(yscale, std::fabs(y[i]));
  }
  const size_t N = x.size();
  const int p = fit.parameters();
  if (N < static_cast<size_t>(p))
    throw Error(ExitCode::data, std::to_string(N) + " points in the window for " + std::to_string(p) +
                                    " parameters (degrees " + std::to_string(n) + "/" + std::to_string(m) + ")");
  if (yscale == 0) yscale = 1;
  for (double& v : ys) v /= yscale;  // unit-size values: parameters of order one
  std::vector<double> guard(kGuardPoints);
  for (int i = 0; i < kGuardPoints; ++i) guard[static_cast<size_t>(i)] = -1 + 2.0 * i / (kGuardPoints - 1);

  // The homotopy over denominator degrees 0..m for this numerator; each level also starts from
  // the polynomial and from the linearized fit, and keeps its best feasible result.
  std::vector<Trial> finals;
  std::vector<double> prev = polynomial_start(x, ys, n, 0);
  for (int mm = 0; mm <= m; ++mm) {
    std::vector<Trial> trials;
    std::vector<double> from_prev(static_cast<size_t>(n + 1 + mm), 0.0);
    std::copy(prev.begin(), prev.end(), from_prev.begin());
    trials.push_back(solve(x, ys, n, mm, guard, polynomial_start(x, ys, n, mm), "polynomial", max_iterations));
    if (mm > 0) {
      trials.push_back(solve(x, ys, n, mm, guard, from_prev, "lower degree", max_iterations));
      const std::vector<double> lin = linearized_start(x, ys, n, mm, guard);
      if (!lin.empty()) trials.push_back(solve(x, ys, n, mm, guard, lin, "linearized", max_iterations));
    }
    if (mm == m)
      for (const RationalFit& s : starts)
        if (s.n <= n && s.m <= m && s.centre == fit.centre && s.half_width == fit.half_width && !s.a.empty())
          trials.push_back(solve(x, ys, n, mm, guard, padded(s, n, mm, yscale), "lower degree", max_iterations));
    std::sort(trials.begin(), trials.end(), [](const Trial& u, const Trial& v) { return u.cost < v.cost; });
    if (mm < m) {
      if (!trials.empty() && std::isfinite(trials.front().cost)) prev = trials.front().theta;
    } else {
      finals = trials;
    }
  }
  // The best converged trial whose denominator has no real root on the window (the guard grid
  // cannot see a pair of roots closer than its spacing; the companion matrix can).
  const Trial* win = nullptr;
  bool any_unconverged = false;
  for (const Trial& t : finals) {
    if (!std::isfinite(t.cost)) continue;
    if (!t.converged) {
      any_unconverged = true;
      continue;
    }
    std::vector<double> den(static_cast<size_t>(m + 1), 1.0);
    for (int k = 1; k <= m; ++k) den[static_cast<size_t>(k)] = t.theta[static_cast<size_t>(n + k)];
    if (!real_roots_in(den, -1, 1).empty()) continue;
    win = &t;
    break;
  }
  if (!win)
    throw Error(ExitCode::data, any_unconverged ? "the fit did not converge in " + std::to_string(max_iterations) +
                                                      " iterations (fewer degrees, or more --max-iterations)"
                                                : "no fit with a root-free denominator on the window");
  const std::vector<double>& th = win->theta;
  fit.a.assign(static_cast<size_t>(n + 1), 0.0);
  fit.b.assign(static_cast<size_t>(m + 1), 1.0);
  for (int k = 0; k <= n; ++k) fit.a[static_cast<size_t>(k)] = th[static_cast<size_t>(k)] * yscale;
  for (int k = 1; k <= m; ++k) fit.b[static_cast<size_t>(k)] = th[static_cast<size_t>(n + k)];
  fit.iterations = win->iterations;
  fit.start = win->start;
  fit.points = N;

  // Residuals, Jacobian and covariance at the solution (scaled problem, then back to data units).
  Eigen::MatrixXd J(N, p);
  fit.rss = 0;
  fit.max_abs = 0;
  for (size_t i = 0; i < N; ++i) {
    const auto ii = static_cast<Eigen::Index>(i);
    const double g = denominator(th.data(), n, m, x[i]);
    const double q = horner(th.data(), n, x[i]) / g;
    const double res = (q - ys[i]) * yscale;
    fit.rss += res * res;
    fit.max_abs = std::max(fit.max_abs, std::fabs(res));
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= x[i]) J(ii, k) = xk / g;
    xk = x[i];
    for (int k = 1; k <= m; ++k, xk *= x[i]) J(ii, n + k) = -q * xk / g;
  }
  fit.rms = std::sqrt(fit.rss / static_cast<double>(N));
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(J, Eigen::ComputeThinV);
  const Eigen::VectorXd sv = svd.singularValues();
  const double smax = sv(0), smin = sv(sv.size() - 1);
  fit.condition = smin > 0 ? smax / smin : std::numeric_limits<double>::infinity();
  const size_t dof = N - static_cast<size_t>(p);
  fit.sigma_y = dof > 0 ? std::sqrt(fit.rss / static_cast<double>(dof)) : 0;
  fit.sigma.assign(static_cast<size_t>(p), std::numeric_limits<double>::quiet_NaN());
  if (dof > 0 && smin > 1e-14 * smax) {
    const double s2 = fit.rss / static_cast<double>(dof) / (yscale * yscale);  // scaled residual variance
    const Eigen::VectorXd inv2 = sv.cwiseInverse().cwiseAbs2();
    Eigen::MatrixXd cov = svd.matrixV() * inv2.asDiagonal() * svd.matrixV().transpose() * s2;
    Eigen::VectorXd d = Eigen::VectorXd::Ones(p);
    d.head(n + 1).setConstant(yscale);
    fit.covariance = d.asDiagonal() * cov * d.asDiagonal();
    for (int k = 0; k < p; ++k) fit.sigma[static_cast<size_t>(k)] = std::sqrt(std::max(0.0, fit.covariance(k, k)));
  }
  fit.min_denominator = 1;
  for (int i = 0; i <= 2000; ++i) fit.min_denominator = std::min(fit.min_denominator, horner(fit.b.data(), m, -1 + i / 1000.0));
  // Information criteria for Gaussian residuals (AICc: Hurvich and Tsai 1989).
  const double Nd = static_cast<double>(N), pd = p;
  const double ll = Nd * std::log(std::max(fit.rss, 1e-300) / Nd);
  fit.aicc = ll + 2 * pd + (Nd - pd - 1 > 0 ? 2 * pd * (pd + 1) / (Nd - pd - 1) : std::numeric_limits<double>::infinity());
  fit.bic = ll + pd * std::log(Nd);
  return fit;
}

}  // namespace turnfit
