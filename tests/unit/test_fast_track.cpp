// The fast tracking paths of issue 17 against the reference: the group stepper (particles
// stepped together, the main field from the map's row table) against the reference stepper
// (one particle, every sample through TrackModel::field), the row table against the spline's
// own sample, and coils summed per window against the same coils one by one.
//
// Bounds: the fast paths evaluate the same expressions in the same order; what differs is the
// azimuth a stage samples (the row table's offsets c_s cells against the unwrapped azimuth's
// rounding, a few 1e-12 of a cell after 190 turns) and, for window sums, the summed table
// (each coil's table within 1e-7 of its peak, test_coil_sum.cpp). Both are far below the
// 1e-6 mm the issue asks of a fast path; the cases check 1e-6 mm for tracks and 1e-12 T for
// samples, and the group stepper bit for bit against itself alone.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "../support.hpp"
#include "../track_support.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;

namespace {

std::string ring8(const std::string& file) { return std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/" + file; }

/// ring8's hidden truth as synth runs it: its effects, and the coils of truth-dvars.json.
Machine ring8_truth() {
  Machine m = load_machine(ring8("truth-machine.json"));
  apply_dvars_file(m, ring8("truth-dvars.json"));
  return m;
}

/// Largest |dr| of two record lists of the same crossings; fails if the crossings differ.
double worst_dr(const std::vector<TurnRecord>& a, const std::vector<TurnRecord>& b) {
  REQUIRE(a.size() == b.size());
  double w = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    REQUIRE(a[i].probe == b[i].probe);
    REQUIRE(a[i].turn == b[i].turn);
    w = std::max(w, std::fabs(a[i].r_mm - b[i].r_mm));
    w = std::max(w, std::fabs(a[i].t_ns - b[i].t_ns) * 1e-3);  // 1 fs counts as 1e-6 mm here
  }
  return w;
}

/// The default path and the reference stepper on one machine: crossings, kicks, path and end.
void check_against_reference(const Machine& m, const TrackModel& model, double turns) {
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  TrackSettings fast = machine_track_settings(m);
  fast.turns = turns;
  TrackSettings ref = fast;
  ref.reference_stepper = true;
  std::vector<TurnRecord> a, b;
  std::vector<KickRecord> ka, kb;
  std::vector<PathPoint> pa, pb;
  const TrackEnd ea = track_particle(model, s0, ref, a, &ka, &pa);
  const TrackEnd eb = track_particle(model, s0, fast, b, &kb, &pb);
  REQUIRE(a.size() > turns / 2);
  CHECK(worst_dr(a, b) < 1e-6);
  REQUIRE(ka.size() == kb.size());
  double dde = 0;
  for (size_t i = 0; i < ka.size(); ++i) dde = std::max(dde, std::fabs(ka[i].kick.de_MeV - kb[i].kick.de_MeV));
  CHECK(dde < 1e-9);
  // The same steps: one path point each, at the same azimuths.
  REQUIRE(pa.size() == pb.size());
  double dth = 0;
  for (size_t i = 0; i < pa.size(); ++i) dth = std::max(dth, std::fabs(pa[i].theta_deg - pb[i].theta_deg));
  CHECK(dth < 1e-9);
  CHECK(ea.lost == eb.lost);
  CHECK(ea.turns == Approx(eb.turns).epsilon(0).margin(1e-12));
  CHECK(ea.energy_MeV == Approx(eb.energy_MeV).epsilon(1e-10));
}

}  // namespace

