// Sector windows follow a spiral: the track model's fitted centre line of sector 1, and trim coil
// sector lists and sector-strength windows that turn with it.
#include <catch2/catch.hpp>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "turnfit/field/sector_field.hpp"
#include "turnfit/track/model.hpp"

using namespace turnfit;

namespace {
constexpr double kDeg = 3.14159265358979323846 / 180;

SectorFieldSpec spiral_spec() {
  SectorFieldSpec s;
  s.sectors = 8;
  s.width_deg = {{2000, 4500}, {21, 19.5}};
  s.spiral_deg = {{1800, 2500, 3500, 4000, 4400, 4900}, {0, 3, 17, 24.5, 33, 39.5}};  // ring8's
  s.spiral_r0_mm = 2000;
  s.fringe_mm = 60;
  s.hill_T = {{1800, 4900}, {1.3, 2.1}};
  s.grid.r_min_mm = 1800;
  s.grid.dr_mm = 20;
  s.grid.nr = 156;
  s.grid.ntheta = 135;
  s.grid.symmetry = 8;
  return s;
}

TrackModel model_of(const SectorFieldSpec& s) {
  TrackModel t;
  t.map = make_sector_field(s);
  fit_sector_centre(t);
  return t;
}
}  // namespace

TEST_CASE("sector windows: the fitted centre line follows the spiral", "[track][sector]") {
  const SectorFieldSpec s = spiral_spec();
  const TrackModel t = model_of(s);
  // Tolerance: the truncation error of the centre line's form. fit_sector_centre (model.cpp)
  // fits a quartic in r to the phase of the field's N-th harmonic, weighted by its amplitude;
  // the sector shape is symmetric about the spiral centre at every radius, so that phase is the
  // centre itself and the only error left is the quartic's. Bound: the largest residual over the
  // grid of the same weighted quartic fitted here to the exact centre line (weights hill (1 - v)
  // sin(N w / 2), a hard-edged sector's first harmonic; the tanh fringe changes them by < 1%):
  // 0.081 deg on ring8's spiral, which turns by 13 deg over the grid. Was 0.15 deg (no source).
  // Measured: 0.075 deg at the grid's inner edge, 0.047 deg at most inside.
  const PolarGrid& g = s.grid;
  const double r_mid = g.r_min_mm + 0.5 * (g.nr - 1) * g.dr_mm, r_half = 0.5 * (g.nr - 1) * g.dr_mm;
  Eigen::MatrixXd A(g.nr, 5);
  Eigen::VectorXd b(g.nr);
  for (int i = 0; i < g.nr; ++i) {
    const double r = g.r_min_mm + i * g.dr_mm, x = (r - r_mid) / r_half;
    const double w = s.hill_T.at(r) * std::sin(s.sectors * 0.5 * s.width_deg.at(r) * kDeg);
    for (int k = 0; k < 5; ++k) A(i, k) = w * std::pow(x, k);
    b(i) = w * sector_centre_deg(s, r);
  }
  const Eigen::VectorXd q = A.colPivHouseholderQr().solve(b);
  double tol = 0;
  for (int i = 0; i < g.nr; ++i) {
    const double r = g.r_min_mm + i * g.dr_mm, x = (r - r_mid) / r_half;
    double v = 0;
    for (int k = 0; k < 5; ++k) v += q(k) * std::pow(x, k);
    tol = std::max(tol, std::fabs(v - sector_centre_deg(s, r)));
  }
  CAPTURE(tol);
  REQUIRE(tol < 0.1);  // the bound itself: a quartic follows this spiral to 0.081 deg
  for (int i = 0; i < g.nr; ++i) {
    const double r = g.r_min_mm + i * g.dr_mm;
    double dc;
    const double c = t.sector_centre(r * 1e-3, dc) / kDeg;
    INFO("r = " << r);
    CHECK(c == Approx(sector_centre_deg(s, r)).epsilon(0).margin(tol));
  }
  // Without a spiral the centre stays on theta = 0; without sectors there is none.
  SectorFieldSpec straight = s;
  straight.spiral_deg = {};
  const TrackModel ts = model_of(straight);
  double dc;
  CHECK(ts.sector_centre(4.0, dc) == Approx(0).epsilon(0).margin(1e-9));  // sums of sin(N theta) over whole periods: rounding
  TrackModel flat;
  flat.map = make_field_map(s.grid, [](double, double) { return 1.0; }, "uniform");
  fit_sector_centre(flat);
  CHECK(flat.sector_centre(3.0, dc) == 0);
}

TEST_CASE("sector windows: a trim coil on sector 1 acts on magnet 1 where the spiral has turned it", "[track][sector]") {
  TrackModel t = model_of(spiral_spec());
  TrimCoil c;
  c.name = "TC";
  c.type = "psi-bfield";
  c.rmin_mm = 1900;
  c.rmax_mm = 4800;
  c.bmax_T = 1e-3;
  c.coefnum = {1.0};  // a flat shape: only the window decides
  c.sectors = {1};
  t.coils.emplace_back(c, 8);
  t.sector_windows = true;
  double dc;
  const double r = 4.5, centre = t.sector_centre(r, dc);
  REQUIRE(centre / kDeg > 9);  // the magnet has turned by about 10 deg here
  auto coil_field = [&](double th_deg) {
    FieldSample with, without;
    REQUIRE(t.field(r, th_deg * kDeg, with));
    REQUIRE(t.map.sample(r, th_deg * kDeg, without));
    return with.bz_T - without.bz_T;
  };
  // 20 deg past magnet 1's centre is still magnet 1's window (a fixed window at 22.5 deg would
  // have cut it there); the next magnet's centre is not.
  CHECK(coil_field(centre / kDeg + 20) == Approx(1e-3).epsilon(1e-9));
  CHECK(coil_field(centre / kDeg - 20) == Approx(1e-3).epsilon(1e-9));
  CHECK(coil_field(centre / kDeg + 45) == 0);
  CHECK(coil_field(centre / kDeg - 25) == 0);
}
