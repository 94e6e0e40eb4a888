// Field maps: spline exactness and continuity, symmetry, readers, writers and their errors.
#include <catch2/catch.hpp>

#include <functional>
#include <cmath>
#include <sstream>

#include "../support.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"

using namespace turnfit;
using Catch::Matchers::Contains;

namespace {
constexpr double kPi = 3.14159265358979323846;

PolarGrid small_grid(int symmetry = 4, int nr = 21, int nt = 36) {
  PolarGrid g;
  g.r_min_mm = 500;
  g.dr_mm = 50;
  g.nr = nr;
  g.theta_min_deg = 0;
  g.ntheta = nt;
  g.symmetry = symmetry;
  return g;
}

}  // namespace

TEST_CASE("field: spline reproduces constants and cubics in r exactly", "[field]") {
  auto f = [](double r, double) { return 0.3 + 0.2 * r - 0.15 * r * r + 0.05 * r * r * r; };
  PolarFieldMap map = make_field_map(small_grid(), f, "cubic");
  for (double r : {0.5, 0.61, 0.777, 1.2345, 1.5}) {
    for (double th : {0.0, 0.1, 1.0, 5.0}) {
      FieldSample s;
      REQUIRE(map.sample(r, th, s));
      // A cubic in r is in the spline's space (turnfit-fieldmap(5), Interpolation): exact up to
      // rounding (values ~0.4 T, a few hundred operations: 1e-13; the slope divides by dr = 0.05 m).
      CHECK(s.bz_T == Approx(f(r, th)).epsilon(0).margin(1e-13));
      CHECK(s.dbz_dr_T_m == Approx(0.2 - 0.3 * r + 0.15 * r * r).epsilon(0).margin(1e-12));
      CHECK(s.dbz_dth_T == Approx(0).epsilon(0).margin(1e-12));
    }
  }
}

TEST_CASE("field: smooth azimuthal variation is interpolated to spline accuracy", "[field]") {
  const int N = 4;
  auto f = [&](double r, double th) { return 1.0 + 0.3 * std::cos(N * th) * r; };
  PolarFieldMap map = make_field_map(small_grid(N, 21, 72), f, "flutter");
  double max_err = 0, max_derr = 0;
  for (double r = 0.52; r < 1.49; r += 0.037)
    for (double th = 0; th < 2 * kPi; th += 0.0137) {
      FieldSample s;
      REQUIRE(map.sample(r, th, s));
      max_err = std::max(max_err, std::fabs(s.bz_T - f(r, th)));
      max_derr = std::max(max_derr, std::fabs(s.dbz_dth_T - (-0.3 * N * std::sin(N * th) * r)));
    }
  // f is linear in r, which the radial spline reproduces exactly, so the error is the periodic
  // cubic spline's in theta times 0.3 r. Bounds for a cubic spline interpolant (Hall and Meyer,
  // J. Approx. Theory 16 (1976) 105): |f - s| <= (5/384) h^4 max|f''''| and
  // |f' - s'| <= (sqrt(3)/216 + 1/24) h^3 max|f''''|, with h = 1.25 deg and
  // max|f''''| = 0.3 r_max N^4 (r_max = 1.49 m): 3.4e-7 and 5.9e-5. Was 2e-6 and 1e-4
  // (a rough estimate, 6 and 1.7 times looser).
  const double h = 2 * kPi / N / 72, f4 = 0.3 * 1.49 * std::pow(N, 4);
  const double bound = 5.0 / 384 * std::pow(h, 4) * f4, dbound = (std::sqrt(3.0) / 216 + 1.0 / 24) * std::pow(h, 3) * f4;
  CAPTURE(max_err, bound, max_derr, dbound);
  CHECK(max_err < bound);
  CHECK(max_derr < dbound);
}