TEST_CASE("fast track: the row table gives the spline's own samples at its azimuths", "[track][fast]") {
  const Machine m = load_machine(ring8("machine.json"));
  const TrackModel model = make_track_model(m);
  const PolarFieldMap& map = model.map;
  const std::vector<double> v = {0, 0.6, 0.9, 0.4, 2.0 / 3};
  const auto tab = map.row_table(v);
  REQUIRE(tab);
  CHECK(map.row_table(v) == tab);  // built once, shared
  CHECK_FALSE(map.row_table(v, 1000));  // over the size limit: none
  const PolarGrid& g = map.grid();
  double worst = 0;
  for (int i = 0; i < g.nr - 1; i += 7)
    for (int j = 0; j < g.ntheta; j += 5)
      for (int s = 0; s < static_cast<int>(v.size()); ++s)
        for (double u : {0.0, 0.3, 0.77}) {
          const double r = g.r_min_m() + (i + u) * g.dr_m();
          const double th = g.theta_min_rad() + (j + v[static_cast<size_t>(s)]) * g.dtheta_rad();
          FieldSample a, b;
          REQUIRE(map.sample(r, th, a));
          REQUIRE(map.sample_row(*tab, r, j, s, b));
          worst = std::max({worst, std::fabs(a.bz_T - b.bz_T), std::fabs(a.dbz_dr_T_m - b.dbz_dr_T_m) * g.dr_m(),
                            std::fabs(a.dbz_dth_T - b.dbz_dth_T) * g.dtheta_rad()});
        }
  CHECK(worst < 1e-12);
  FieldSample out;
  CHECK_FALSE(map.sample_row(*tab, g.r_max_m() + 1e-6, 0, 0, out));
  CHECK_FALSE(map.sample_row(*tab, g.r_min_m() - 1e-6, 0, 0, out));
}

TEST_CASE("fast track: a group's lanes sampled together give sample_row_near's numbers bit for bit",
          "[track][fast]") {
  // sample_rows_near takes the lanes still in their cells eight at a time where the processor
  // has AVX-512, against the same call lane by lane (`vector` off: sample_row_near compiled in
  // the same file, without multiply-add contraction). Radii: in the guessed cell, on its lower
  // edge (u = 0) and at its upper edge (u = 1 and just below), a cell off, without a guess, at
  // the map's edges, off the map, NaN; groups of every size up to 16 lanes, so every partial
  // block of eight is met.
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (!__builtin_cpu_supports("avx512f")) WARN("no AVX-512 here: both sides of this test are the scalar path");
#endif
  // ring8's map, and a flutter map whose radii are binary fractions (r_min 1 m, cells of 2^-6 m),
  // where a radius on a cell's upper edge gives u = 1 exactly (on ring8's 20 mm cells it never
  // does), the hit test's boundary.
  const Machine m = load_machine(ring8("machine.json"));
  const TrackModel model = make_track_model(m);
  PolarGrid fine;
  fine.r_min_mm = 1000;
  fine.dr_mm = 15.625;
  fine.nr = 65;
  fine.ntheta = 40;
  fine.symmetry = 8;
  const PolarFieldMap binary = make_field_map(
      fine, [](double r, double th) { return 1.2 + 0.3 * r * r * std::sin(8 * th) - 0.05 * r; }, "binary cells");
  REQUIRE(binary.grid().dr_m() == 0.015625);
  std::mt19937_64 rng(17);
  std::uniform_real_distribution<double> unit(0, 1);
  long compared = 0, mismatched = 0, kept_cell = 0, upper_edge = 0;
  auto same = [](double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; };
  for (int trial = 0; trial < 8000; ++trial) {
    const PolarFieldMap& map = trial % 2 ? binary : model.map;
    const PolarGrid& g = map.grid();
    const auto tab = map.row_table({0, 0.2, 0.3, 0.8, 8.0 / 9, 1.0 / 3});
    REQUIRE(tab);
    const int n = 1 + (trial / 2) % 16;
    const int j = static_cast<int>(rng() % static_cast<unsigned>(g.ntheta));
    const int s = static_cast<int>(rng() % static_cast<unsigned>(tab->nslot));
    double r[16];
    int cell_a[16], cell_b[16];
    for (int l = 0; l < n; ++l) {
      const int i = static_cast<int>(rng() % static_cast<unsigned>(g.nr - 1));
      const unsigned kind = static_cast<unsigned>(rng() % 12);
      const double edge = g.r_min_m() + i * g.dr_m(), next = g.r_min_m() + (i + 1) * g.dr_m();
      r[l] = g.r_min_m() + (i + unit(rng)) * g.dr_m();
      cell_a[l] = i;                                     // kinds 0-5: in the guessed cell
      if (kind == 6) cell_a[l] = i > 0 ? i - 1 : i + 1;  // a cell off
      if (kind == 7) cell_a[l] = -1;                     // no guess
      if (kind == 8) r[l] = unit(rng) < 0.5 ? g.r_min_m() : g.r_max_m();  // the map's edges
      if (kind == 9) {
        const double off[3] = {g.r_min_m() - 1e-3, g.r_max_m() + 1e-3, std::nan("")};
        r[l] = off[rng() % 3];
      }
      if (kind == 10) r[l] = edge;                                         // u = 0
      if (kind == 11) r[l] = unit(rng) < 0.5 ? next : std::nextafter(next, 0.0);  // u = 1, just below
      upper_edge += kind == 11 && cell_a[l] == i && (r[l] - edge) * (1 / g.dr_m()) == 1.0;
      cell_b[l] = cell_a[l];
    }
    double bz[16], br[16], bt[16], bz_b[16], br_b[16], bt_b[16];
    unsigned char good[16], good_b[16];
    std::fill(good, good + 16, 1);
    std::fill(good_b, good_b + 16, 1);
    int before[16];
    std::copy(cell_a, cell_a + n, before);
    map.sample_rows_near(*tab, n, r, j, s, cell_a, bz, br, bt, good);
    map.sample_rows_near(*tab, n, r, j, s, cell_b, bz_b, br_b, bt_b, good_b, false);
    for (int l = 0; l < n; ++l) {
      ++compared;
      kept_cell += before[l] >= 0 && cell_b[l] == before[l] && good_b[l];
      if (!(same(bz[l], bz_b[l]) && same(br[l], br_b[l]) && same(bt[l], bt_b[l])) || cell_a[l] != cell_b[l] ||
          good[l] != good_b[l])
        ++mismatched;
    }
  }
  INFO(compared << " lanes, " << kept_cell << " sampled in the cell they had, " << upper_edge << " at u = 1");
  CHECK(mismatched == 0);
  CHECK(kept_cell > compared / 2);  // the kernel's case is the common one
  CHECK(upper_edge > 100);
}

