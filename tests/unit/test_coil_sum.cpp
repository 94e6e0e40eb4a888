// The summed trim coil table (TrimCoilSum, trimcoil.hpp): the coils acting at every azimuth as
// one radial table, against the same coils evaluated one by one.
//
// Bound (derived, not fitted): each coil's own table is within 1e-7 of its peak |s_i| of its
// formula (tabulate()'s criterion, checked where a Hermite error peaks), and the sum's spacing on
// every piece is at most each coil's own, so each of the two paths is within
// sum_i |bmax_i| 1e-7 peak_i of the exact sum: they differ by at most twice that. Slopes: ten
// times that relative to each coil's peak slope (tabulate()'s slope criterion).
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

using namespace turnfit;

namespace {

std::string ring8(const std::string& file) { return std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/" + file; }

/// ring8 with every trim coil excited, alternating in sign (up to 2 mT, the paper's coils'
/// size), one coil restricted to two sectors so that it stays single.
Machine excited_ring8() {
  Machine m = load_machine(ring8("machine.json"));
  for (size_t i = 0; i < m.trimcoils.size(); ++i)
    m.trimcoils[i].bmax_T = (i % 2 ? -1.0 : 1.0) * 1e-3 * (1 + 0.1 * static_cast<double>(i % 7));
  m.trimcoils.back().sectors = {1, 5};
  return m;
}

/// Largest |s| and |ds/dr| of a coil's formula over [a, b].
void peaks_of(const TrimCoilField& c, double a, double b, double& s_max, double& ds_max) {
  s_max = ds_max = 0;
  for (int k = 0; k <= 20000; ++k) {
    double s, ds;
    c.shape_exact(a + (b - a) * k / 20000.0, s, ds);
    s_max = std::max(s_max, std::fabs(s));
    ds_max = std::max(ds_max, std::fabs(ds));
  }
}

}  // namespace

TEST_CASE("coil sum: ring8's summed coils give the field of the coils one by one within the table bound", "[coil-sum]") {
  const Machine m = excited_ring8();
  TrackModel summed = make_track_model(m);
  TrackModel single = summed;
  single.sum_coils(false);
  REQUIRE(summed.coil_sum.coils() == m.trimcoils.size() - 1);  // all but the sector-restricted one
  REQUIRE(summed.single_coils == std::vector<size_t>{m.trimcoils.size() - 1});
  REQUIRE(single.coil_sum.empty());
  REQUIRE(single.single_coils.size() == m.trimcoils.size());  // all excited

  const double lo = summed.map.grid().r_min_m(), hi = summed.map.grid().r_max_m();
  double bound_b = 0, bound_db = 0;
  for (size_t i = 0; i + 1 < summed.coils.size(); ++i) {
    double s, ds;
    peaks_of(summed.coils[i], lo, hi, s, ds);
    bound_b += 2 * std::fabs(summed.coils[i].coil().bmax_T) * 1e-7 * s;
    bound_db += 2 * std::fabs(summed.coils[i].coil().bmax_T) * 1e-6 * ds;
  }
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> R(lo, hi), T(0, 2 * 3.14159265358979323846);
  double worst_b = 0, worst_db = 0, worst_dth = 0, coil_part = 0;
  for (int k = 0; k < 20000; ++k) {
    const double r = R(rng), th = T(rng);
    FieldSample a, b, main;
    REQUIRE(summed.field(r, th, a));
    REQUIRE(single.field(r, th, b));
    REQUIRE(summed.map.sample(r, th, main));
    worst_b = std::max(worst_b, std::fabs(a.bz_T - b.bz_T));
    worst_db = std::max(worst_db, std::fabs(a.dbz_dr_T_m - b.dbz_dr_T_m));
    worst_dth = std::max(worst_dth, std::fabs(a.dbz_dth_T - b.dbz_dth_T));
    coil_part = std::max(coil_part, std::fabs(b.bz_T - main.bz_T));
  }
  INFO("field " << worst_b << " T (bound " << bound_b << "), dB/dr " << worst_db << " T/m (bound " << bound_db
                << "), dB/dtheta " << worst_dth << ", largest coil field " << coil_part << " T");
  CHECK(coil_part > 1e-3);  // the coils do act: the comparison is not of zeros
  CHECK(worst_b <= bound_b);
  CHECK(worst_db <= bound_db);
  // dB/dtheta comes only from the threshold fall-off: the coil field times dw/dtheta.
  CHECK(worst_dth <= bound_b * 1e3);
}

TEST_CASE("coil sum: ring8 tracked with summed coils gives the turns of the coils one by one", "[coil-sum]") {
  const Machine m = excited_ring8();
  TrackModel summed = make_track_model(m);
  TrackModel single = summed;
  single.sum_coils(false);
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  const TrackSettings st = machine_track_settings(m);
  std::vector<TurnRecord> a, b;
  track_particle(summed, s0, st, a);
  track_particle(single, s0, st, b);
  REQUIRE(a.size() == b.size());
  REQUIRE(a.size() > 150);
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    REQUIRE(a[i].turn == b[i].turn);
    REQUIRE(a[i].probe == b[i].probe);
    worst = std::max(worst, std::fabs(a[i].r_mm - b[i].r_mm));
  }
  // The fields differ by < 4.3e-9 T (the bound above; 4e-9 of the 1.1 T main field), and a turn
  // radius moves by about r dB/B = 4 m x 4e-9 = 1.6e-5 mm per unit of accumulated effect; the
  // bound is that loose because it adds every coil's worst case. 1e-6 mm is what issue 17 asks of
  // any faster field path (measured: 2.5e-9 mm).
  INFO("worst turn difference " << worst << " mm");
  CHECK(worst <= 1e-6);
}