TEST_CASE("field: Bz and both derivatives are continuous across cell boundaries", "[field]") {
  // A rough map (random-looking values) is the hard case for continuity.
  auto f = [](double r, double th) { return std::sin(37 * r) + 0.5 * std::cos(3 * th + 11 * r) + std::fmod(r * 7.3, 0.1); };
  PolarFieldMap map = make_field_map(small_grid(3, 15, 24), f, "rough");
  const PolarGrid& g = map.grid();
  // turnfit-fieldmap(5), Interpolation: B_z, dB_z/dr and dB_z/dtheta are continuous. Across a
  // grid line, samples 2 eps apart then differ by 2 eps times the next derivative (the spline is
  // C2 in each variable, so both slopes are C1 in both): the bound is 2 eps times that
  // derivative, read from the sample (values) or by a one-sided difference over delta inside
  // the cell (slopes), times 1.1 for its change over delta, plus rounding (values ~2 T: 1e-14;
  // slopes: 1e-12; the one-sided difference's own error |s'''| delta ~ 1e5 x 1e-7, times 2 eps:
  // 2e-11; 1e-10 covers both). A break in the value or a slope is of the order of the map's
  // steps (0.1-1 T, 10-100 T/m). Was 1e-7 and 1e-5 (no source).
  const double eps = 1e-9, delta = 1e-7;
  auto jump_bound = [&](double d_left, double d_right, double floor) {
    return 1.1 * 2 * eps * std::max(std::fabs(d_left), std::fabs(d_right)) + floor;
  };
  // Continuity across one grid line: at(s) samples the map a signed distance s across it, and
  // `radial` says which slope is the one normal to the line (it bounds the value's jump).
  auto across = [&](const std::function<FieldSample(double)>& at, bool radial) {
    const FieldSample a = at(-eps), b = at(eps), a2 = at(-eps - delta), b2 = at(eps + delta);
    CHECK(a.bz_T == Approx(b.bz_T).epsilon(0).margin(
                        jump_bound(radial ? a.dbz_dr_T_m : a.dbz_dth_T, radial ? b.dbz_dr_T_m : b.dbz_dth_T, 1e-14)));
    const double dr_l = (a.dbz_dr_T_m - a2.dbz_dr_T_m) / delta, dr_r = (b2.dbz_dr_T_m - b.dbz_dr_T_m) / delta;
    const double dt_l = (a.dbz_dth_T - a2.dbz_dth_T) / delta, dt_r = (b2.dbz_dth_T - b.dbz_dth_T) / delta;
    CHECK(a.dbz_dr_T_m == Approx(b.dbz_dr_T_m).epsilon(0).margin(jump_bound(dr_l, dr_r, 1e-10)));
    CHECK(a.dbz_dth_T == Approx(b.dbz_dth_T).epsilon(0).margin(jump_bound(dt_l, dt_r, 1e-10)));
  };
  for (int i = 1; i < g.nr - 1; ++i) {  // radial grid lines
    const double r = g.r_min_m() + i * g.dr_m();
    for (double th : {0.1, 0.7, 1.3}) {
      INFO("r = " << r << ", theta = " << th);
      across(
          [&](double s) {
            FieldSample f;
            REQUIRE(map.sample(r + s, th, f));
            return f;
          },
          true);
    }
  }
  for (int j = 0; j < g.ntheta; ++j) {  // azimuthal grid lines, including the periodic seam
    const double th = j * g.dtheta_rad();
    for (double r : {0.61, 0.93}) {
      INFO("r = " << r << ", theta = " << th);
      across(
          [&](double s) {
            FieldSample f;
            REQUIRE(map.sample(r, th + s, f));
            return f;
          },
          false);
    }
  }
}

TEST_CASE("field: N-fold symmetry and the radial range", "[field]") {
  auto f = [](double r, double th) { return 1 + 0.2 * std::cos(4 * th) + 0.1 * std::sin(8 * th) * r; };
  PolarFieldMap map = make_field_map(small_grid(4), f, "sym");
  for (double th : {0.05, 1.0, 2.5}) {
    CHECK(map.bz(0.8, th) == Approx(map.bz(0.8, th + kPi / 2)).epsilon(0).margin(1e-12));
    CHECK(map.bz(0.8, th) == Approx(map.bz(0.8, th - 6 * kPi)).epsilon(0).margin(1e-12));
  }
  FieldSample s;
  CHECK(map.sample(0.5, 0, s));
  CHECK(map.sample(1.5, 0, s));  // the last radius belongs to the map
  CHECK_FALSE(map.sample(0.4999, 0, s));
  CHECK_FALSE(map.sample(1.5001, 0, s));
  CHECK_FALSE(map.sample(std::nan(""), 0, s));
  CHECK(std::isnan(map.bz(2.0, 0)));
}

