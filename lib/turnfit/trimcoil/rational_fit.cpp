// Rational least-squares fits with Ceres (paper Sec. II.C, Eq. 2: delta sin(phi) ~ f(r)/g(r)).
#include "turnfit/trimcoil/rational_fit.hpp"

#include "turnfit/optimize/ceres_logging.hpp"

#include <ceres/ceres.h>

#include <algorithm>
#include <complex>
#include <random>
#include <cstdio>
#include <cmath>
#include <limits>
#include <mutex>

#include "turnfit/io/error.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

namespace turnfit {
namespace {

constexpr double kMinDenominator = 1e-9;  // g(0) = 1: a denominator this small is a pole
constexpr int kGuardPoints = 257;         // where g > 0 is checked besides the root test

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

/// Distance in the complex plane from the nearest root of g = 1 + b_1 x + ... to the window
/// [-1, 1] (infinity for m = 0). A root closer than the data spacing is a feature the data
/// cannot resolve: a pole-zero pair fitting noise, a spike of the derivative (the field).
double pole_distance(const double* theta, int n, int m) {
  int deg = m;
  while (deg > 0 && theta[n + deg] == 0) --deg;
  if (deg == 0) return std::numeric_limits<double>::infinity();
  Eigen::MatrixXd comp = Eigen::MatrixXd::Zero(deg, deg);
  for (int i = 1; i < deg; ++i) comp(i, i - 1) = 1;
  const double lead = theta[n + deg];
  comp(0, deg - 1) = -1 / lead;
  for (int i = 1; i < deg; ++i) comp(i, deg - 1) = -theta[n + i] / lead;
  const Eigen::VectorXcd ev = comp.eigenvalues();
  double best = std::numeric_limits<double>::infinity();
  for (Eigen::Index i = 0; i < ev.size(); ++i) {
    const double re = ev(i).real(), im = std::fabs(ev(i).imag());
    const double dre = re < -1 ? -1 - re : re > 1 ? re - 1 : 0.0;
    best = std::min(best, std::hypot(dre, im));
  }
  return best;
}

// Gauss-Legendre nodes and weights on [-1, 1] (8 points): the integral model's quadrature.
constexpr double kGLx[8] = {-0.9602898564975363, -0.7966664774136267, -0.5255324099163290, -0.1834346424956498,
                            0.1834346424956498,  0.5255324099163290,  0.7966664774136267,  0.9602898564975363};
constexpr double kGLw[8] = {0.1012285362903763, 0.2223810344533745, 0.3137066458778873, 0.3626837833783620,
                            0.3626837833783620, 0.3137066458778873, 0.2223810344533745, 0.1012285362903763};

/// The fitted curve at the data points, and its Jacobian, for both models. Parameters
/// (a_0..a_n, b_1..b_m[, c]).
struct Model {
  const std::vector<double>& x;
  int n, m;
  bool integral;               // y = c - integral of f/g
  const Eigen::MatrixXd* K;    // response: y = c + K (f/g)(xg)
  std::vector<double> xg;      // response grid (scaled)
  std::vector<double> xq, wq;  // integral: 8 nodes per segment [x_{i-1}, x_i] (x_{-1} = -1)

  Model(const std::vector<double>& xs, int n_, int m_, bool integ, const Eigen::MatrixXd* k = nullptr,
        std::vector<double> grid = {})
      : x(xs), n(n_), m(m_), integral(integ), K(k), xg(std::move(grid)) {
    if (!integral) return;
    double lo = -1;
    for (double xi : x) {
      const double mid = 0.5 * (lo + xi), half = 0.5 * (xi - lo);
      for (int q = 0; q < 8; ++q) {
        xq.push_back(mid + half * kGLx[q]);
        wq.push_back(half * kGLw[q]);
      }
      lo = xi;
    }
  }
  bool has_c() const { return integral || K; }
  int params() const { return n + 1 + m + (has_c() ? 1 : 0); }

