// Built-in multi-objective test problems: values at hand-worked points, bounds, known fronts.
#include <catch2/catch.hpp>

#include <cmath>

#include "../support.hpp"
#include "turnfit/optimize/problems.hpp"

using namespace turnfit;
using turnfit::test::error_code;

namespace {
constexpr double kPi = 3.14159265358979323846;
}

TEST_CASE("ZDT problems at hand-worked points", "[nsga2][problems]") {
  auto z1 = make_problem("zdt1");
  REQUIRE(z1->name() == "ZDT1");
  REQUIRE(z1->n_variables() == 30);
  REQUIRE(z1->n_objectives() == 2);
  REQUIRE(z1->n_constraints() == 0);
  std::vector<double> x(30, 0.0);
  x[0] = 0.25;
  auto e = z1->evaluate(x);
  REQUIRE(e.ok);
  CHECK(e.f[0] == Approx(0.25));
  CHECK(e.f[1] == Approx(0.5));  // g = 1: 1 - sqrt(0.25)
  std::fill(x.begin() + 1, x.end(), 1.0);  // g = 1 + 9 = 10
  e = z1->evaluate(x);
  CHECK(e.f[1] == Approx(10 * (1 - std::sqrt(0.025))));

  auto z2 = make_problem("ZDT2", 5);
  REQUIRE(z2->n_variables() == 5);
  e = z2->evaluate({0.5, 0, 0, 0, 0});
  CHECK(e.f[1] == Approx(0.75));
  e = z2->evaluate({0.5, 0.5, 0.5, 0.5, 0.5});  // g = 1 + 4.5 = 5.5
  CHECK(e.f[1] == Approx(5.5 * (1 - std::pow(0.5 / 5.5, 2))));

  auto z3 = make_problem("ZDT3");
  std::vector<double> x3(30, 0.0);
  x3[0] = 0.05;
  CHECK(z3->evaluate(x3).f[1] == Approx(1 - std::sqrt(0.05) - 0.05 * std::sin(0.5 * kPi)));

  auto z4 = make_problem("ZDT4");
  REQUIRE(z4->n_variables() == 10);
  CHECK(z4->lower()[0] == 0);
  CHECK(z4->upper()[0] == 1);
  CHECK(z4->lower()[5] == -5);
  CHECK(z4->upper()[5] == 5);
  std::vector<double> x4(10, 0.0);
  x4[0] = 0.36;
  CHECK(z4->evaluate(x4).f[1] == Approx(0.4));  // cos(0) = 1: g = 1 + 90 - 90
  x4[3] = 0.5;  // x^2 - 10 cos(2 pi) adds 0.25 - 10, from -10: +0.25
  CHECK(z4->evaluate(x4).f[1] == Approx(1.25 * (1 - std::sqrt(0.36 / 1.25))));

  auto z6 = make_problem("ZDT6");
  REQUIRE(z6->n_variables() == 10);
  std::vector<double> x6(10, 0.0);
  x6[0] = 0.1;
  const double f1 = 1 - std::exp(-0.4) * std::pow(std::sin(0.6 * kPi), 6);
  e = z6->evaluate(x6);
  CHECK(e.f[0] == Approx(f1));
  CHECK(e.f[1] == Approx(1 - f1 * f1));
}