TEST_CASE("field: invalid grids and values are rejected", "[field]") {
  PolarGrid g = small_grid();
  std::vector<double> v(static_cast<size_t>(g.nr) * g.ntheta, 1.0);
  CHECK(turnfit::test::error_code([&] { PolarFieldMap(g, std::vector<double>(10, 1.0)); }) == 65);
  v[7] = std::nan("");
  CHECK(turnfit::test::error_code([&] { PolarFieldMap(g, v); }) == 65);
  g.nr = 1;
  CHECK(turnfit::test::error_code([&] { PolarFieldMap(g, std::vector<double>(36, 1.0)); }) == 65);
}

TEST_CASE("field: turnfit format round trip is bit-identical", "[field][io]") {
  auto f = [](double r, double th) { return 1.234567891234 + 0.1 * std::cos(4 * th) * r + 1e-7 * r; };
  PolarFieldMap map = make_field_map(small_grid(), f, "round trip");
  std::ostringstream os;
  write_turnfit_map(os, map);
  PolarFieldMap back = parse_turnfit_map(os.str(), "mem");
  CHECK(back.values() == map.values());
  CHECK(back.grid().symmetry == 4);
  CHECK(back.grid().r_min_mm == 500);
  CHECK(back.label() == "round trip");
  CHECK(back.bz(0.777, 0.3) == map.bz(0.777, 0.3));
}

TEST_CASE("field: psi-ring writer output is read back by the psi-ring reader", "[field][io]") {
  auto f = [](double r, double th) { return 1.5 + 0.4 * std::cos(4 * th) * r - 3e-3 * r * r; };
  PolarFieldMap map = make_field_map(small_grid(), f, "analytic");
  std::ostringstream os;
  write_psi_ring(os, map);
  PolarFieldMap back = parse_psi_ring(os.str(), "mem");
  REQUIRE(back.grid().nr == map.grid().nr);
  REQUIRE(back.grid().ntheta == map.grid().ntheta);
  CHECK(back.grid().symmetry == 4);
  for (size_t k = 0; k < map.values().size(); ++k)  // 9 significant digits in kG
    CHECK(back.values()[k] == Approx(map.values()[k]).epsilon(1e-8));
  // A second round trip is exact: the file keeps what it was given.
  std::ostringstream os2;
  write_psi_ring(os2, back);
  CHECK(parse_psi_ring(os2.str(), "mem2").values() == back.values());
  CHECK(os2.str() == [&] { std::ostringstream o; write_psi_ring(o, parse_psi_ring(os2.str(), "x")); return o.str(); }());
}