TEST_CASE("coil sum: linear in every coil strength (an optimizer's finite differences see a smooth field)",
          "[coil-sum]") {
  Machine m = excited_ring8();
  TrackModel t0 = make_track_model(m);
  const double lo = t0.map.grid().r_min_m(), hi = t0.map.grid().r_max_m();
  Machine m2 = m;
  m2.trimcoils[3].bmax_T *= 1 + 1e-6;  // the size of a finite-difference step
  TrackModel t1 = make_track_model(m2);
  Machine m3 = m;
  m3.trimcoils[3].bmax_T *= 1 + 2e-6;
  TrackModel t2 = make_track_model(m3);
  REQUIRE(t0.coil_sum.nodes() == t1.coil_sum.nodes());
  REQUIRE(t0.coil_sum.nodes() == t2.coil_sum.nodes());
  double worst = 0, largest = 0;
  for (int k = 0; k <= 5000; ++k) {
    const double r = lo + (hi - lo) * k / 5000.0;
    double b0, b1, b2, d;
    t0.coil_sum.value(r, b0, d);
    t1.coil_sum.value(r, b1, d);
    t2.coil_sum.value(r, b2, d);
    largest = std::max(largest, std::fabs(b1 - b0));
    worst = std::max(worst, std::fabs((b2 - b1) - (b1 - b0)));  // second difference: 0 if linear
  }
  INFO("first difference up to " << largest << " T, second difference up to " << worst << " T");
  CHECK(largest > 0);
  CHECK(worst <= 1e-15);
}

TEST_CASE("coil sum: a kept hint gives value()'s numbers along a particle's radii, across pieces and gaps",
          "[coil-sum]") {
  // ring8's coils, all excited: pieces between their support edges, and radii below and above
  // every support.
  const Machine m = excited_ring8();
  const TrackModel model = make_track_model(m);
  const TrimCoilSum& sum = model.coil_sum;
  REQUIRE(!sum.empty());
  const double lo = model.map.grid().r_min_m() - 0.05, hi = model.map.grid().r_max_m() + 0.05;
  // Walks as a particle's radius moves: small steps, node-sized and piece-sized jumps, both
  // directions, and radii outside every piece. The hint must never change a number.
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> U(0, 1);
  TrimCoilSum::Hint hint;
  double r = lo;
  long nonzero = 0;
  for (int k = 0; k < 200000; ++k) {
    const double size = k % 3 == 0 ? 2e-3 : (k % 3 == 1 ? 2e-5 : 0.2);
    r += size * (U(rng) - 0.45);
    if (r < lo || r > hi) r = lo + (hi - lo) * U(rng);
    double a, da, b, db;
    sum.value_near(r, hint, a, da);
    sum.value(r, b, db);
    nonzero += b != 0;
    REQUIRE(a == b);
    REQUIRE(da == db);
  }
  CHECK(nonzero > 1000);
  // Exactly at piece ends and beside them, from a hint kept elsewhere.
  for (int k = 0; k <= 20000; ++k) {
    const double x = lo + (hi - lo) * k / 20000.0;
    for (double rr : {x, std::nextafter(x, 0.0), std::nextafter(x, 10.0)}) {
      double a, da, b, db;
      sum.value_near(rr, hint, a, da);
      sum.value(rr, b, db);
      REQUIRE(a == b);
      REQUIRE(da == db);
    }
  }
}
