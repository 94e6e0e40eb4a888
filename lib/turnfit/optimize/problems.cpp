// Built-in multi-objective test problems and their known Pareto fronts.
#include "turnfit/optimize/problems.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <limits>

#include "turnfit/io/error.hpp"

namespace turnfit {

namespace {

constexpr double kPi = 3.14159265358979323846;

/// `n` evenly spaced values from a to b inclusive (a alone when n == 1).
std::vector<double> linspace(double a, double b, size_t n) {
  std::vector<double> v(n);
  for (size_t i = 0; i < n; ++i) v[i] = n == 1 ? a : a + (b - a) * double(i) / double(n - 1);
  return v;
}

/// At most `n` points of a front, evenly spaced in the order given (sorted by f1 by callers).
std::vector<std::vector<double>> thin(std::vector<std::vector<double>> pts, size_t n) {
  if (pts.size() <= n || n == 0) return pts;
  std::vector<std::vector<double>> out;
  out.reserve(n);
  for (size_t i = 0; i < n; ++i) out.push_back(pts[i * (pts.size() - 1) / std::max<size_t>(1, n - 1)]);
  return out;
}

/// The non-dominated points of `pts` sorted by the first objective, at most about n of them.
std::vector<std::vector<double>> front_of(std::vector<std::vector<double>> pts, size_t n) {
  auto nd = nondominated_points(pts);
  std::sort(nd.begin(), nd.end());
  return thin(std::move(nd), n);
}

/// The front of the feasible (violation <= tol) designs among `candidates`: about n points.
std::vector<std::vector<double>> feasible_front_of(const Problem& p, const std::vector<std::vector<double>>& candidates,
                                                   double tol, size_t n) {
  std::vector<std::vector<double>> pts;
  for (const auto& x : candidates) {
    Evaluation e = p.evaluate(x);
    if (constraint_violation(e.g) <= tol) pts.push_back(std::move(e.f));
  }
  return front_of(std::move(pts), n);
}

double sq(double v) { return v * v; }

/// Points on the unit simplex in `m` dimensions with `h` divisions (Das and Dennis 1998).
void simplex_lattice(size_t m, size_t h, std::vector<double>& cur, size_t left,
                     std::vector<std::vector<double>>& out) {
  if (cur.size() + 1 == m) {
    cur.push_back(double(left) / double(h));
    out.push_back(cur);
    cur.pop_back();
    return;
  }
  for (size_t k = 0; k <= left; ++k) {
    cur.push_back(double(k) / double(h));
    simplex_lattice(m, h, cur, left - k, out);
    cur.pop_back();
  }
}

/// About npoints directions on the positive part of the unit sphere in m dimensions.
std::vector<std::vector<double>> sphere_points(size_t m, size_t npoints) {
  // The lattice has C(h + m - 1, m - 1) points; take the first h that reaches npoints.
  size_t h = 1;
  for (;; ++h) {
    double count = 1;
    for (size_t i = 1; i < m; ++i) count = count * double(h + i) / double(i);
    if (count >= double(npoints) || h > 10000) break;
  }
  std::vector<std::vector<double>> w;
  std::vector<double> cur;
  simplex_lattice(m, h, cur, h, w);
  for (auto& p : w) {
    double r = 0;
    for (double v : p) r += v * v;
    r = std::sqrt(r);
    for (double& v : p) v /= r;
  }
  return w;
}

// ---- ZDT (Zitzler, Deb, Thiele 2000, "Comparison of multiobjective evolutionary algorithms") --

/// ZDT1-4 and ZDT6: f1 = f1(x1), f2 = g h(f1, g); all minimized.
class Zdt : public Problem {
 public:
  Zdt(int k, size_t n)
      : Problem("ZDT" + std::to_string(k), lower_bounds(k, n), upper_bounds(k, n), 2, 0), k_(k) {}

