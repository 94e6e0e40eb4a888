// The default machine ring8 (issue 4): isochronism, tunes and resonances, turn count and turn
// separation against the paper's PSI Ring figures, and its two committed map formats.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>

#include "turnfit/field/load.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/field/sector_field.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/orbit/closed_orbit.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;

namespace {
std::string ring8(const std::string& file) { return std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/" + file; }

OrbitSettings settings_of(const Machine& m) {
  OrbitSettings s;
  s.mass_MeV = m.particle.mass_MeV;
  s.charge_e = m.particle.charge_e;
  s.harmonic = m.rf.harmonic;
  s.rf_MHz = m.rf.frequency_MHz;
  return s;
}

std::vector<double> every_MeV(double a, double b) {
  std::vector<double> e;
  for (double x = a; x <= b; x += 1) e.push_back(x);
  return e;
}

// Turn records of one probe, in turn order.
std::vector<TurnRecord> at_probe(const std::vector<TurnRecord>& all, int probe) {
  std::vector<TurnRecord> out;
  for (const auto& t : all)
    if (t.probe == probe) out.push_back(t);
  return out;
}
}  // namespace

TEST_CASE("ring8: isochronous to 1e-5 from 72 to 590 MeV, every MeV", "[ring8]") {
  const Machine m = load_machine(ring8("machine.json"));
  const OrbitSettings s = settings_of(m);
  const std::vector<OrbitRow> rows = orbit_table(load_main_field(m), s, every_MeV(72, 590), 2);
  const double f_target = s.rf_MHz / s.harmonic;
  double worst = 0, worst_slip = 0;
  for (const auto& r : rows) {
    REQUIRE(r.ok());
    worst = std::max(worst, std::fabs(r.f_rev_MHz / f_target - 1));
    worst_slip = std::max(worst_slip, std::fabs(r.phase_slip_deg));
  }
  // README: "below 1e-5 at every MeV from 72 to 590 MeV"; the slip is the same bound in RF phase.
  CHECK(worst < 1e-5);
  CHECK(worst_slip < 360 * 6 * 1e-5);  // 0.0216 deg of RF phase per turn
}

TEST_CASE("ring8: tunes in the PSI Ring's range, no integer or nu_r = 2 nu_z crossing", "[ring8]") {
  const Machine m = load_machine(ring8("machine.json"));
  const std::vector<OrbitRow> rows = orbit_table(load_main_field(m), settings_of(m), every_MeV(72, 590), 2);
  for (const auto& r : rows) {
    REQUIRE(r.ok());
    // PSI Ring (FIXPO, physics.md; our PSI table reaches nu_r 1.71): nu_r 1.1-1.7, nu_z 0.8-0.95.
    // An isochronous field has nu_r ~ gamma, 1.629 at 590 MeV; flutter adds 0.1 at the top.
    CHECK(r.nu_r > 1.1);
    CHECK(r.nu_r < 1.74);
    CHECK(r.nu_z > 0.8);
    CHECK(r.nu_z < 0.95);
    // Walkinshaw (nu_r = 2 nu_z, driven by the nonlinear field) stays at least 0.05 away.
    CHECK(2 * r.nu_z - r.nu_r > 0.05);
  }
  // nu_r rises monotonically through 1.5 (the third-integer 2 nu_r = 3 needs a third field
  // harmonic, absent from an 8-fold field: harmless); no integer is crossed.
  for (size_t i = 1; i < rows.size(); ++i) CHECK(rows[i].nu_r > rows[i - 1].nu_r);
}

TEST_CASE("ring8: 590 MeV after 182 turns, turn separations like the paper's RRI2 and RRL", "[ring8]") {
  const Machine m = load_machine(ring8("machine.json"));
  const TrackModel model = make_track_model(m);
  const ParticleState start = injection_state(*m.injection, m.particle.mass_MeV);
  TrackSettings ts;
  ts.turns = 184;
  std::vector<TurnRecord> turns;
  const TrackEnd end = track_particle(model, start, ts, turns);
  REQUIRE_FALSE(end.lost);
  // Energy at the probe crossings of turns 180 and 184 brackets 590 MeV: 182 +- 2 turns.
  const auto rrl = at_probe(turns, 1);
  const auto rri2 = at_probe(turns, 0);
  REQUIRE(model.probes[0].name == "RRI2");
  REQUIRE(model.probes[1].name == "RRL");
  REQUIRE(rri2.size() == 16);
  REQUIRE(rrl.size() == 174);  // turns 9-182: the probe ends half-way between 182 and 183
  CHECK(rrl.front().turn == 9);
  CHECK(rrl.back().turn == 182);
  CHECK(rrl.back().energy_MeV > 585);
  CHECK(rrl.back().energy_MeV < 590);
  CHECK(end.energy_MeV > 590);  // two more turns past the probe
  // Turn separation at RRI2 within the paper's observed range (Sec. II.B: 18-27 mm): a design
  // envelope for ring8, not an accuracy (ring8 is a different machine; its beam is centred).
  for (size_t i = 1; i < rri2.size(); ++i) {
    CHECK(rri2[i].r_mm - rri2[i - 1].r_mm > 18);
    CHECK(rri2[i].r_mm - rri2[i - 1].r_mm < 27);
  }
}

TEST_CASE("ring8: RRL turn separations as documented (regression)", "[ring8][regression]") {
  // Regression: ring8 only resembles the paper's PSI Ring (RRL 22.9 -> 4.56 mm, 6.09 mm over the
  // last 20 turns), it is not a model of it, so the paper's numbers cannot be a reference with a
  // tolerance. These are ring8's own values as README and bench/RESULTS.md document them: 21.6
  // mm at turn 10, the smallest 5.4 mm, 5.83 mm on average over the last 20 turns. Trusted
  // because the tracker that makes them is tied to OPAL's anchors and to RK4 (test_track.cpp);
  // guards the committed machine (voltages, phases, injection) and the tracker against
  // drifting. Tolerance: half a unit of the documented last digit.
  const Machine m = load_machine(ring8("machine.json"));
  const TrackModel model = make_track_model(m);
  TrackSettings ts;
  ts.turns = 184;
  std::vector<TurnRecord> turns;
  REQUIRE_FALSE(track_particle(model, injection_state(*m.injection, m.particle.mass_MeV), ts, turns).lost);
  REQUIRE(model.probes[1].name == "RRL");
  const auto rrl = at_probe(turns, 1);
  REQUIRE(rrl.size() == 174);
  double last20 = 0, smallest = 1e9;
  for (size_t i = rrl.size() - 20; i < rrl.size(); ++i) last20 += (rrl[i].r_mm - rrl[i - 1].r_mm) / 20;
  for (size_t i = 1; i < rrl.size(); ++i) smallest = std::min(smallest, rrl[i].r_mm - rrl[i - 1].r_mm);
  CHECK(rrl[1].r_mm - rrl[0].r_mm == Approx(21.6).epsilon(0).margin(0.05));
  CHECK(last20 == Approx(5.83).epsilon(0).margin(0.005));
  CHECK(smallest == Approx(5.4).epsilon(0).margin(0.05));
}

TEST_CASE("ring8: the OPAL RING map holds the same field as the turnfit map", "[ring8]") {
  const PolarFieldMap a = read_field_map(ring8("field.map"), MapFormat::turnfit);
  const PolarFieldMap b = read_field_map(ring8("field-ring.dat"), MapFormat::psi_ring);
  REQUIRE(a.values().size() == b.values().size());
  // 1e-8 T: the RING format's fixed-width numbers (kG, 16 characters) round the field there.
  for (size_t i = 0; i < a.values().size(); ++i) CHECK(b.values()[i] == Approx(a.values()[i]).epsilon(0).margin(1e-8));
  // And both are the committed spec, sampled.
  const PolarFieldMap c = make_sector_field(read_sector_spec(ring8("field.json")));
  for (size_t i = 0; i < a.values().size(); i += 97) CHECK(c.values()[i] == a.values()[i]);
}