TEST_CASE("ZDT fronts: shapes, the disconnected ZDT3 and ZDT6's lower end", "[nsga2][problems]") {
  auto f1 = make_problem("ZDT1")->true_front(101);
  REQUIRE(f1.size() == 101);
  for (auto& p : f1) CHECK(p[1] == Approx(1 - std::sqrt(p[0])).epsilon(0).margin(1e-12));
  CHECK(nondominated_points(f1).size() == f1.size());

  auto f3 = make_problem("ZDT3")->true_front(5000);
  REQUIRE(f3.size() > 3000);
  CHECK(nondominated_points(f3).size() == f3.size());
  // Five pieces: the first ends at f1 = 0.0830, the second starts at 0.1822 (Zitzler et al.).
  double max_first = 0, min_second = 1;
  for (auto& p : f3) {
    CHECK(!(p[0] > 0.0835 && p[0] < 0.1820));
    if (p[0] < 0.13) max_first = std::max(max_first, p[0]);
    else min_second = std::min(min_second, p[0]);
  }
  CHECK(max_first == Approx(0.0830015349).epsilon(0).margin(2e-4));
  CHECK(min_second == Approx(0.1822287280).epsilon(0).margin(2e-4));
  CHECK(f3.back()[0] == Approx(0.8518328654).epsilon(0).margin(2e-4));
  CHECK(f3.back()[1] == Approx(-0.7733).epsilon(0).margin(1e-3));

  auto f6 = make_problem("ZDT6")->true_front(100);
  CHECK(f6.front()[0] == Approx(0.2807753191).epsilon(0).margin(1e-6));
  CHECK(f6.back()[0] == Approx(1.0));
}

TEST_CASE("DTLZ2 and C2-DTLZ2", "[nsga2][problems]") {
  auto d = make_problem("DTLZ2");
  REQUIRE(d->n_variables() == 12);
  REQUIRE(d->n_objectives() == 3);
  std::vector<double> x(12, 0.5);
  x[0] = 0.3;
  x[1] = 0.8;
  auto e = d->evaluate(x);
  CHECK(e.f[0] == Approx(std::cos(0.15 * kPi) * std::cos(0.4 * kPi)));
  CHECK(e.f[1] == Approx(std::cos(0.15 * kPi) * std::sin(0.4 * kPi)));
  CHECK(e.f[2] == Approx(std::sin(0.15 * kPi)));
  x[5] = 1.0;  // g = 0.25
  e = d->evaluate(x);
  CHECK(e.f[0] * e.f[0] + e.f[1] * e.f[1] + e.f[2] * e.f[2] == Approx(1.25 * 1.25));

  auto d5 = make_problem("dtlz2", 0, 5);
  REQUIRE(d5->n_objectives() == 5);
  REQUIRE(d5->n_variables() == 14);
  auto front5 = d5->true_front(200);
  REQUIRE(front5.size() >= 200);
  for (auto& p : front5) {
    double r = 0;
    for (double v : p) r += v * v;
    CHECK(r == Approx(1));
  }

  auto c2 = make_problem("C2-DTLZ2");
  REQUIRE(c2->n_constraints() == 1);
  // On the front near the axis f3: feasible (inside radius 0.4 of (0, 0, 1)).
  std::vector<double> xa(12, 0.5);
  xa[0] = 0.95;
  CHECK(c2->evaluate(xa).g[0] < 0);
  // Between an axis point and the centre, (1/sqrt 2, 1/sqrt 2, 0): infeasible.
  std::vector<double> xb(12, 0.5);
  xb[0] = 0;
  xb[1] = 0.5;
  e = c2->evaluate(xb);
  const double s = 1 / std::sqrt(2.0), c = 1 / std::sqrt(3.0);
  const double expect = std::min((s - 1) * (s - 1) + 0.5 - 0.16, 2 * (s - c) * (s - c) + c * c - 0.16);
  CHECK(e.g[0] == Approx(expect));
  CHECK(e.g[0] > 0);
  auto front = c2->true_front(500);
  REQUIRE(front.size() > 100);
  for (auto& p : front) CHECK(p[0] * p[0] + p[1] * p[1] + p[2] * p[2] == Approx(1));
}