  /// out[i] = y(x_i); jac (row-major N x p) if not null. False if g <= 0 at a point used.
  bool predict(const double* th, double* out, double* jac) const {
    const int p = params();
    if (K) {
      const size_t G = xg.size();
      Eigen::VectorXd R(static_cast<Eigen::Index>(G));
      Eigen::MatrixXd dR = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(G), p - 1);
      std::vector<double> rowbuf(static_cast<size_t>(p));
      for (size_t j = 0; j < G; ++j) {
        const double g = denominator(th, n, m, xg[j]);
        if (!(g > kMinDenominator)) return false;
        const double q = horner(th, n, xg[j]) / g;
        R(static_cast<Eigen::Index>(j)) = q;
        if (jac) {
          row(th, xg[j], g, q, rowbuf.data(), 1.0);
          for (int k = 0; k < p - 1; ++k) dR(static_cast<Eigen::Index>(j), k) = rowbuf[static_cast<size_t>(k)];
        }
      }
      const Eigen::VectorXd y = *K * R;
      const double c = th[p - 1];
      for (size_t i = 0; i < x.size(); ++i) out[i] = c + y(static_cast<Eigen::Index>(i));
      if (jac) {
        const Eigen::MatrixXd J = *K * dR;
        for (size_t i = 0; i < x.size(); ++i) {
          double* rw = jac + i * static_cast<size_t>(p);
          for (int k = 0; k < p - 1; ++k) rw[k] = J(static_cast<Eigen::Index>(i), k);
          rw[p - 1] = 1;
        }
      }
      return true;
    }
    if (!integral) {
      for (size_t i = 0; i < x.size(); ++i) {
        const double g = denominator(th, n, m, x[i]);
        if (!(g > kMinDenominator)) return false;
        const double q = horner(th, n, x[i]) / g;
        out[i] = q;
        if (jac) row(th, x[i], g, q, jac + i * static_cast<size_t>(p), 1.0);
      }
      return true;
    }
    double acc = 0;
    std::vector<double> gacc(static_cast<size_t>(p), 0.0);
    const double c = th[n + 1 + m];
    for (size_t i = 0; i < x.size(); ++i) {
      for (size_t k = 8 * i; k < 8 * i + 8; ++k) {
        const double g = denominator(th, n, m, xq[k]);
        if (!(g > kMinDenominator)) return false;
        const double q = horner(th, n, xq[k]) / g;
        acc += wq[k] * q;
        if (jac) row(th, xq[k], g, q, gacc.data(), wq[k], true);
      }
      out[i] = c - acc;
      if (jac) {
        double* rw = jac + i * static_cast<size_t>(p);
        for (int j = 0; j < p - 1; ++j) rw[j] = -gacc[static_cast<size_t>(j)];
        rw[p - 1] = 1;
      }
    }
    return true;
  }

  /// d(f/g)/d(theta) at x, times w, stored (or added) into r.
  void row(const double*, double xv, double g, double q, double* r, double w, bool add = false) const {
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= xv) r[k] = (add ? r[k] : 0) + w * xk / g;
    xk = xv;
    for (int k = 1; k <= m; ++k, xk *= xv) r[n + k] = (add ? r[n + k] : 0) - w * q * xk / g;
  }
};

/// Residuals y(x_i) - data_i, analytic Jacobian. A trial point whose denominator is not
/// positive on the whole guard grid fails to evaluate: Ceres then counts the step as infinitely
/// bad and shrinks its trust region, so the iterates never cross a pole into the window.
class RationalResiduals final : public ceres::CostFunction {
 public:
  RationalResiduals(const Model& model, const std::vector<double>& y, const std::vector<double>& guard,
                    double min_pole_distance)
      : model_(model), y_(y), guard_(guard), min_pole_(min_pole_distance) {
    set_num_residuals(static_cast<int>(y.size()));
    mutable_parameter_block_sizes()->push_back(model.params());
  }

  bool Evaluate(double const* const* params, double* res, double** jac) const override {
    const double* th = params[0];
    if (model_.m > 0) {
      if (!(pole_distance(th, model_.n, model_.m) > min_pole_)) return false;
      for (double xg : guard_)
        if (!(denominator(th, model_.n, model_.m, xg) > kMinDenominator)) return false;
    }
    if (!model_.predict(th, res, jac && jac[0] ? jac[0] : nullptr)) return false;
    for (size_t i = 0; i < y_.size(); ++i) res[i] -= y_[i];
    return true;
  }

