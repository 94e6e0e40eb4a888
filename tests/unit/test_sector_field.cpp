// Analytic separated-sector fields: edge shape, periodicity, flutter, spiral, sampling, checks.
#include <catch2/catch.hpp>

#include <cmath>
#include <functional>
#include <nlohmann/json.hpp>

#include "../support.hpp"
#include "turnfit/field/sector_field.hpp"

using namespace turnfit;
using turnfit::test::error_code;

namespace {
SectorFieldSpec ring_like() {
  SectorFieldSpec s;
  s.sectors = 8;
  s.width_deg = {{2000, 4500}, {18, 24}};
  s.hill_T = {{2000, 4500}, {1.6, 2.1}};
  s.fringe_mm = 40;
  s.grid.r_min_mm = 1800;
  s.grid.dr_mm = 20;
  s.grid.nr = 151;
  s.grid.ntheta = 135;
  s.grid.symmetry = 8;
  return s;
}

/// The shape on a magnet's centre line: both tanh edges half a width away along the arc,
/// (1 + tanh(d / lambda))^2 / 4 with d = r w / 2 (turnfit-sector-field(5)); not exactly 1.
double centre_shape(const SectorFieldSpec& s, double r_mm) {
  const double d = r_mm * 0.5 * s.width_deg.at(r_mm) * 3.14159265358979323846 / 180;
  const double e = 0.5 * (1 + std::tanh(d / s.fringe_mm));
  return e * e;
}
}  // namespace

TEST_CASE("sector field: radial tables are natural cubic splines, straight beyond the ends", "[field][sector]") {
  RadialTable t{{1000, 2000, 2500, 4000}, {1, 3, 2.5, 2}};
  // Through the nodes.
  for (size_t i = 0; i < t.r_mm.size(); ++i) CHECK(t.at(t.r_mm[i]) == Approx(t.value[i]).epsilon(1e-14));
  // C2 inside: one-sided second differences agree at an interior node; slope() is the derivative.
  const double h = 1e-2;
  for (double r : {2000.0, 2500.0}) {
    const double left = (t.at(r) - 2 * t.at(r - h) + t.at(r - 2 * h)) / (h * h);
    const double right = (t.at(r + 2 * h) - 2 * t.at(r + h) + t.at(r)) / (h * h);
    CHECK(left == Approx(right).epsilon(0).margin(1e-6));
  }
  for (double r : {1200.0, 2200.0, 3900.0})
    CHECK(t.slope(r) == Approx((t.at(r + h) - t.at(r - h)) / (2 * h)).epsilon(1e-7));
  // Natural ends: no curvature there, so the straight continuation is C2 too.
  const std::vector<double> m2 = t.curvatures();
  CHECK(m2.front() == 0);
  CHECK(m2.back() == 0);
  CHECK(t.at(500) == Approx(1 - 500 * t.slope(1000)).epsilon(1e-14));
  CHECK(t.at(5000) == Approx(2 + 1000 * t.slope(4000)).epsilon(1e-14));
  // A spline reproduces straight lines exactly, whatever the node spacing.
  RadialTable line{{1000, 1300, 2000, 3700}, {2, 2.6, 4, 7.4}};
  for (double r = 800; r < 4000; r += 77) CHECK(line.at(r) == Approx(2 + 0.002 * (r - 1000)).epsilon(1e-13));
  CHECK(RadialTable{{1000}, {7}}.at(3000) == 7);
  CHECK(RadialTable{{1000}, {7}}.slope(3000) == 0);
}

TEST_CASE("sector field: the shape is 1 in a magnet, 0 in a valley, 1/2 on an edge", "[field][sector]") {
  const SectorFieldSpec s = ring_like();
  const double r = 3000, w = s.width_deg.at(r);
  // On the centre line both edges are half a width away: (1 + tanh(d / lambda))^2 / 4 with
  // d = r w / 2, 1 - 5e-12 here (the neighbours' tails, exp(-2 r (45 - w / 2) / lambda) ~ 1e-50,
  // do not show). Exact up to rounding (1e-12).
  CHECK(sector_shape(s, r, 0) == Approx(centre_shape(s, r)).epsilon(0).margin(1e-12));
  CHECK(sector_shape(s, r, 22.5) == Approx(0).margin(1e-12));
  // On the edge the rising tanh is 1/2 and the falling one, a magnet width away, is 1.
  CHECK(sector_shape(s, r, w / 2) == Approx(0.5).epsilon(0).margin(1e-12));
  CHECK(sector_shape(s, r, -w / 2) == Approx(0.5).epsilon(0).margin(1e-12));
  // One edge length inside: (1 + tanh 1) / 2.
  const double one = s.fringe_mm / r * 180 / 3.14159265358979323846;
  CHECK(sector_shape(s, r, w / 2 - one) == Approx(0.5 * (1 + std::tanh(1.0))).epsilon(1e-12));
}