TEST_CASE("Constrained problems: hand-worked values and fronts", "[nsga2][problems]") {
  auto bnh = make_problem("BNH");
  auto e = bnh->evaluate({0, 0});
  CHECK(e.f == std::vector<double>{0, 50});
  CHECK(e.g[0] == Approx(0));  // on the boundary of C1
  CHECK(e.g[1] == Approx(7.7 - 64 - 9));
  CHECK(constraint_violation(bnh->evaluate({5, 3}).g) == 0);
  auto fb = bnh->true_front(200);
  CHECK(fb.front() == std::vector<double>{0, 50});
  CHECK(fb.back()[0] == Approx(136));  // x = (5, 3)
  CHECK(fb.back()[1] == Approx(4));

  auto tnk = make_problem("TNK");
  e = tnk->evaluate({1, 1});
  CHECK(e.g[0] == Approx(1.1 - 2));
  CHECK(e.g[1] == Approx(0).margin(1e-15));
  CHECK(tnk->evaluate({0.5, 0.5}).g[0] > 0);  // inside the wavy circle
  auto ft = tnk->true_front(200);
  REQUIRE(ft.size() > 50);
  for (auto& p : ft) {
    auto ev = tnk->evaluate(p);  // f = x
    CHECK(std::fabs(ev.g[0]) < 1e-12);
    CHECK(ev.g[1] <= 0);
  }
  CHECK(nondominated_points(ft).size() == ft.size());

  auto osy = make_problem("OSY");
  REQUIRE(osy->n_variables() == 6);
  REQUIRE(osy->n_constraints() == 6);
  e = osy->evaluate({5, 1, 5, 0, 5, 0});  // the front's end of least f1 (Deb 2001)
  CHECK(e.f[0] == Approx(-274));
  CHECK(e.f[1] == Approx(76));
  CHECK(constraint_violation(e.g) == 0);
  auto fo = osy->true_front(300);
  CHECK(fo.front()[0] == Approx(-274));
  CHECK(fo.back()[0] == Approx(-42));  // x = (1, 1, 1, 0, 1, 0): the end of least f2
  CHECK(fo.back()[1] == Approx(4));

  auto srn = make_problem("SRN");
  e = srn->evaluate({-2.5, 2.5});
  CHECK(e.f[0] == Approx(24.5));
  CHECK(e.f[1] == Approx(-24.75));
  CHECK(e.g[1] == Approx(0));
  auto fs = srn->true_front(400);
  REQUIRE(fs.size() == 400);
  CHECK(nondominated_points(fs).size() == fs.size());
  // The middle is Deb's x1 = -2.5 (there f1 + f2 = -0.25); the ends lie on the constraints,
  // the small-f1 end on x1 = 3 x2 - 10 near (1.2, 3.74), f1 about 10.1.
  int middle = 0;
  for (auto& f : fs) middle += std::fabs(f[0] + f[1] + 0.25) < 1e-9;
  CHECK(middle > 100);
  CHECK(fs.front()[0] < 10.2);
  CHECK(fs.front()[0] > 9.5);
}

TEST_CASE("make_problem refuses unknown names and impossible sizes", "[nsga2][problems]") {
  std::string msg;
  CHECK(error_code([] { make_problem("zdt5"); }, &msg) == 64);
  CHECK(msg.find("ZDT1") != std::string::npos);
  CHECK(error_code([] { make_problem("OSY", 7); }) == 64);
  CHECK(error_code([] { make_problem("ZDT1", 1); }) == 64);
  CHECK(error_code([] { make_problem("ZDT1", 30, 3); }) == 64);
  CHECK(error_code([] { make_problem("DTLZ2", 2, 3); }) == 64);
  for (auto& n : builtin_problem_names()) CHECK(make_problem(n)->name() == n);
}

TEST_CASE("Violation, non-dominated filter and distances to a front", "[nsga2][problems]") {
  CHECK(constraint_violation({-1, 0.5, 0, 2}) == 2.5);
  CHECK(constraint_violation({}) == 0);
  CHECK(std::isnan(constraint_violation({1, std::nan("")})));
  auto nd = nondominated_points({{1, 3}, {2, 2}, {2, 2}, {3, 3}, {3, 1}, {1, 4}});
  CHECK(nd == std::vector<std::vector<double>>{{1, 3}, {2, 2}, {3, 1}});
  std::vector<std::vector<double>> front{{0, 1}, {1, 0}};
  CHECK(generational_distance({{0, 2}, {1, 0}}, front) == Approx(0.5));
  CHECK(inverted_generational_distance({{0, 1}}, front) == Approx(std::sqrt(2.0) / 2));
}