  Evaluation evaluate(const std::vector<double>& x) const override {
    const size_t n = x.size();
    Evaluation e;
    double f1 = x[0];
    double g = 0;
    if (k_ == 4) {
      // g = 1 + 10 (n - 1) + sum (x_i^2 - 10 cos(4 pi x_i)): 21^9 local fronts.
      for (size_t i = 1; i < n; ++i) g += x[i] * x[i] - 10 * std::cos(4 * kPi * x[i]);
      g += 1 + 10.0 * double(n - 1);
    } else if (k_ == 6) {
      f1 = 1 - std::exp(-4 * x[0]) * std::pow(std::sin(6 * kPi * x[0]), 6);
      for (size_t i = 1; i < n; ++i) g += x[i];
      g = 1 + 9 * std::pow(g / double(n - 1), 0.25);
    } else {
      for (size_t i = 1; i < n; ++i) g += x[i];
      g = 1 + 9 * g / double(n - 1);
    }
    const double r = f1 / g;
    double h = 0;
    switch (k_) {
      case 2: case 6: h = 1 - r * r; break;
      case 3: h = 1 - std::sqrt(r) - r * std::sin(10 * kPi * f1); break;
      default: h = 1 - std::sqrt(r); break;
    }
    e.f = {f1, g * h};
    return e;
  }

  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    // g = 1 on the front: f2 = h(f1, 1); ZDT6's f1 reaches down to 1 - exp(-4 x1) sin^6(6 pi
    // x1) minimized over x1, and ZDT3's curve is cut to its non-dominated pieces.
    std::vector<std::vector<double>> pts;
    const size_t dense = k_ == 3 || k_ == 6 ? std::max<size_t>(20000, 40 * npoints) : npoints;
    double lo = 0;
    if (k_ == 6) {
      lo = 1;
      for (double x1 : linspace(0, 1, 200001))
        lo = std::min(lo, 1 - std::exp(-4 * x1) * std::pow(std::sin(6 * kPi * x1), 6));
    }
    for (double f1 : linspace(lo, 1, dense)) {
      double f2 = 0;
      switch (k_) {
        case 2: case 6: f2 = 1 - f1 * f1; break;
        case 3: f2 = 1 - std::sqrt(f1) - f1 * std::sin(10 * kPi * f1); break;
        default: f2 = 1 - std::sqrt(f1); break;
      }
      pts.push_back({f1, f2});
    }
    return front_of(std::move(pts), npoints);
  }

 private:
  static std::vector<double> lower_bounds(int k, size_t n) {
    std::vector<double> lo(n, k == 4 ? -5.0 : 0.0);
    lo[0] = 0;
    return lo;
  }
  static std::vector<double> upper_bounds(int k, size_t n) {
    std::vector<double> hi(n, k == 4 ? 5.0 : 1.0);
    hi[0] = 1;
    return hi;
  }
  int k_;
};

// ---- DTLZ2 (Deb, Thiele, Laumanns, Zitzler 2002) and C2-DTLZ2 (Jain and Deb 2014) ----------

/// DTLZ2: a sphere front sum f_i^2 = 1 in the positive orthant; C2-DTLZ2 keeps only the
/// regions of radius r around the axis points and the centre of the front.
class Dtlz2 : public Problem {
 public:
  Dtlz2(size_t m, size_t n, bool c2)
      : Problem(c2 ? "C2-DTLZ2" : "DTLZ2", std::vector<double>(n, 0.0), std::vector<double>(n, 1.0),
                m, c2 ? 1 : 0),
        m_(m), c2_(c2), r_(m == 3 ? 0.4 : 0.5) {}

  Evaluation evaluate(const std::vector<double>& x) const override {
    Evaluation e;
    double g = 0;
    for (size_t i = m_ - 1; i < x.size(); ++i) g += (x[i] - 0.5) * (x[i] - 0.5);
    e.f.assign(m_, 1 + g);
    // f_j = (1 + g) prod_{i < m - 1 - j} cos(x_i pi/2) * sin(x_{m-1-j} pi/2) (j > 0).
    for (size_t j = 0; j < m_; ++j) {
      const size_t ncos = m_ - 1 - j;
      for (size_t i = 0; i < ncos; ++i) e.f[j] *= std::cos(x[i] * kPi / 2);
      if (j > 0) e.f[j] *= std::sin(x[ncos] * kPi / 2);
    }
    if (c2_) e.g = {c2_constraint(e.f)};
    return e;
  }

  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    auto pts = sphere_points(m_, c2_ ? 6 * npoints : npoints);
    if (c2_) {
      std::vector<std::vector<double>> keep;
      for (auto& p : pts)
        if (c2_constraint(p) <= 0) keep.push_back(p);
      pts = std::move(keep);
    }
    return pts;
  }

