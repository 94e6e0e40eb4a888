// Trim coils of type "table" read from CSV (man 5 turnfit-machine, trimcoils[]: "CSV profile
// r_mm,b_shape"; man 1 turnfit-track, Trim coils: "interpolated by a monotone cubic, zero outside
// the table and outside [rmin, rmax]"), against the analytic coil they sample (issue 14 item 5).
//
// The reference is a Lorentzian psi-bfield coil, L(r) = 1 / (1 + ((r - rc)/w)^2), whose derivative
// bounds are analytic: max |L''| = 2/w^2 and max |L''''| = 24/w^4 (both at r = rc).
//
// Error bound of the table (derived here, not fitted to the result): the interpolant is a cubic
// Hermite curve through the samples with Fritsch-Carlson slopes m_i, the harmonic mean of the
// neighbouring secants d_{i-1}, d_i (0 where they differ in sign; a secant at the ends). A secant
// over [x_i, x_i + h] differs from f'(x_i) by at most h max|f''| / 2, a harmonic mean of two
// numbers of one sign lies between them, and when they differ in sign f'(x_i) lies between them,
// so |m_i - f'(x_i)| <= h M2 / 2. The Hermite curve with exact slopes is within h^4 M4 / 384 of f;
// slope errors e_i add h (H10(t) e_i + H11(t) e_{i+1}) with |H10| + |H11| = t (1 - t) <= 1/4, so
//   |table(r) - f(r)| <= h^2 M2 / 8 + h^4 M4 / 384,
// and, for the slope (|H10'| + |H11'| <= 1, the exact-slope Hermite derivative error is at most
// sqrt(3) h^3 M4 / 216), |table'(r) - f'(r)| <= h M2 / 2 + sqrt(3) h^3 M4 / 216.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <vector>

#include <nlohmann/json.hpp>

#include "../support.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

using namespace turnfit;

namespace {

constexpr double kRc = 0.46, kW = 0.05;  // Lorentzian centre and half width [m]
constexpr double kRmin_mm = 330, kRmax_mm = 590;

double lorentz(double r_m) {
  const double u = (r_m - kRc) / kW;
  return 1 / (1 + u * u);
}

/// The psi-bfield description of the Lorentzian: f/g = 1 / (1 + 400 s^2), s = r - rc in metres.
TrimCoil rational_coil() {
  TrimCoil c;
  c.name = "TCR";
  c.type = "psi-bfield";
  c.rmin_mm = kRmin_mm;
  c.rmax_mm = kRmax_mm;
  c.coef_origin_mm = kRc * 1e3;
  c.coefnum = {1.0};
  c.coefdenom = {1.0, 0.0, 1 / (kW * kW)};
  return c;
}

/// Writes the Lorentzian sampled every h_mm over [rmin, rmax] as r_mm,b_shape (17 digits).
std::string write_table(const test::TempDir& dir, const std::string& name, double h_mm) {
  std::ostringstream s;
  s << "# the Lorentzian 1/(1 + ((r - 460 mm)/50 mm)^2)\nr_mm,b_shape\n";
  const int n = static_cast<int>(std::lround((kRmax_mm - kRmin_mm) / h_mm));
  char line[96];
  for (int i = 0; i <= n; ++i) {
    const double r_mm = kRmin_mm + i * h_mm;
    std::snprintf(line, sizeof line, "%.17g,%.17g\n", r_mm, lorentz(r_mm * 1e-3));
    s << line;
  }
  return dir.file(name, s.str());
}

double value_bound(double h_m) {
  const double m2 = 2 / (kW * kW), m4 = 24 / std::pow(kW, 4);
  return h_m * h_m * m2 / 8 + std::pow(h_m, 4) * m4 / 384;
}
double slope_bound(double h_m) {
  const double m2 = 2 / (kW * kW), m4 = 24 / std::pow(kW, 4);
  return h_m * m2 / 2 + std::sqrt(3.0) * std::pow(h_m, 3) * m4 / 216;
}

}  // namespace

TEST_CASE("trimcoil table: a CSV table of a rational coil gives its shape within the interpolation bound",
          "[trimcoil][table]") {
  test::TempDir dir;
  const TrimCoilField exact(rational_coil(), 4);
  for (double h_mm : {5.0, 2.0}) {
    TrimCoil t;
    t.name = "TCT";
    t.type = "table";
    t.rmin_mm = kRmin_mm;
    t.rmax_mm = kRmax_mm;
    t.table = write_table(dir, "tc" + std::to_string(static_cast<int>(h_mm)) + ".csv", h_mm);
    const TrimCoilField table(t, 4);
    double worst_v = 0, worst_d = 0;
    for (double r_mm = kRmin_mm; r_mm <= kRmax_mm; r_mm += 0.05) {
      double sv, sd, ev, ed;
      table.shape(r_mm * 1e-3, sv, sd);
      exact.shape_exact(r_mm * 1e-3, ev, ed);
      worst_v = std::max(worst_v, std::fabs(sv - ev));
      worst_d = std::max(worst_d, std::fabs(sd - ed));
    }
    INFO("h = " << h_mm << " mm: max |shape error| " << worst_v << " (bound " << value_bound(h_mm * 1e-3)
                << "), max |slope error| " << worst_d << " /m (bound " << slope_bound(h_mm * 1e-3) << ")");
    CHECK(worst_v <= value_bound(h_mm * 1e-3));
    CHECK(worst_d <= slope_bound(h_mm * 1e-3));
    // The samples themselves are reproduced (an interpolant passes through its nodes; the CSV holds
    // 17 digits), and the monotone cubic does not overshoot the largest sample (1 at rc, a node).
    for (double r_mm : {kRmin_mm, 400.0, 460.0, 530.0, kRmax_mm}) {
      double sv, sd;
      table.shape(r_mm * 1e-3, sv, sd);
      CHECK(sv == Approx(lorentz(r_mm * 1e-3)).epsilon(1e-15));
    }
    double peak = 0;
    for (double r_mm = 455; r_mm <= 465; r_mm += 0.01) {
      double sv, sd;
      table.shape(r_mm * 1e-3, sv, sd);
      peak = std::max(peak, sv);
    }
    CHECK(peak <= 1.0);
    // Zero outside [rmin, rmax] (and outside the table, which spans exactly that).
    for (double r_mm : {kRmin_mm - 0.01, 100.0, kRmax_mm + 0.01, 900.0}) {
      double sv = 1, sd = 1;
      table.shape(r_mm * 1e-3, sv, sd);
      CHECK(sv == 0);
      CHECK(sd == 0);
    }
  }
}