TEST_CASE("fast track: remainder_two_pi is std::remainder(x, 2 pi) bit for bit", "[track][fast]") {
  std::vector<double> xs = {0.0, -0.0, kPi, -kPi, 3 * kPi, -3 * kPi, 2 * kPi, -2 * kPi, 5 * kPi, 1e300, -1e-300,
                            std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity(),
                            std::nan("")};
  for (double e : {kPi, -kPi, 3 * kPi, -3 * kPi, 2 * kPi, -2 * kPi})
    for (double x = e, y = e; std::fabs(x - e) <= 4 * std::fabs(e) * 1e-16; ) {
      xs.push_back(x = std::nextafter(x, 10.0));
      xs.push_back(y = std::nextafter(y, -10.0));
    }
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> wide(-20, 20), narrow(-1e-6, 1e-6);
  for (int i = 0; i < 200000; ++i) xs.push_back(i % 2 ? wide(rng) : narrow(rng) + (i % 3 - 1) * 2 * kPi);
  long differ = 0;
  for (double x : xs) {
    const double a = remainder_two_pi(x), b = std::remainder(x, 2 * kPi);
    if (!(std::memcmp(&a, &b, sizeof a) == 0 || (std::isnan(a) && std::isnan(b)))) ++differ;
  }
  CHECK(differ == 0);
}

