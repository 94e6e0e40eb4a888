// Rational least squares (tc-fit's engine): exact recovery, honest uncertainties, root-free
// denominators, bad input.
#include <catch2/catch.hpp>
#include <cmath>
#include <random>

#include "../support.hpp"
#include "turnfit/trimcoil/rational_fit.hpp"

using namespace turnfit;

namespace {

/// f/g in the scaled variable x (b_0 = 1).
double rat(const std::vector<double>& a, const std::vector<double>& b, double x) {
  double f = 0, g = 0;
  for (size_t k = a.size(); k-- > 0;) f = f * x + a[k];
  for (size_t k = b.size(); k-- > 0;) g = g * x + b[k];
  return f / g;
}

struct Samples {
  std::vector<double> r, y;
};

Samples samples_of(const std::vector<double>& a, const std::vector<double>& b, double lo, double hi, int n) {
  Samples s;
  const double c = 0.5 * (lo + hi), h = 0.5 * (hi - lo);
  for (int i = 0; i < n; ++i) {
    const double r = lo + (hi - lo) * i / (n - 1);
    s.r.push_back(r);
    s.y.push_back(rat(a, b, (r - c) / h));
  }
  return s;
}

}  // namespace

TEST_CASE("rational fit recovers a known 2/4 function from noiseless samples", "[tcfit]") {
  // A step-like phase shift (the shape a trim coil leaves in delta sin(phi)), g > 0 on [-1, 1].
  const std::vector<double> a = {-0.02, -0.03, 0.01}, b = {1, 0.35, 0.5, -0.2, 0.3};
  const Samples s = samples_of(a, b, 2150, 2700, 40);
  const RationalFit f = fit_rational(s.r, s.y, 2150, 2700, 2, 4);
  REQUIRE(f.a.size() == 3);
  REQUIRE(f.b.size() == 5);
  for (size_t k = 0; k < a.size(); ++k) CHECK(f.a[k] == Approx(a[k]).epsilon(0).margin(1e-10));
  for (size_t k = 1; k < b.size(); ++k) CHECK(f.b[k] == Approx(b[k]).epsilon(0).margin(1e-8));
  CHECK(f.rms < 1e-13);
  CHECK(f.min_denominator > 0);
  // Between the samples and in r units as well.
  CHECK(f.value(2333.3) == Approx(rat(a, b, (2333.3 - 2425) / 275)).epsilon(0).margin(1e-12));
}

TEST_CASE("rational fit recovers a 4/5 function (the paper's outer coils)", "[tcfit]") {
  const std::vector<double> a = {0.01, -0.04, 0.02, 0.015, -0.01}, b = {1, -0.3, 0.6, 0.2, -0.1, 0.15};
  const Samples s = samples_of(a, b, 4060, 4540, 50);
  const RationalFit f = fit_rational(s.r, s.y, 4060, 4540, 4, 5);
  for (size_t k = 0; k < a.size(); ++k) CHECK(f.a[k] == Approx(a[k]).epsilon(0).margin(1e-9));
  for (size_t k = 1; k < b.size(); ++k) CHECK(f.b[k] == Approx(b[k]).epsilon(0).margin(1e-7));
  CHECK(f.rms < 1e-12);
}

TEST_CASE("coefficients in r reproduce the scaled fit", "[tcfit]") {
  const std::vector<double> cx = {0.3, -1.2, 0.7, 0.25, -0.4};
  const double c = 4.3, h = 0.24;  // metres, as a machine file's coefficients
  const std::vector<double> cr = polynomial_in_r(cx, c, h);
  for (double r : {4.06, 4.2, 4.3, 4.45, 4.54}) {
    double px = 0, pr = 0;
    for (size_t k = cx.size(); k-- > 0;) px = px * ((r - c) / h) + cx[k];
    for (size_t k = cr.size(); k-- > 0;) pr = pr * r + cr[k];
    CHECK(pr == Approx(px).epsilon(0).margin(1e-9));
  }
}

TEST_CASE("real roots on an interval", "[tcfit]") {
  // (x - 0.5)(x + 0.25)(x^2 + 1) = x^4 - 0.25 x^3 + 0.875 x^2 - 0.25 x - 0.125
  const std::vector<double> c = {-0.125, -0.25, 0.875, -0.25, 1};
  const auto roots = real_roots_in(c, -1, 1);
  REQUIRE(roots.size() == 2);
  CHECK(roots[0] == Approx(-0.25).epsilon(0).margin(1e-12));
  CHECK(roots[1] == Approx(0.5).epsilon(0).margin(1e-12));
  CHECK(real_roots_in(c, 0.6, 2).empty());
}