 private:
  /// min( min_i [(f_i - 1)^2 + sum_{j != i} f_j^2 - r^2], sum_i (f_i - 1/sqrt(m))^2 - r^2 ).
  double c2_constraint(const std::vector<double>& f) const {
    double sumsq = 0, centre = 0;
    const double c = 1 / std::sqrt(double(m_));
    for (double v : f) {
      sumsq += v * v;
      centre += (v - c) * (v - c);
    }
    double best = centre - r_ * r_;
    for (double v : f) best = std::min(best, sumsq - v * v + (v - 1) * (v - 1) - r_ * r_);
    return best;
  }
  size_t m_;
  bool c2_;
  double r_;
};

// ---- Constrained two-objective problems (Deb 2001, "Multi-objective optimization using
// evolutionary algorithms", and Deb et al. 2002 sec. VI) ----------------------------------

/// Binh and Korn (BNH): 2 variables, 2 constraints.
class Bnh : public Problem {
 public:
  Bnh() : Problem("BNH", {0, 0}, {5, 3}, 2, 2) {}
  Evaluation evaluate(const std::vector<double>& x) const override {
    Evaluation e;
    e.f = {4 * x[0] * x[0] + 4 * x[1] * x[1], sq(x[0] - 5) + sq(x[1] - 5)};
    e.g = {sq(x[0] - 5) + x[1] * x[1] - 25, 7.7 - sq(x[0] - 8) - sq(x[1] + 3)};
    return e;
  }
  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    // x1 = x2 in [0, 3], then x2 = 3 with x1 in [3, 5] (both constraints inactive).
    std::vector<std::vector<double>> pts;
    for (double t : linspace(0, 5, std::max<size_t>(npoints, 2))) {
      const double x1 = t, x2 = std::min(t, 3.0);
      pts.push_back(evaluate({x1, x2}).f);
    }
    return front_of(std::move(pts), npoints);
  }
};

/// Tanaka (TNK): f = x, the front on the wavy circle x1^2 + x2^2 = 1 + 0.1 cos(16 atan(x1/x2)).
class Tnk : public Problem {
 public:
  Tnk() : Problem("TNK", {0, 0}, {kPi, kPi}, 2, 2) {}
  Evaluation evaluate(const std::vector<double>& x) const override {
    Evaluation e;
    e.f = {x[0], x[1]};
    // atan2 equals atan(x1/x2) on the box and stays defined at x2 = 0.
    e.g = {1 + 0.1 * std::cos(16 * std::atan2(x[0], x[1])) - x[0] * x[0] - x[1] * x[1],
           (x[0] - 0.5) * (x[0] - 0.5) + (x[1] - 0.5) * (x[1] - 0.5) - 0.5};
    return e;
  }
  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    std::vector<std::vector<double>> pts;
    for (double phi : linspace(0, kPi / 2, std::max<size_t>(20000, 40 * npoints))) {
      const double r = std::sqrt(1 + 0.1 * std::cos(16 * phi));
      const std::vector<double> x{r * std::sin(phi), r * std::cos(phi)};
      if (evaluate(x).g[1] <= 0) pts.push_back(x);
    }
    return front_of(std::move(pts), npoints);
  }
};

/// Osyczka and Kundu (OSY): 6 variables, 6 constraints; the front is made of five pieces
/// (Deb 2001, sec. 8.3), each with some constraints active.
class Osy : public Problem {
 public:
  Osy() : Problem("OSY", {0, 0, 1, 0, 1, 0}, {10, 10, 5, 6, 5, 10}, 2, 6) {}
  Evaluation evaluate(const std::vector<double>& x) const override {
    Evaluation e;
    const double f1 = -(25 * sq(x[0] - 2) + sq(x[1] - 2) + sq(x[2] - 1) + sq(x[3] - 4) + sq(x[4] - 1));
    double f2 = 0;
    for (double v : x) f2 += v * v;
    e.f = {f1, f2};
    e.g = {2 - x[0] - x[1], x[0] + x[1] - 6, x[1] - x[0] - 2, x[0] - 3 * x[1] - 2,
           sq(x[2] - 3) + x[3] - 4, 4 - sq(x[4] - 3) - x[5]};
    return e;
  }
  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    std::vector<std::vector<double>> cand;
    const size_t n = std::max<size_t>(2000, 10 * npoints);
    for (double t : linspace(1, 5, n)) {
      cand.push_back({5, 1, t, 0, 5, 0});                // x5 = 5, x3 free
      cand.push_back({5, 1, t, 0, 1, 0});                // x5 = 1, x3 free
      cand.push_back({0, 2, t, 0, 1, 0});                // x1 = 0, x2 = 2, x3 free
    }
    for (double t : linspace(2, 5, n)) cand.push_back({t, (t - 2) / 3, 1, 0, 1, 0});
    for (double t : linspace(0, 1, n)) cand.push_back({t, 2 - t, 1, 0, 1, 0});
    return feasible_front_of(*this, cand, 1e-12, npoints);
  }
};