TEST_CASE("fast track: ring8 and its truth, default path against the reference stepper", "[track][fast]") {
  const Machine nominal = load_machine(ring8("machine.json")), truth = ring8_truth();
  check_against_reference(nominal, make_track_model(nominal), 182);
  check_against_reference(truth, make_track_model(truth), 182);
}

TEST_CASE("fast track: the PSI Ring example against the reference stepper", "[track][fast][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  const Machine m = load_machine(std::string(TURNFIT_TEST_DIR) + "/../examples/psi-ring/aeo.json");
  check_against_reference(m, make_track_model(m), 190);
}

TEST_CASE("fast track: steps of other sizes, a fraction of a cell and OPAL's map", "[track][fast]") {
  Machine m = ring8_truth();
  for (double step : {1.0 / 3, 2.0 / 3, 0.1}) {
    INFO("step " << step);
    m.tracking.step_deg = step;
    check_against_reference(m, make_track_model(m), 20);
  }
  m.tracking.step_deg = 0;
  ModelOptions o;
  o.opal_map = true;
  check_against_reference(m, make_track_model(m, o), 20);
}

TEST_CASE("fast track: a group gives each particle what it alone gives, losses included", "[track][fast]") {
  const Machine m = ring8_truth();
  const TrackModel model = make_track_model(m);
  const Injection inj = effective_injection(m);
  TrackSettings st = machine_track_settings(m);
  st.turns = 182;
  // 40 particles (groups of 16, 16 and 8), two of them thrown out of the map early. (The whole
  // 182 turns and several groups: a group once differed from its particles alone by 5e-10 mm,
  // from the harmonic's azimuth terms cached by whichever particle came first.)
  std::vector<BunchOffset> off = gaussian_bunch(*m.bunch, 40, 1);
  off[3].dr_mm = 1500;
  off[37].dE_MeV = 400;
  std::vector<ParticleState> s0;
  for (const auto& o : off) s0.push_back(offset_state(inj, m.particle.mass_MeV, model.rf_MHz, o));
  std::vector<std::vector<TurnRecord>> together(s0.size());
  std::vector<TrackEnd> ends(s0.size());
  track_particles(model, s0.data(), s0.size(), st, together.data(), ends.data());
  int lost = 0;
  for (size_t i = 0; i < s0.size(); ++i) {
    INFO("particle " << i);
    std::vector<TurnRecord> alone, ref;
    const TrackEnd e = track_particle(model, s0[i], st, alone);
    REQUIRE(alone.size() == together[i].size());
    for (size_t k = 0; k < alone.size(); ++k) {
      CHECK(alone[k].r_mm == together[i][k].r_mm);  // bit for bit
      CHECK(alone[k].t_ns == together[i][k].t_ns);
    }
    CHECK(e.status == ends[i].status);
    CHECK(e.turns == ends[i].turns);
    lost += e.lost;
    // And against the reference stepper, losses at the same place.
    TrackSettings rs = st;
    rs.reference_stepper = true;
    const TrackEnd er = track_particle(model, s0[i], rs, ref);
    CHECK(er.lost == e.lost);
    CHECK(er.turns == Approx(e.turns).epsilon(0).margin(1e-9));
    CHECK(worst_dr(ref, alone) < 1e-6);
  }
  CHECK(lost == 2);
}

TEST_CASE("fast track: coils summed per window track as the coils one by one", "[track][fast]") {
  const Machine m = ring8_truth();
  ModelOptions one;
  one.sum_window_coils = false;
  const TrackModel summed = make_track_model(m), single = make_track_model(m, one);
  // ring8's truth puts TC6-TC14 on the odd sectors; TC7, TC10 and TC13 are excited: one
  // window sum of three, no single coil left.
  REQUIRE(summed.window_sums.size() == 1);
  CHECK(summed.window_sums[0].sum.coils() == 3);
  CHECK(single.window_sums.empty());
  CHECK(summed.single_coils.empty());
  CHECK(single.single_coils.size() == 3);
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  TrackSettings st = machine_track_settings(m);
  st.turns = 182;
  std::vector<TurnRecord> a, b;
  track_particle(summed, s0, st, a);
  track_particle(single, s0, st, b);
  CHECK(worst_dr(a, b) < 1e-6);
}