TEST_CASE("sector field: periodic in 360/N, mirror-symmetric without spiral", "[field][sector]") {
  const SectorFieldSpec s = ring_like();
  for (double r : {1900.0, 2500.0, 4400.0})
    for (double th = -30; th < 30; th += 0.37) {
      CHECK(sector_shape(s, r, th + 45) == Approx(sector_shape(s, r, th)).epsilon(0).margin(1e-14));
      CHECK(sector_shape(s, r, -th) == Approx(sector_shape(s, r, th)).epsilon(0).margin(1e-14));
    }
}

TEST_CASE("sector field: the mean of the shape over a sector is the magnet's share of it", "[field][sector]") {
  // The integral of the two tanh edges over azimuth is the width exactly, up to tails of
  // exp(-2 r w / lambda), negligible here: <S> = width / (360 / N).
  const SectorFieldSpec s = ring_like();
  for (double r : {2000.0, 3000.0, 4500.0}) {
    const int n = 36000;
    double sum = 0;
    for (int i = 0; i < n; ++i) sum += sector_shape(s, r, -22.5 + 45.0 * (i + 0.5) / n);
    CHECK(sum / n == Approx(s.width_deg.at(r) / 45).epsilon(1e-9));
  }
}

TEST_CASE("sector field: a spiral turns the centre line by tan(xi) ln(r / r0)", "[field][sector]") {
  SectorFieldSpec s = ring_like();
  s.spiral_deg = {{2000}, {30}};
  s.spiral_r0_mm = 2000;
  const double r = 2000 * std::exp(0.5), centre = std::tan(30 * 3.14159265358979323846 / 180) * 0.5 * 180 /
                                                      3.14159265358979323846;
  // At r0 the centre line is at 0: the centred value (1 + tanh(d / lambda))^2 / 4 = 1 - 3e-7
  // (width 18 deg at 2 m: d = 314 mm, 7.85 edge lengths), exact up to rounding.
  CHECK(sector_shape(s, 2000, 0) == Approx(centre_shape(s, 2000)).epsilon(0).margin(1e-12));
  for (double d : {1.0, 5.0, 9.0}) CHECK(sector_shape(s, r, centre + d) == Approx(sector_shape(s, r, centre - d)).epsilon(0).margin(1e-13));
  CHECK(sector_shape(s, r, centre + 0.5 * s.width_deg.at(r)) == Approx(0.5).epsilon(0).margin(1e-12));
}

TEST_CASE("sector field: a spiral table turns the centre line at d theta_c / dr = tan(xi(r)) / r", "[field][sector]") {
  SectorFieldSpec s = ring_like();
  s.spiral_deg = {{1800, 2500, 3500, 4500}, {0, 5, 20, 35}};
  s.spiral_r0_mm = 2000;
  CHECK(sector_centre_deg(s, 2000) == 0);
  const double d2r = 3.14159265358979323846 / 180;
  for (double r : {1900.0, 2300.0, 3000.0, 4400.0, 4800.0}) {
    const double h = 0.01;
    const double dc = (sector_centre_deg(s, r + h) - sector_centre_deg(s, r - h)) / (2 * h) * d2r;
    CHECK(dc == Approx(std::tan(s.spiral_deg.at(r) * d2r) / r).epsilon(1e-8));
  }
  // The magnet stays symmetric about the turned centre line.
  const double r = 4000, c = sector_centre_deg(s, r);
  for (double d : {2.0, 8.0, 15.0}) CHECK(sector_shape(s, r, c + d) == Approx(sector_shape(s, r, c - d)).epsilon(0).margin(1e-13));
}