/// Srinivas and Deb (SRN). Deb (2001) gives the Pareto set as x1 = -2.5, x2 in [2.5, 14.79]
/// (where the objectives' gradients are opposite); the ends of the front, though, lie on the
/// constraints: on x1 = 3 x2 - 10 towards small f1 and on the circle towards small f2. The
/// front is the non-dominated part of all these curves.
class Srn : public Problem {
 public:
  Srn() : Problem("SRN", {-20, -20}, {20, 20}, 2, 2) {}
  Evaluation evaluate(const std::vector<double>& x) const override {
    Evaluation e;
    e.f = {2 + sq(x[0] - 2) + sq(x[1] - 1), 9 * x[0] - sq(x[1] - 1)};
    e.g = {x[0] * x[0] + x[1] * x[1] - 225, x[0] - 3 * x[1] + 10};
    return e;
  }
  std::vector<std::vector<double>> true_front(size_t npoints) const override {
    std::vector<std::vector<double>> cand;
    const size_t n = std::max<size_t>(5000, 20 * npoints);
    for (double x2 : linspace(-20, 20, n)) {
      cand.push_back({-2.5, x2});          // stationary curve
      cand.push_back({3 * x2 - 10, x2});   // on the linear constraint
    }
    for (double a : linspace(0, 2 * kPi, 4 * n)) cand.push_back({15 * std::cos(a), 15 * std::sin(a)});
    return feasible_front_of(*this, cand, 1e-9, npoints);
  }
};

std::string upper(std::string s) {
  for (char& c : s) c = char(std::toupper(static_cast<unsigned char>(c)));
  return s;
}

}  // namespace

double constraint_violation(const std::vector<double>& g) {
  double v = 0;
  for (double gj : g) v += gj > 0 ? gj : (std::isnan(gj) ? std::numeric_limits<double>::quiet_NaN() : 0.0);
  return v;
}

Problem::Problem(std::string name, std::vector<double> lower, std::vector<double> upper,
                 size_t n_objectives, size_t n_constraints, std::vector<std::string> variable_names)
    : name_(std::move(name)), lower_(std::move(lower)), upper_(std::move(upper)),
      n_objectives_(n_objectives), n_constraints_(n_constraints),
      variable_names_(std::move(variable_names)) {
  if (lower_.size() != upper_.size() || lower_.empty())
    throw usage_error("problem " + name_ + ": lower and upper bounds must have one value per variable");
  for (size_t i = 0; i < lower_.size(); ++i)
    if (!(lower_[i] <= upper_[i]))
      throw usage_error("problem " + name_ + ": variable " + std::to_string(i) + " has lower > upper bound");
  if (!variable_names_.empty() && variable_names_.size() != lower_.size())
    throw usage_error("problem " + name_ + ": one name per variable expected");
  if (n_objectives_ == 0) throw usage_error("problem " + name_ + ": no objectives");
}

std::vector<std::vector<double>> Problem::true_front(size_t) const { return {}; }

std::vector<std::string> builtin_problem_names() {
  return {"ZDT1", "ZDT2", "ZDT3", "ZDT4", "ZDT6", "DTLZ2", "BNH", "TNK", "OSY", "SRN", "C2-DTLZ2"};
}