TEST_CASE("noisy samples: coefficients within their reported uncertainties", "[tcfit]") {
  // 100 seeds; with Gaussian noise of known sigma the reported 1-sigma intervals should hold
  // the truth about 68 % of the time and 2-sigma about 95 % (linearized: a little less).
  const std::vector<double> a = {-0.02, -0.03, 0.01}, b = {1, 0.35, 0.5, -0.2, 0.3};
  const Samples clean = samples_of(a, b, 2150, 2700, 60);
  const double noise = 2e-4;
  std::vector<double> truth = a;
  truth.insert(truth.end(), b.begin() + 1, b.end());
  int in1 = 0, in2 = 0, total = 0;
  double sigma_y_sum = 0;
  for (unsigned seed = 1; seed <= 100; ++seed) {
    std::mt19937_64 rng(seed);
    std::normal_distribution<double> nd(0, noise);
    Samples s = clean;
    for (double& v : s.y) v += nd(rng);
    const RationalFit f = fit_rational(s.r, s.y, 2150, 2700, 2, 4);
    REQUIRE(f.sigma.size() == truth.size());
    sigma_y_sum += f.sigma_y;
    for (size_t k = 0; k < truth.size(); ++k) {
      const double est = k < f.a.size() ? f.a[k] : f.b[k - f.a.size() + 1];
      const double d = std::fabs(est - truth[k]);
      in1 += d <= f.sigma[k];
      in2 += d <= 2 * f.sigma[k];
      ++total;
    }
  }
  const double f1 = static_cast<double>(in1) / total, f2 = static_cast<double>(in2) / total;
  INFO("within 1 sigma " << f1 << ", within 2 sigma " << f2);
  CHECK(f1 > 0.58);
  CHECK(f1 < 0.78);
  CHECK(f2 > 0.90);
  // The residual scale sqrt(rss / (N - p)) estimates the noise: N = 60 samples, p = 7
  // coefficients, nu = 53 degrees of freedom. Its mean is c4(nu) noise, c4 = 1 - 1/(4 nu)
  // (+ O(nu^-2)); each estimate scatters by 1/sqrt(2 nu) = 9.7 %, the mean of 100 by 0.97 %.
  // Tolerance 3 standard errors (2.9 %), while dividing by N instead of N - p would be
  // sqrt(53/60) - 1 = -6 % off.
  const double nu = 60 - 7, c4 = 1 - 1 / (4 * nu);
  const double tol = 3 / std::sqrt(2 * nu) / std::sqrt(100.0);
  REQUIRE(tol < 0.5 * (1 - std::sqrt(nu / 60)));
  INFO("mean sigma_y / noise = " << sigma_y_sum / 100 / noise);
  CHECK(sigma_y_sum / 100 == Approx(c4 * noise).epsilon(tol));
}

TEST_CASE("the denominator stays free of roots on the window", "[tcfit]") {
  // Data with a pole just inside the window: an unconstrained 1/1 fit would put g's root at
  // x = 0.1 and chase it. The fit must keep g > 0 on [-1, 1].
  std::vector<double> r, y;
  for (int i = 0; i <= 40; ++i) {
    const double x = -1 + 2.0 * i / 40;
    if (std::fabs(x - 0.1) < 0.04) continue;
    r.push_back(1000 + 100 * x);
    y.push_back(1 / (x - 0.1));
  }
  const RationalFit f = fit_rational(r, y, 900, 1100, 1, 1);
  CHECK(f.min_denominator > 0);
  CHECK(real_roots_in(f.b, -1, 1).empty());
}

TEST_CASE("rational fit: bad input is a clear data error", "[tcfit]") {
  std::string msg;
  const std::vector<double> r = {1, 2, 3, 4, 5}, y = {0, 1, 2, 1, 0};
  CHECK(test::error_code([&] { fit_rational(r, y, 1, 5, 2, 4); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("5 points in the window for 7 parameters"));
  const std::vector<double> rd = {1, 2, 2, 4, 5, 6, 7, 8};
  const std::vector<double> yd = {0, 1, 2, 1, 0, 0, 0, 0};
  CHECK(test::error_code([&] { fit_rational(rd, yd, 1, 8, 1, 1); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("increase strictly"));
  const std::vector<double> yn = {0, 1, NAN, 1, 0};
  CHECK(test::error_code([&] { fit_rational(r, yn, 1, 5, 1, 0); }, &msg) == 65);
}