 private:
  const Model& model_;
  const std::vector<double>& y_;
  const std::vector<double>& guard_;
  double min_pole_;
};

struct Trial {
  std::vector<double> theta;
  double cost = std::numeric_limits<double>::infinity();
  int iterations = 0;
  bool converged = false;
  std::string start;
};

bool feasible(const std::vector<double>& theta, int n, int m, const std::vector<double>& guard, double min_pole) {
  if (m == 0) return true;
  if (!(pole_distance(theta.data(), n, m) > min_pole)) return false;
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

/// The polynomial fit (g = 1): the model is then linear in a (and c), so its Jacobian at
/// b = 0 is the design matrix.
std::vector<double> polynomial_start(const Model& md, const std::vector<double>& y) {
  const size_t N = y.size();
  const int p = md.params();
  std::vector<double> th(static_cast<size_t>(p), 0.0), pred(N), jac(N * static_cast<size_t>(p));
  md.predict(th.data(), pred.data(), jac.data());
  std::vector<int> cols;
  for (int k = 0; k <= md.n; ++k) cols.push_back(k);
  if (md.has_c()) cols.push_back(p - 1);
  Eigen::MatrixXd A(N, cols.size());
  Eigen::VectorXd rhs(N);
  for (size_t i = 0; i < N; ++i) {
    for (size_t j = 0; j < cols.size(); ++j)
      A(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) = jac[i * static_cast<size_t>(p) + static_cast<size_t>(cols[j])];
    rhs(static_cast<Eigen::Index>(i)) = y[i];
  }
  const Eigen::VectorXd t = weighted_lsq(A, rhs, Eigen::VectorXd::Ones(static_cast<Eigen::Index>(N)));
  for (size_t j = 0; j < cols.size(); ++j) th[static_cast<size_t>(cols[j])] = t(static_cast<Eigen::Index>(j));
  return th;
}

/// The linearized problem f(x_i) - v_i g(x_i) = 0 (Levy) for samples v_i of the rational itself,
/// reweighted by 1/g of the previous iterate so that it approaches least squares
/// (Sanathanan-Koerner). For the integral model the samples are the data's negative
/// difference quotients at interval midpoints, and c follows from the mean residual. Returns the
/// iterate with the smallest true residual among those with a root-free denominator (empty if
/// none was).
std::vector<double> linearized_start(const Model& md, const std::vector<double>& y, const std::vector<double>& guard,
                                     double min_pole) {
  if (md.K) return {};  // no direct samples of f/g
  const int n = md.n, m = md.m, p = md.params();
  std::vector<double> xs, vs;
  if (!md.integral) {
    xs = md.x;
    vs = y;
  } else {
    for (size_t i = 0; i + 1 < y.size(); ++i) {
      xs.push_back(0.5 * (md.x[i] + md.x[i + 1]));
      vs.push_back(-(y[i + 1] - y[i]) / (md.x[i + 1] - md.x[i]));
    }
  }
  const size_t N = xs.size();
  if (N < static_cast<size_t>(n + 1 + m)) return {};
  Eigen::MatrixXd A(N, n + 1 + m);
  Eigen::VectorXd rhs(N), w = Eigen::VectorXd::Ones(static_cast<Eigen::Index>(N));
  for (size_t i = 0; i < N; ++i) {
    const auto ii = static_cast<Eigen::Index>(i);
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= xs[i]) A(ii, k) = xk;
    xk = xs[i];
    for (int k = 1; k <= m; ++k, xk *= xs[i]) A(ii, n + k) = -vs[i] * xk;
    rhs(ii) = vs[i];
  }
  std::vector<double> best;
  double best_cost = std::numeric_limits<double>::infinity();
  std::vector<double> pred(y.size());
  for (int it = 0; it < 8; ++it) {
    const Eigen::VectorXd t = weighted_lsq(A, rhs, w);
    if (!t.allFinite()) break;
    std::vector<double> theta(static_cast<size_t>(p), 0.0);
    std::copy(t.data(), t.data() + n + 1 + m, theta.begin());
    if (!feasible(theta, n, m, guard, min_pole)) break;  // the reweighting needs a root-free g
    for (size_t i = 0; i < N; ++i) w(static_cast<Eigen::Index>(i)) = 1 / denominator(theta.data(), n, m, xs[i]);
    if (!md.predict(theta.data(), pred.data(), nullptr)) break;
    if (md.integral) {  // the constant: the mean offset
      double off = 0;
      for (size_t i = 0; i < y.size(); ++i) off += y[i] - pred[i];
      theta[static_cast<size_t>(p - 1)] = off / static_cast<double>(y.size());
      md.predict(theta.data(), pred.data(), nullptr);
    }
    double cost = 0;
    for (size_t i = 0; i < y.size(); ++i) cost += (pred[i] - y[i]) * (pred[i] - y[i]);
    if (cost < best_cost) {
      best_cost = cost;
      best = theta;
    }
  }
  return best;
}