TEST_CASE("field: psi-ring reader errors name the file and line", "[field][io]") {
  auto f = [](double r, double) { return 1.0 + r; };
  std::ostringstream os;
  write_psi_ring(os, make_field_map(small_grid(4, 5, 36), f, "x"));
  const std::string good = os.str();
  std::string msg;

  // Truncated in the middle of a record.
  CHECK(turnfit::test::error_code([&] { parse_psi_ring(good.substr(0, good.size() * 2 / 3), "cut.dat"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("cut.dat") && Contains("truncated"));

  // A garbled number: the message names its line.
  std::string bad = good;
  auto rec = bad.find("LREC=");
  auto line_start = bad.find('\n', rec) + 1;
  bad.replace(line_start, 16, "    0.1x000E+01");
  bad.insert(line_start, " ");
  long line = 1 + static_cast<long>(std::count(bad.begin(), bad.begin() + static_cast<long>(line_start), '\n'));
  CHECK(turnfit::test::error_code([&] { parse_psi_ring(bad, "bad.dat"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("bad.dat:" + std::to_string(line) + ":"));

  CHECK(turnfit::test::error_code([&] { parse_psi_ring("", "empty.dat"); }, &msg) == 65);
  CHECK(turnfit::test::error_code([&] { parse_psi_ring("1900\n20\n0\n-3\nno blocks here\n", "x.dat"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("LPAR"));
  CHECK(turnfit::test::error_code([&] { parse_psi_ring("1900\n-20\n0\n-3\n", "neg.dat"); }, &msg) == 65);
  // A symmetry that contradicts the grid.
  CHECK(turnfit::test::error_code([&] { parse_psi_ring(good, "sym.dat", 8); }, &msg) == 65);
  CHECK_THAT(msg, Contains("symmetry"));
}

TEST_CASE("field: turnfit-format reader errors", "[field][io]") {
  const std::string head =
      "turnfit-fieldmap 1\nsymmetry 2\nr_min_mm 100\ndr_mm 10\nnr 2\ntheta_min_deg 0\nntheta 3\nunit T\ndata\n";
  CHECK_NOTHROW(parse_turnfit_map(head + "1 2 3\n4 5 6\n", "ok"));
  CHECK(parse_turnfit_map(head + "1 2 3\n4 5 6\n", "ok").value(1, 2) == 6);
  std::string msg;
  CHECK(turnfit::test::error_code([&] { parse_turnfit_map(head + "1 2 3\n", "short"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("truncated"));
  CHECK(turnfit::test::error_code([&] { parse_turnfit_map(head + "1 2 3\n4 5\n", "row"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("row:11:"));
  CHECK(turnfit::test::error_code([&] { parse_turnfit_map(head + "1 2 3\n4 nan 6\n", "nan"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("nan:11:"));
  CHECK(turnfit::test::error_code([&] { parse_turnfit_map("hello\n", "x"); }, &msg) == 65);
  CHECK(turnfit::test::error_code([&] { parse_turnfit_map("turnfit-fieldmap 1\nsymmetry 2\ncolour red\n", "key"); }, &msg) == 65);
  CHECK_THAT(msg, Contains("key:3:") && Contains("colour"));
  std::string kg = head;
  kg.replace(kg.find("unit T"), 6, "unit kG");
  CHECK(parse_turnfit_map(kg + "10 20 30\n40 50 60\n", "kg").value(0, 1) == Approx(2.0).epsilon(0).margin(1e-15));  // 20 kG / 10: exact
}

TEST_CASE("field: the PSI Ring map reads as physics.md describes it", "[field][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  PolarFieldMap map = read_field_map(path, MapFormat::psi_ring);
  const PolarGrid& g = map.grid();
  CHECK(g.nr == 141);
  CHECK(g.ntheta == 135);
  CHECK(g.symmetry == 8);
  CHECK(g.r_min_mm == 1900);
  // Grid arithmetic on the header's integers (1900 + 140 x 20 mm, 2 pi / (8 x 135)): exact to an ulp.
  CHECK(g.r_max_m() == Approx(4.7).epsilon(1e-12));
  CHECK(g.dtheta_rad() == Approx(kPi / 540).epsilon(1e-12));
  // First value of the first record: 0.591675472E+01 kG, read and divided by 10: exact to an ulp
  // (the file's 9 significant digits are kept, so 1e-12 relative is far below its last digit).
  CHECK(map.value(0, 0) == Approx(0.591675472).epsilon(1e-12));
  // Peak hill field about 14.8 kG at 2.1 m and 20.7 kG at 4.5 m, at theta = 0 (hill centre).
  auto peak = [&](int i) {
    double m = 0;
    int at = 0;
    for (int j = 0; j < g.ntheta; ++j)
      if (map.value(i, j) > m) m = map.value(i, at = j);
    return std::make_pair(m, at);
  };
  auto p21 = peak(10), p45 = peak(130);
  CAPTURE(p21.first, p45.first);
  // physics.md states the peaks to 0.1 kG ("about 14.8 kG", "20.7 kG"): the map's grid maximum
  // rounds to those digits, so within half of the last one, 0.05 kG = 0.005 T.
  CHECK(p21.first == Approx(1.48).epsilon(0).margin(0.005));
  CHECK(p45.first == Approx(2.07).epsilon(0).margin(0.005));
  CHECK(p21.second <= 6);  // within 2 deg of theta = 0
  CHECK(map.bz(2.1, 0) > map.bz(2.1, kPi / 8));  // hill centre above the valley
}

TEST_CASE("field: the PSI Ring map survives both writers unchanged", "[field][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  PolarFieldMap map = read_field_map(path, MapFormat::psi_ring);
  std::ostringstream a, b;
  write_turnfit_map(a, map);
  write_psi_ring(b, map);
  CHECK(parse_turnfit_map(a.str(), "a").values() == map.values());
  CHECK(parse_psi_ring(b.str(), "b").values() == map.values());
}