TEST_CASE("sector field: JSON round trip gives the same field bit for bit", "[field][sector]") {
  SectorFieldSpec s = ring_like();
  s.spiral_deg = {{1800, 3000, 4500}, {0, 12.5, 31}};
  s.spiral_r0_mm = 2000;
  s.valley_fraction = 0.03;
  s.description = "round trip";
  const nlohmann::json doc = sector_spec_to_json(s);
  const SectorFieldSpec back = sector_spec_from_json(nlohmann::json::parse(doc.dump()), "mem");
  const PolarFieldMap a = make_sector_field(s), b = make_sector_field(back);
  REQUIRE(a.values().size() == b.values().size());
  for (size_t i = 0; i < a.values().size(); ++i) REQUIRE(a.values()[i] == b.values()[i]);
  CHECK(back.description == "round trip");
}

TEST_CASE("sector field: JSON errors name the key path", "[field][sector]") {
  const nlohmann::json good = sector_spec_to_json(ring_like());
  std::string msg;
  auto bad = [&](const std::function<void(nlohmann::json&)>& change) {
    nlohmann::json d = good;
    change(d);
    return error_code([&] { sector_spec_from_json(d, "spec.json"); }, &msg);
  };
  CHECK(bad([](nlohmann::json& d) { d["fringe_cm"] = 4; }) == 65);
  CHECK_THAT(msg, Catch::Contains("spec.json") && Catch::Contains("/fringe_cm") && Catch::Contains("fringe_mm"));
  CHECK(bad([](nlohmann::json& d) { d["hill"]["field_T"] = {1.5}; }) == 65);
  CHECK_THAT(msg, Catch::Contains("/hill/field_T"));
  CHECK(bad([](nlohmann::json& d) { d["width"]["r_mm"] = {3000, 2000}; }) == 65);
  CHECK_THAT(msg, Catch::Contains("/width/r_mm/1"));
  CHECK(bad([](nlohmann::json& d) { d["format"] = "turnfit-machine/1"; }) == 65);
  CHECK_THAT(msg, Catch::Contains("/format"));
  CHECK(bad([](nlohmann::json& d) { d["grid"]["nr"] = 2.5; }) == 65);
  CHECK_THAT(msg, Catch::Contains("/grid/nr"));
  CHECK(bad([](nlohmann::json& d) { d["width"]["width_deg"] = {50, 50}; }) == 65);
  CHECK_THAT(msg, Catch::Contains("width_deg"));
}

TEST_CASE("sector field: sampled maps hold B_hill (v + (1 - v) S) at the nodes", "[field][sector]") {
  SectorFieldSpec s = ring_like();
  s.valley_fraction = 0.1;
  const PolarFieldMap m = make_sector_field(s);
  for (int i : {0, 40, 150})
    for (int j : {0, 27, 67, 134}) {
      const double r = 1800 + 20 * i, th = j / 3.0;
      const double want = s.hill_T.at(r) * (0.1 + 0.9 * sector_shape(s, r, th));
      CHECK(m.value(i, j) == Approx(want).epsilon(1e-14));
    }
  // The valley keeps its fraction of the hill field.
  CHECK(m.bz(3.0, 22.5 * 3.14159265358979323846 / 180) == Approx(0.1 * s.hill_T.at(3000)).epsilon(1e-6));
}

TEST_CASE("sector field: unusable specs are data errors naming the field", "[field][sector]") {
  std::string msg;
  SectorFieldSpec s = ring_like();
  s.width_deg.value = {18, 46};
  CHECK(error_code([&] { validate_sector_spec(s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("width_deg"));
  s = ring_like();
  s.hill_T.r_mm = {2000, 2000};
  CHECK(error_code([&] { validate_sector_spec(s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("hill_T"));
  s = ring_like();
  s.fringe_mm = 0;
  CHECK(error_code([&] { make_sector_field(s); }) == 65);
  s = ring_like();
  s.grid.symmetry = 4;
  CHECK(error_code([&] { make_sector_field(s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("symmetry"));
  s = ring_like();
  s.valley_fraction = 1.5;
  CHECK(error_code([&] { validate_sector_spec(s); }) == 65);
}