Trial solve(const Model& md, const std::vector<double>& y, const std::vector<double>& guard, double min_pole,
            std::vector<double> theta, const std::string& start, int max_iterations) {
  quiet_ceres_logging();
  Trial t;
  t.start = start;
  if (!feasible(theta, md.n, md.m, guard, min_pole)) return t;
  ceres::Problem problem;
  problem.AddResidualBlock(new RationalResiduals(md, y, guard, min_pole), nullptr, theta.data());
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

/// A parameter vector of degrees (n, m) from one of lower degrees (new coefficients zero).
std::vector<double> widen(const std::vector<double>& th, int n0, int m0, int n, int m, bool with_c) {
  std::vector<double> out(static_cast<size_t>(n + 1 + m + (with_c ? 1 : 0)), 0.0);
  for (int k = 0; k <= n0; ++k) out[static_cast<size_t>(k)] = th[static_cast<size_t>(k)];
  for (int k = 1; k <= m0; ++k) out[static_cast<size_t>(n + k)] = th[static_cast<size_t>(n0 + k)];
  if (with_c) out.back() = th.back();
  return out;
}

std::vector<double> padded(const RationalFit& f, int n, int m, double scale, double cscale) {
  const bool integ = f.model != RationalModel::value;
  std::vector<double> th(static_cast<size_t>(n + 1 + m + (integ ? 1 : 0)), 0.0);
  for (int k = 0; k <= f.n; ++k) th[static_cast<size_t>(k)] = f.a[static_cast<size_t>(k)] / scale;
  for (int k = 1; k <= f.m; ++k) th[static_cast<size_t>(n + k)] = f.b[static_cast<size_t>(k)];
  if (integ) th.back() = f.offset / cscale;
  return th;
}


}  // namespace

void RationalFit::eval(double r, double& q, double& dq, double& d2q) const {
  rational(a, b, x_of(r), q, dq, d2q);
  dq /= half_width;
  d2q /= half_width * half_width;
}

namespace {
/// The integral model's integral_{-1}^{x} f/g dx' and its parameter gradient (without c):
/// composite 8-point Gauss-Legendre on 16 panels (f/g is smooth and root-free on the window).
double integral_of(const RationalFit& f, double x, Eigen::VectorXd* grad) {
  const int p = f.n + 1 + f.m;
  if (grad) *grad = Eigen::VectorXd::Zero(p + 1);
  double acc = 0;
  const int panels = 16;
  const double h = (x + 1) / panels;
  for (int k = 0; k < panels; ++k) {
    const double mid = -1 + (k + 0.5) * h;
    for (int q = 0; q < 8; ++q) {
      const double xq = mid + 0.5 * h * kGLx[q], w = 0.5 * h * kGLw[q];
      const double g = horner(f.b.data(), f.m, xq), v = horner(f.a.data(), f.n, xq) / g;
      acc += w * v;
      if (grad) {
        double xk = 1;
        for (int j = 0; j <= f.n; ++j, xk *= xq) (*grad)(j) += w * xk / g;
        xk = xq;
        for (int j = 1; j <= f.m; ++j, xk *= xq) (*grad)(f.n + j) -= w * v * xk / g;
      }
    }
  }
  return acc;
}
}  // namespace