TEST_CASE("trimcoil table: a table coil in a machine file tracks like the rational coil it samples",
          "[trimcoil][table][track]") {
  // The uniform 1 T test map (10 MeV proton circle at R = p/(qB) = 458.155 mm, tests/data/machine/
  // track/circle.json's setup) with one trim coil of bmax = 10 mT: the Lorentzian as a psi-bfield
  // coil, or as a table sampled every 2 mm (written beside the machine, named relative to it).
  //
  // Bound on the turn radii (first order in the field difference): the two fields differ by
  // dB(r) with |dB| <= bmax * value_bound(h) (above). A field change dB moves the closed orbit by
  // r dB / (B nu_r^2) at most, and a particle started at the same point oscillates about the
  // moved orbit, so its radius differs by at most twice that. Here B >= 1 T and nu_r^2 = 1 - n
  // with n = -(r/B) dB/dr <= R bmax max|L'| / B = 0.46 * 0.01 * (3 sqrt(3)/8)/0.05 = 0.06.
  test::TempDir dir;
  const double h_mm = 2.0;
  write_table(dir, "tc.csv", h_mm);
  auto machine = [&](const nlohmann::json& coil) {
    nlohmann::json m = {
        {"format", "turnfit-machine/1"},
        {"particle", {{"species", "proton"}}},
        {"field", {{"map", test::test_file("machine/track/uniform_1T.map")}, {"format", "turnfit"}}},
        {"probes", nlohmann::json::array({{{"name", "X90"}, {"phi_deg", 90.0}, {"s_min_mm", 300.0}, {"s_max_mm", 700.0}}})},
        {"injection", {{"energy_MeV", 10.0}, {"r_mm", 458.1553757766}, {"phi_deg", 0.0}}},
        {"tracking", {{"turns", 20}}},
        {"trimcoils", nlohmann::json::array({coil})}};
    return m;
  };
  nlohmann::json rational = {{"name", "TC1"},        {"type", "psi-bfield"},   {"rmin_mm", kRmin_mm},
                             {"rmax_mm", kRmax_mm},  {"bmax_T", 0.01},          {"coef_origin_mm", kRc * 1e3},
                             {"coefnum", {1.0}},     {"coefdenom", {1.0, 0.0, 1 / (kW * kW)}}};
  nlohmann::json table = {{"name", "TC1"},       {"type", "table"}, {"rmin_mm", kRmin_mm},
                          {"rmax_mm", kRmax_mm}, {"bmax_T", 0.01},  {"table", "tc.csv"}};
  std::ofstream(dir.path + "/rational.json") << machine(rational).dump(1);
  std::ofstream(dir.path + "/table.json") << machine(table).dump(1);
  std::vector<std::vector<TurnRecord>> runs;
  for (const char* name : {"/rational.json", "/table.json", "/none.json"}) {
    if (std::string(name) == "/none.json") {
      nlohmann::json m = machine(rational);
      m.erase("trimcoils");
      std::ofstream(dir.path + name) << m.dump(1);
    }
    Machine mach = load_machine(dir.path + name);
    TrackModel model = make_track_model(mach);
    TrackSettings st = machine_track_settings(mach);
    std::vector<TurnRecord> turns;
    TrackEnd end = track_particle(model, injection_state(*mach.injection, mach.particle.mass_MeV), st, turns);
    REQUIRE_FALSE(end.lost);
    REQUIRE(turns.size() == 20);
    runs.push_back(turns);
  }
  const double r_m = 0.4582, bmax = 0.01, b_min = 1.0, nu2 = 1 - 0.06;
  const double bound_mm = 2 * r_m * bmax * value_bound(h_mm * 1e-3) / (b_min * nu2) * 1e3;
  double worst = 0, coil_effect = 0;
  for (size_t i = 0; i < 20; ++i) {
    worst = std::max(worst, std::fabs(runs[1][i].r_mm - runs[0][i].r_mm));
    coil_effect = std::max(coil_effect, std::fabs(runs[2][i].r_mm - runs[0][i].r_mm));
  }
  INFO("table vs rational: max |dr| " << worst << " mm (bound " << bound_mm << " mm); the coil itself moves turns by "
                                       << coil_effect << " mm");
  CHECK(worst <= bound_mm);
  // The coil acts (a table read as zero would agree with nothing here): 10 mT on 1 T moves the
  // orbit by about r dB/B = 4.6 mm, so the turns oscillate over up to twice that.
  CHECK(coil_effect > 100 * bound_mm);
}