TEST_CASE("fast track: particles with a model each (an optimizer's designs) as each alone", "[track][fast]") {
  // Models made from one read of the files share the map, so their particles go through the
  // grid steps together, each with its own effects, coils, gaps and probes: ring8's truth
  // (harmonic, sector strength, coils on odd sectors, bowed and tilted gaps, a rotated probe),
  // the nominal machine, the nominal machine with a coil and a cavity voltage changed, and two
  // variants of the truth below: lanes whose models differ in which effects they have
  // (TrackModel::add_to_main_models) and in their harmonic's azimuth terms (caches shared only
  // between models with the same terms).
  const Machine nominal = load_machine(ring8("machine.json")), truth = ring8_truth();
  const ModelFiles files = read_model_files(nominal);
  Machine changed = nominal;
  set_dvar(changed, "tc05mb", dvar_value(changed, "tc05mb") + 2e-4);
  set_dvar(changed, "vmaincav2", dvar_value(changed, "vmaincav2") * 1.01);
  // Two more variants of the truth: the harmonic at another phase without the sector strength
  // (other azimuth terms, no scaling), and the sector strength without the harmonic.
  Machine turned = truth, scaled = truth;
  turned.effect_set.field_harmonics[0].phase_deg += 30;
  turned.effect_set.sector_strengths.clear();
  scaled.effect_set.field_harmonics.clear();
  const TrackModel a = make_track_model(truth, {}, &files), b = make_track_model(nominal, {}, &files),
                   c = make_track_model(changed, {}, &files), d = make_track_model(turned, {}, &files),
                   e = make_track_model(scaled, {}, &files);
  REQUIRE(&a.map.values() == &b.map.values());  // one map: the particles are grouped
  REQUIRE(&a.map.values() == &c.map.values());
  REQUIRE(&a.map.values() == &e.map.values());
  const TrackModel* kinds[5] = {&a, &b, &c, &d, &e};
  const Machine* machines[5] = {&truth, &nominal, &changed, &turned, &scaled};
  std::vector<const TrackModel*> models;
  std::vector<ParticleState> s0;
  const std::vector<BunchOffset> off = gaussian_bunch(*nominal.bunch, 20, 3);
  for (size_t i = 0; i < off.size(); ++i) {
    const Machine& m = *machines[i % 5];
    models.push_back(kinds[i % 5]);
    s0.push_back(offset_state(effective_injection(m), m.particle.mass_MeV, models.back()->rf_MHz, off[i]));
  }
  TrackSettings st = machine_track_settings(nominal);
  st.turns = 60;
  std::vector<std::vector<TurnRecord>> together(s0.size());
  std::vector<TrackEnd> ends(s0.size());
  track_particles(models.data(), s0.data(), s0.size(), st, together.data(), ends.data());
  for (size_t i = 0; i < s0.size(); ++i) {
    INFO("particle " << i);
    std::vector<TurnRecord> alone;
    const TrackEnd e = track_particle(*models[i], s0[i], st, alone);
    REQUIRE(alone.size() == together[i].size());
    for (size_t k = 0; k < alone.size(); ++k) {
      CHECK(alone[k].r_mm == together[i][k].r_mm);  // bit for bit
      CHECK(alone[k].t_ns == together[i][k].t_ns);
    }
    CHECK(e.status == ends[i].status);
  }
  // The three models differ where it shows: the same offsets give other turns.
  std::vector<TurnRecord> ta, tb;
  track_particle(a, s0[0], st, ta);
  track_particle(b, s0[0], st, tb);
  REQUIRE(!ta.empty());
  REQUIRE(tb.size() >= ta.size());
  CHECK(std::fabs(ta.back().r_mm - tb[ta.size() - 1].r_mm) > 0.01);
}