double RationalFit::value(double r) const {
  if (model == RationalModel::integral) return offset - integral_of(*this, x_of(r), nullptr);
  if (model == RationalModel::response) {
    for (size_t i = 0; i + 1 < fitted_r.size(); ++i)
      if (r >= fitted_r[i] && r <= fitted_r[i + 1])
        return fitted_y[i] + (r - fitted_r[i]) / (fitted_r[i + 1] - fitted_r[i]) * (fitted_y[i + 1] - fitted_y[i]);
    return fitted_r.size() == 1 && r == fitted_r[0] ? fitted_y[0] : std::numeric_limits<double>::quiet_NaN();
  }
  double q, dq, d2q;
  eval(r, q, dq, d2q);
  return q;
}

void RationalFit::slope(double r, double& dy, double& d2y) const {
  double q, dq, d2q;
  eval(r, q, dq, d2q);
  if (model != RationalModel::value) {  // y' = -(f/g) / h (response: the field alike)
    dy = -q / half_width;
    d2y = -dq / half_width;
  } else {
    dy = dq;
    d2y = d2q;
  }
}

double RationalFit::value_sigma(double r) const {
  if (covariance.size() == 0 || model == RationalModel::response) return 0;
  const double x = x_of(r);
  Eigen::VectorXd grad(parameters());
  if (model == RationalModel::integral) {
    Eigen::VectorXd gi;
    integral_of(*this, x, &gi);
    grad = -gi;
    grad(parameters() - 1) = 1;
  } else {
    const double f = horner(a.data(), n, x), g = horner(b.data(), m, x), q = f / g;
    double xk = 1;
    for (int k = 0; k <= n; ++k, xk *= x) grad(k) = xk / g;
    xk = x;
    for (int k = 1; k <= m; ++k, xk *= x) grad(n + k) = -q * xk / g;
  }
  const double v = grad.dot(covariance * grad);
  return v > 0 ? std::sqrt(v) : 0;
}