std::unique_ptr<Problem> make_problem(const std::string& name, size_t n_variables, size_t n_objectives) {
  const std::string u = upper(name);
  auto fixed = [&](size_t n, size_t m) {
    if (n_variables != 0 && n_variables != n)
      throw usage_error("problem " + u + " has " + std::to_string(n) + " variables, not " +
                        std::to_string(n_variables));
    if (n_objectives != 0 && n_objectives != m)
      throw usage_error("problem " + u + " has " + std::to_string(m) + " objectives, not " +
                        std::to_string(n_objectives));
  };
  if (u.size() == 4 && u.compare(0, 3, "ZDT") == 0 && std::string("12346").find(u[3]) != std::string::npos) {
    const int k = u[3] - '0';
    const size_t n = n_variables ? n_variables : (k == 4 || k == 6 ? 10 : 30);
    if (n < 2) throw usage_error("problem " + u + " needs at least 2 variables");
    if (n_objectives != 0 && n_objectives != 2)
      throw usage_error("problem " + u + " has 2 objectives, not " + std::to_string(n_objectives));
    return std::make_unique<Zdt>(k, n);
  }
  if (u == "DTLZ2" || u == "C2-DTLZ2" || u == "C2DTLZ2") {
    const size_t m = n_objectives ? n_objectives : 3;
    const size_t n = n_variables ? n_variables : m + 9;
    if (m < 2 || n < m)
      throw usage_error("problem " + u + " needs at least 2 objectives and as many variables");
    return std::make_unique<Dtlz2>(m, n, u != "DTLZ2");
  }
  if (u == "BNH") { fixed(2, 2); return std::make_unique<Bnh>(); }
  if (u == "TNK") { fixed(2, 2); return std::make_unique<Tnk>(); }
  if (u == "OSY") { fixed(6, 2); return std::make_unique<Osy>(); }
  if (u == "SRN") { fixed(2, 2); return std::make_unique<Srn>(); }
  std::string known;
  for (auto& n : builtin_problem_names()) known += (known.empty() ? "" : ", ") + n;
  throw usage_error("unknown problem '" + name + "' (built in: " + known + ")");
}

std::vector<std::vector<double>> nondominated_points(const std::vector<std::vector<double>>& pts) {
  std::vector<std::vector<double>> out;
  const size_t n = pts.size();
  std::vector<size_t> order(n);
  for (size_t i = 0; i < n; ++i) order[i] = i;
  // Lexicographic order: a point can only be dominated by one before it.
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return pts[a] < pts[b]; });
  std::vector<size_t> kept;
  const bool two = n > 0 && pts[order[0]].size() == 2;
  double f2min = std::numeric_limits<double>::infinity();
  for (size_t oi = 0; oi < n; ++oi) {
    const auto& p = pts[order[oi]];
    bool dominated = false;
    if (two) {
      // Two objectives: weakly dominated iff an earlier point has f2 <= this f2.
      dominated = !(p[1] < f2min);
      if (!dominated) f2min = p[1];
    } else {
      for (size_t k : kept) {
        const auto& q = pts[k];
        bool all_le = true;
        for (size_t d = 0; d < p.size() && all_le; ++d) all_le = q[d] <= p[d];
        if (all_le) { dominated = true; break; }  // also drops exact duplicates
      }
    }
    if (!dominated) kept.push_back(order[oi]);
  }
  std::sort(kept.begin(), kept.end());
  for (size_t k : kept) out.push_back(pts[k]);
  return out;
}

namespace {
double nearest(const std::vector<double>& p, const std::vector<std::vector<double>>& set) {
  double best = std::numeric_limits<double>::infinity();
  for (const auto& q : set) {
    double d = 0;
    for (size_t i = 0; i < p.size(); ++i) d += (p[i] - q[i]) * (p[i] - q[i]);
    best = std::min(best, d);
  }
  return std::sqrt(best);
}
}  // namespace

double generational_distance(const std::vector<std::vector<double>>& points,
                             const std::vector<std::vector<double>>& front) {
  if (points.empty() || front.empty()) return std::numeric_limits<double>::quiet_NaN();
  double s = 0;
  for (const auto& p : points) s += nearest(p, front);
  return s / double(points.size());
}

double inverted_generational_distance(const std::vector<std::vector<double>>& points,
                                      const std::vector<std::vector<double>>& front) {
  return generational_distance(front, points);
}

}  // namespace turnfit
