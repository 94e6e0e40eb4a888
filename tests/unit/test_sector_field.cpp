// Analytic separated-sector fields: edge shape, periodicity, flutter, spiral, sampling, checks.
#include <catch2/catch.hpp>

#include <cmath>

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
}  // namespace

TEST_CASE("sector field: radial tables are linear between nodes and flat beyond", "[field][sector]") {
  RadialTable t{{1000, 2000, 4000}, {1, 3, 2}};
  CHECK(t.at(500) == 1);
  CHECK(t.at(1500) == Approx(2));
  CHECK(t.at(3000) == Approx(2.5));
  CHECK(t.at(5000) == 2);
  CHECK(RadialTable{{1000}, {7}}.at(3000) == 7);
}

TEST_CASE("sector field: the shape is 1 in a magnet, 0 in a valley, 1/2 on an edge", "[field][sector]") {
  const SectorFieldSpec s = ring_like();
  const double r = 3000, w = s.width_deg.at(r);
  CHECK(sector_shape(s, r, 0) == Approx(1).margin(1e-12));
  CHECK(sector_shape(s, r, 22.5) == Approx(0).margin(1e-12));
  // On the edge the rising tanh is 1/2 and the falling one, a magnet width away, is 1.
  CHECK(sector_shape(s, r, w / 2) == Approx(0.5).margin(1e-12));
  CHECK(sector_shape(s, r, -w / 2) == Approx(0.5).margin(1e-12));
  // One edge length inside: (1 + tanh 1) / 2.
  const double one = s.fringe_mm / r * 180 / 3.14159265358979323846;
  CHECK(sector_shape(s, r, w / 2 - one) == Approx(0.5 * (1 + std::tanh(1.0))).epsilon(1e-12));
}

TEST_CASE("sector field: periodic in 360/N, mirror-symmetric without spiral", "[field][sector]") {
  const SectorFieldSpec s = ring_like();
  for (double r : {1900.0, 2500.0, 4400.0})
    for (double th = -30; th < 30; th += 0.37) {
      CHECK(sector_shape(s, r, th + 45) == Approx(sector_shape(s, r, th)).margin(1e-14));
      CHECK(sector_shape(s, r, -th) == Approx(sector_shape(s, r, th)).margin(1e-14));
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
  s.spiral_deg = 30;
  s.spiral_r0_mm = 2000;
  const double r = 2000 * std::exp(0.5), centre = std::tan(30 * 3.14159265358979323846 / 180) * 0.5 * 180 /
                                                      3.14159265358979323846;
  CHECK(sector_shape(s, 2000, 0) == Approx(1).margin(1e-12));
  for (double d : {1.0, 5.0, 9.0}) CHECK(sector_shape(s, r, centre + d) == Approx(sector_shape(s, r, centre - d)).margin(1e-13));
  CHECK(sector_shape(s, r, centre + 0.5 * s.width_deg.at(r)) == Approx(0.5).margin(1e-12));
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