Eigen::VectorXd RationalFit::slope_gradient(double r) const {
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
  Eigen::VectorXd grad = Eigen::VectorXd::Zero(parameters());
  if (model != RationalModel::value) {
    // y' = -(f/g) / h: d/da_k = -x^k / (g h), d/db_k = (f/g) x^k / (g h).
    const double q = f / g;
    for (int k = 0; k <= n; ++k) grad(k) = -std::pow(x, k) / g;
    for (int k = 1; k <= m; ++k) grad(n + k) = q * std::pow(x, k) / g;
    return grad / half_width;
  }
  // y' = D / h with D = (f' g - f g') / g^2; d/da_k and d/db_k by the quotient rule.
  const double D = (df * g - f * dg) / (g * g);
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
  // p(x) with x = (r - c)/h = q(r - c), q_k = c_k h^-k; q(r - c) in powers of r is q shifted by -c.
  std::vector<long double> q(c_x.begin(), c_x.end());
  long double hk = 1;
  for (long double& v : q) {
    v *= hk;
    hk /= static_cast<long double>(half_width);
  }
  const std::vector<long double> out = taylor_shift(std::move(q), -static_cast<long double>(centre));
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
                         int n, int m, const std::vector<RationalFit>& starts, int max_iterations, RationalModel model,
                         const LinearResponse* response, int extra_starts) {
  if (n < 0 || m < 0) throw Error(ExitCode::usage, "degrees must be non-negative");
  if (r.size() != y.size()) throw Error(ExitCode::software, "fit_rational: r and y differ in length");
  if (!(r_hi > r_lo)) throw Error(ExitCode::data, "the fit window is empty (rmax <= rmin)");
  const bool integral = model == RationalModel::integral;
  const bool with_c = model != RationalModel::value;
  if (model == RationalModel::response &&
      (!response || response->K.rows() != static_cast<Eigen::Index>(r.size()) ||
       response->K.cols() != static_cast<Eigen::Index>(response->r_grid.size())))
    throw Error(ExitCode::software, "fit_rational: the response matrix does not match the data and its grid");
  RationalFit fit;
  fit.model = model;
  fit.n = n;
  fit.m = m;
  fit.centre = 0.5 * (r_lo + r_hi);
  fit.half_width = 0.5 * (r_hi - r_lo);
  std::vector<double> x, ys;
  std::vector<Eigen::Index> rows;
  double yscale = 0;
  for (size_t i = 0; i < r.size(); ++i) {
    if (!std::isfinite(r[i]) || !std::isfinite(y[i])) throw Error(ExitCode::data, "a radius or value is not finite");
    if (r[i] < r_lo || r[i] > r_hi) continue;
    rows.push_back(static_cast<Eigen::Index>(i));
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
  // The response model: the rows of the points in the window, scaled like the values; its
  // grid in x. f/g is then a field in units of yscale / (unit of K).
  Eigen::MatrixXd Kw;
  std::vector<double> xg;
  if (model == RationalModel::response) {
    Kw.resize(static_cast<Eigen::Index>(rows.size()), response->K.cols());
    for (size_t i = 0; i < rows.size(); ++i) Kw.row(static_cast<Eigen::Index>(i)) = response->K.row(rows[i]) / yscale;
    for (double rg : response->r_grid) xg.push_back(fit.x_of(rg));
    if (!Kw.allFinite()) throw Error(ExitCode::data, "the response is not finite at every point (a run missed a radius)");
  }
  const Eigen::MatrixXd* Kp = model == RationalModel::response ? &Kw : nullptr;
  std::vector<double> guard(kGuardPoints);
  for (int i = 0; i < kGuardPoints; ++i) guard[static_cast<size_t>(i)] = -1 + 2.0 * i / (kGuardPoints - 1);
  // Poles of f/g must stay one data spacing (median, in x) away from the window: a bump whose
  // poles sit at distance w has a half width w, and a bump narrower than two samples across is
  // not resolved by them (it fits noise; ring8's coils have w = 36-75 mm against 25 mm samples).
  std::vector<double> gaps;
  for (size_t i = 1; i < N; ++i) gaps.push_back(x[i] - x[i - 1]);
  double min_pole = 0;
  if (!gaps.empty()) {
    std::nth_element(gaps.begin(), gaps.begin() + static_cast<long>(gaps.size() / 2), gaps.end());
    min_pole = gaps[gaps.size() / 2];
  }

  // The homotopy over denominator degrees 0..m for this numerator; each level also starts from
  // the polynomial and from the linearized fit, and keeps its best feasible result.
  std::vector<Trial> finals;
  std::vector<double> prev;
  for (int mm = 0; mm <= m; ++mm) {
    const Model md(x, n, mm, integral, Kp, xg);
    std::vector<Trial> trials;
    trials.push_back(solve(md, ys, guard, min_pole, polynomial_start(md, ys), "polynomial", max_iterations));
    if (mm > 0) {
      if (!prev.empty()) trials.push_back(solve(md, ys, guard, min_pole, widen(prev, n, mm - 1, n, mm, with_c), "lower degree", max_iterations));
      const std::vector<double> lin = linearized_start(md, ys, guard, min_pole);
      if (!lin.empty()) trials.push_back(solve(md, ys, guard, min_pole, lin, "linearized", max_iterations));
    }
    if (mm == m)
      for (const RationalFit& s : starts)
        if (s.n <= n && s.m <= m && s.model == model && s.centre == fit.centre && s.half_width == fit.half_width &&
            !s.a.empty())
          trials.push_back(solve(md, ys, guard, min_pole, padded(s, n, mm, model == RationalModel::response ? 1.0 : yscale, yscale),
                                 "lower degree", max_iterations));
    std::sort(trials.begin(), trials.end(), [](const Trial& u, const Trial& v) { return u.cost < v.cost; });
    if (mm < m) {
      if (!trials.empty() && std::isfinite(trials.front().cost)) prev = trials.front().theta;
    } else {
      finals = trials;
    }
  }
  // The best converged trial whose denominator has no real root on the window (the guard grid
  // cannot see a pair of roots closer than its spacing; the companion matrix can) and is not
  // held at the pole bound: a fit held there has a feature the samples cannot resolve.
  const Model md_final(x, n, m, integral, Kp, xg);
  bool any_unconverged = false;
  auto root_free = [&](const Trial& t) {
    std::vector<double> den(static_cast<size_t>(m + 1), 1.0);
    for (int k = 1; k <= m; ++k) den[static_cast<size_t>(k)] = t.theta[static_cast<size_t>(n + k)];
    return real_roots_in(den, -1, 1).empty();
  };
  auto at_bound = [&](const Trial& t) { return m > 0 && pole_distance(t.theta.data(), n, m) < 1.02 * min_pole; };
  double bound_cost = std::numeric_limits<double>::infinity();
  auto pick = [&](const std::vector<Trial>& ts) -> const Trial* {
    const Trial* best = nullptr;
    for (const Trial& t : ts) {
      if (!std::isfinite(t.cost)) continue;
      if (!t.converged) {
        any_unconverged = true;
        continue;
      }
      if (!root_free(t)) continue;
      if (at_bound(t)) {
        bound_cost = std::min(bound_cost, t.cost);
        continue;
      }
      if (!best || t.cost < best->cost) best = &t;
    }
    return best;
  };
  const Trial* win = pick(finals);
  std::vector<Trial> extra;
  if (!win && m > 0) {
    // Every start ended at the bound (or failed): the least-squares surface may still hold a
    // resolvable local optimum in another basin. Deterministic extra starts: denominators with
    // roots placed away from the window (conjugate pairs, and one real root beyond an end for
    // odd m), each with the numerator (and constant) the data give linearly for it.
    std::mt19937_64 rng(20261123);
    auto uni = [&](double lo, double hi) { return lo + (hi - lo) * static_cast<double>(rng() >> 11) * 0x1.0p-53; };
    for (int k = 0; k < extra_starts; ++k) {
      std::vector<std::complex<double>> roots;
      for (int j = 0; j + 1 < m; j += 2) {
        const std::complex<double> z(uni(-1.5, 1.5), uni(2 * min_pole, 1.0));
        roots.push_back(z);
        roots.push_back(std::conj(z));
      }
      if (m % 2) roots.push_back(uni(0, 1) < 0.5 ? -1 - 2 * min_pole - uni(0, 1) : 1 + 2 * min_pole + uni(0, 1));
      std::vector<std::complex<double>> g{1.0};
      for (const auto& z : roots) {  // g *= (x - z)
        std::vector<std::complex<double>> h(g.size() + 1, 0.0);
        for (size_t i = 0; i < g.size(); ++i) {
          h[i + 1] += g[i];
          h[i] -= z * g[i];
        }
        g = h;
      }
      std::vector<double> theta(static_cast<size_t>(md_final.params()), 0.0);
      for (int j = 1; j <= m; ++j) theta[static_cast<size_t>(n + j)] = g[static_cast<size_t>(j)].real() / g[0].real();
      // The linear part for this denominator: the model is linear in a (and c).
      std::vector<double> pred(N), jac(N * static_cast<size_t>(p));
      if (!md_final.predict(theta.data(), pred.data(), jac.data())) continue;
      std::vector<int> cols;
      for (int j = 0; j <= n; ++j) cols.push_back(j);
      if (with_c) cols.push_back(p - 1);
      Eigen::MatrixXd A(N, static_cast<Eigen::Index>(cols.size()));
      Eigen::VectorXd rhs(N);
      for (size_t i = 0; i < N; ++i) {
        for (size_t j = 0; j < cols.size(); ++j)
          A(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) = jac[i * static_cast<size_t>(p) + static_cast<size_t>(cols[j])];
        rhs(static_cast<Eigen::Index>(i)) = ys[i];
      }
      const Eigen::VectorXd t = A.colPivHouseholderQr().solve(rhs);
      for (size_t j = 0; j < cols.size(); ++j) theta[static_cast<size_t>(cols[j])] = t(static_cast<Eigen::Index>(j));
      extra.push_back(solve(md_final, ys, guard, min_pole, theta, "placed roots", max_iterations));
    }
    win = pick(extra);
  }
  if (!win) {
    if (std::isfinite(bound_cost))
      throw Error(ExitCode::data, "degrees " + std::to_string(n) + "/" + std::to_string(m) +
                                      ": the least-squares optimum wants a pole within one data spacing of the "
                                      "window (every start ended there): a feature the samples cannot resolve, a "
                                      "spike in the field; use fewer degrees or --degrees auto");
    throw Error(ExitCode::data, any_unconverged ? "the fit did not converge in " + std::to_string(max_iterations) +
                                                      " iterations (fewer degrees, or more --max-iterations)"
                                                : "no fit with a root-free denominator on the window");
  }
  if (bound_cost < win->cost) fit.rss_at_pole_bound = 2 * bound_cost * yscale * yscale;  // Ceres: cost = rss / 2
  const std::vector<double>& th = win->theta;
  fit.a.assign(static_cast<size_t>(n + 1), 0.0);
  fit.b.assign(static_cast<size_t>(m + 1), 1.0);
  // f/g carries the data's scale, except in the response model, whose K was scaled instead.
  const double ascale = model == RationalModel::response ? 1.0 : yscale;
  for (int k = 0; k <= n; ++k) fit.a[static_cast<size_t>(k)] = th[static_cast<size_t>(k)] * ascale;
  for (int k = 1; k <= m; ++k) fit.b[static_cast<size_t>(k)] = th[static_cast<size_t>(n + k)];
  if (with_c) fit.offset = th.back() * yscale;
  fit.iterations = win->iterations;
  fit.start = win->start;
  fit.points = N;

  // Residuals, Jacobian and covariance at the solution (scaled problem, then back to data units).
  const Model md(x, n, m, integral, Kp, xg);
  std::vector<double> pred(N), jac(N * static_cast<size_t>(p));
  md.predict(th.data(), pred.data(), jac.data());
  Eigen::MatrixXd J(N, p);
  fit.rss = 0;
  fit.max_abs = 0;
  for (size_t i = 0; i < N; ++i) {
    const double res = (pred[i] - ys[i]) * yscale;
    fit.rss += res * res;
    fit.max_abs = std::max(fit.max_abs, std::fabs(res));
    for (int k = 0; k < p; ++k) J(static_cast<Eigen::Index>(i), k) = jac[i * static_cast<size_t>(p) + static_cast<size_t>(k)];
  }
  fit.rms = std::sqrt(fit.rss / static_cast<double>(N));
  for (size_t i = 0; i < N; ++i) {
    fit.fitted_r.push_back(fit.centre + x[i] * fit.half_width);
    fit.fitted_y.push_back(pred[i] * yscale);
  }
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
    d.head(n + 1).setConstant(ascale);
    if (with_c) d(p - 1) = yscale;
    fit.covariance = d.asDiagonal() * cov * d.asDiagonal();
    for (int k = 0; k < p; ++k) fit.sigma[static_cast<size_t>(k)] = std::sqrt(std::max(0.0, fit.covariance(k, k)));
  }
  fit.min_denominator = 1;
  for (int i = 0; i <= 2000; ++i) fit.min_denominator = std::min(fit.min_denominator, horner(fit.b.data(), m, -1 + i / 1000.0));
  fit.pole_distance = m > 0 ? (pole_distance)(th.data(), n, m) : std::numeric_limits<double>::infinity();
  // Information criteria for Gaussian residuals (AICc: Hurvich and Tsai 1989).
  const double Nd = static_cast<double>(N), pd = p;
  const double ll = Nd * std::log(std::max(fit.rss, 1e-300) / Nd);
  fit.aicc = ll + 2 * pd + (Nd - pd - 1 > 0 ? 2 * pd * (pd + 1) / (Nd - pd - 1) : std::numeric_limits<double>::infinity());
  fit.bic = ll + pd * std::log(Nd);
  return fit;
}

}  // namespace turnfit
