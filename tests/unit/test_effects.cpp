// Machine-file effects (issue 4, "Concealed effects"): validation in the loader, and each
// effect in the tracker against an analytic limit or an exact equivalence, in both integrators.
//
// Most checks run in a uniform field B0, where an orbit is a circle of radius R = p / (q B0)
// and nu_r = 1. Linearizing the azimuth equations (physics.md) about the circle gives, for a
// small field change dB(theta), x'' + x = -R dB / B0 (x = r - R, ' = d/dtheta; Wiedemann,
// Particle Accelerator Physics, ch. 15, "closed orbit distortion" with nu = 1). A first
// harmonic dB = B0 a cos(theta - phi) is resonant there: the particular solution
// x = -(R a / 2) theta sin(theta - phi) grows by -pi R a sin(psi - phi) per turn at a probe at
// azimuth psi, while every other harmonic and the free oscillation repeat turn by turn. In a
// field with index k (B ~ r^k, nu_r^2 = 1 + k) the same harmonic gives the closed orbit
// x = -R a cos(theta - phi) / k instead.
#include <catch2/catch.hpp>
#include <cmath>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "../support.hpp"
#include "../track_support.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/rf/cavity.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;
using nlohmann::json;

namespace {

constexpr double kMass = 938.27208816;  // proton [MeV]
constexpr double kC = kSpeedOfLight;
constexpr double kDeg = kPi / 180;
constexpr double kB0 = 1.0;  // uniform field [T]
constexpr double kR = 2.0;   // orbit radius [m]

/// Kinetic energy [MeV] of a proton on a circle of radius r in a field B: p = q B r.
double energy_on(double B, double r_m) {
  const double p_MeV = B * r_m * kC * 1e-6;
  return std::sqrt(p_MeV * p_MeV + kMass * kMass) - kMass;
}

/// Revolution frequency [MHz] in a uniform field: q B c^2 / (2 pi gamma m c^2).
double f_rev_MHz(double B, double e_MeV) {
  const double gamma = 1 + e_MeV / kMass;
  return B * kC * kC / (2 * kPi * gamma * kMass * 1e6) * 1e-6;
}

/// The uniform model of track_support.hpp with RF at the revolution frequency of the kR
/// circle, so rk4's steps per turn are turns of this particle.
TrackModel uniform(double B = kB0) {
  TrackModel m = test::uniform_model(B, f_rev_MHz(kB0, energy_on(kB0, kR)));
  m.mass_MeV = kMass;
  return m;
}


/// A straight radial gap (pdis 0) at `angle_deg` over [rmin, rmax].
Gap gap(const std::string& name, double angle_deg, double volt_MV, double rmin_mm, double rmax_mm, double rf_MHz,
        double phase_deg = 0, VoltageProfile profile = {}) {
  Cavity c;
  c.name = name;
  c.voltage_MV = volt_MV;
  c.angle_deg = angle_deg;
  c.phase_deg = phase_deg;
  c.rmin_mm = rmin_mm;
  c.rmax_mm = rmax_mm;
  return Gap(c, rf_MHz, std::move(profile));
}

/// Start at azimuth 0, t = 0, radius r, with p_r / p = pr_rel.
ParticleState start(double e_MeV, double r_m, double pr_rel = 0) {
  Injection inj;
  inj.energy_MeV = e_MeV;
  inj.r_mm = r_m * 1e3;
  const double g = 1 + e_MeV / kMass;
  inj.pr_betagamma = pr_rel * std::sqrt(g * g - 1);
  return injection_state(inj, kMass);
}

struct Run {
  std::vector<TurnRecord> turns;
  std::vector<KickRecord> kicks;
  TrackEnd end;
  /// Recorded radii [mm] of one probe, turn by turn.
  std::vector<double> r(int p) const {
    std::vector<double> out;
    for (const auto& t : turns)
      if (t.probe == p) out.push_back(t.r_mm);
    return out;
  }
  std::vector<double> col(int p, double TurnRecord::*f) const {
    std::vector<double> out;
    for (const auto& t : turns)
      if (t.probe == p) out.push_back(t.*f);
    return out;
  }
};

Run track(const TrackModel& m, const ParticleState& s0, const std::string& integ, double turns, int spt = 2880) {
  TrackSettings st;
  st.integrator = integ;
  st.turns = turns;
  st.steps_per_turn = spt;
  Run out;
  out.end = track_particle(m, s0, st, out.turns, &out.kicks);
  return out;
}

/// Least-squares slope of y against its index.
double slope(const std::vector<double>& y) {
  const double n = static_cast<double>(y.size());
  double sx = 0, sy = 0, sxx = 0, sxy = 0;
  for (size_t i = 0; i < y.size(); ++i) {
    const double x = static_cast<double>(i);
    sx += x, sy += y[i], sxx += x * x, sxy += x * y[i];
  }
  return (n * sxy - sx * sy) / (n * sxx - sx * sx);
}

/// A valid machine document to put effects into (the map is never read here).
json machine_doc() {
  return json::parse(R"({
    "format": "turnfit-machine/1",
    "field": {"map": "none.map", "format": "turnfit", "symmetry": 4},
    "rf": {"harmonic": 1, "frequency_MHz": 10},
    "cavities": [{"name": "g1", "voltage_MV": 0.1, "angle_deg": 90, "rmin_mm": 1500, "rmax_mm": 2500}],
    "trimcoils": [{"name": "TC6", "rmin_mm": 1000, "rmax_mm": 3000, "bmax_T": 0.001, "coefnum": [1]},
                  {"name": "TC7", "rmin_mm": 1000, "rmax_mm": 3000, "bmax_T": 0.001, "coefnum": [1]}],
    "probes": [{"name": "P90", "phi_deg": 90, "s_min_mm": 300, "s_max_mm": 3900},
               {"name": "P180", "phi_deg": 180, "s_min_mm": 300, "s_max_mm": 3900}],
    "injection": {"energy_MeV": 100, "r_mm": 2000, "phi_deg": 0}
  })");
}

Machine with_effects(const json& effects, json doc = machine_doc()) {
  doc["effects"] = effects;
  return machine_from_json(doc, "fx.json", "");
}

const char* const kIntegrators[] = {"azimuth", "rk4"};

}  // namespace

// ---------------------------------------------------------------------------------------------
// Loader

TEST_CASE("effects: each type is read with its defaults written back", "[effects][machine]") {
  Machine m = with_effects(json::parse(R"([
    {"type": "field-harmonic", "amplitude_T": 1e-4, "phase_deg": 30, "r_mm": 2000, "width_mm": 300},
    {"type": "harmonic-error", "n": 2, "amplitude_T": -2e-5},
    {"type": "sector-strength", "sector": 3, "relative": 0.002},
    {"type": "trimcoil-sectors", "coils": ["TC6", "TC7"], "sectors": [1, 3]},
    {"type": "gap-bow", "cavity": "g1", "sagitta_mm": 5, "description": "bowed by 5 mm"},
    {"type": "voltage-tilt", "cavity": "g1", "slope": 0.05},
    {"type": "probe-offset", "probe": "P90", "dphi_deg": 0.1, "pivot_s_mm": 3000},
    {"type": "injection-offset", "dr_mm": 3, "dpr_mrad": 1}
  ])"));
  const Effects& fx = m.effect_set;
  REQUIRE(fx.field_harmonics.size() == 2);
  CHECK(fx.field_harmonics[0].n == 1);
  CHECK(fx.field_harmonics[0].width_mm == 300);
  CHECK(fx.field_harmonics[1].n == 2);
  CHECK(fx.field_harmonics[1].width_mm == 0);
  CHECK(fx.field_harmonics[1].index == 1);
  REQUIRE(fx.sector_strengths.size() == 1);
  CHECK(fx.sector_strengths[0].sector == 3);
  REQUIRE(fx.trimcoil_sectors.size() == 1);
  CHECK(fx.trimcoil_sectors[0].sectors == std::vector<int>{1, 3});
  REQUIRE(fx.gap_bows.size() == 1);
  CHECK(fx.gap_bows[0].sagitta_mm == 5);
  REQUIRE(fx.voltage_tilts.size() == 1);
  CHECK(fx.voltage_tilts[0].pivot_rho_n == 0.5);
  REQUIRE(fx.probe_offsets.size() == 1);
  CHECK(fx.probe_offsets[0].pivot_s_mm == 3000);
  CHECK(fx.probe_offsets[0].ds_mm == 0);
  REQUIRE(fx.injection_offset.has_value());
  CHECK(fx.injection_offset->index == 7);
  // Defaults are written back, so a design variable can point at any effect parameter.
  CHECK(m.doc["effects"][5]["pivot_rho_n"] == 0.5);
  CHECK(m.doc["effects"][7]["dE_MeV"] == 0);
  CHECK(m.effects[2]["transition_deg"] == 0);
  apply_sets(m, {"/effects/0/amplitude_T=3e-4"});
  CHECK(m.effect_set.field_harmonics[0].amplitude_T == 3e-4);
  CHECK(with_effects(json::array()).effect_set.empty());
}

TEST_CASE("effects: bad effects are EX_DATAERR naming the file and the JSON path", "[effects][machine]") {
  struct Case {
    const char* effect;
    const char* path;
    const char* text;
  };
  const Case cases[] = {
      {R"({"type": "field-bump", "amplitude_T": 1e-4})", "/effects/0/type", "unknown effect type 'field-bump'"},
      {R"({"type": "field-harmonic", "amplitude_G": 1})", "/effects/0/amplitude_G", "wrong unit: expected 'amplitude_T'"},
      {R"({"type": "field-harmonic", "amplitude": 1})", "/effects/0/amplitude", "missing unit: expected 'amplitude_T'"},
      {R"({"type": "field-harmonic"})", "/effects/0/amplitude_T", "missing required key"},
      {R"({"type": "field-harmonic", "amplitude_T": 2})", "/effects/0/amplitude_T", "must be within [-0.5, 0.5]"},
      {R"({"type": "field-harmonic", "amplitude_T": 1e-4, "n": 1.5})", "/effects/0/n", "expected an integer"},
      {R"({"type": "field-harmonic", "amplitude_T": 1e-4, "n": -1})", "/effects/0/n", "must be in 0..64"},
      {R"({"type": "field-harmonic", "amplitude_T": 1e-4, "r_mm": 2000})", "/effects/0/width_mm", "go together"},
      {R"({"type": "field-harmonic", "amplitude_T": 1e-4, "r_mm": 2000, "width_mm": 0})", "/effects/0/width_mm",
       "must be > 0"},
      {R"({"type": "field-harmonic", "amplitude_T": "big"})", "/effects/0/amplitude_T", "expected a number"},
      {R"({"type": "sector-strength", "sector": 5, "relative": 0.001})", "/effects/0/sector", "sector 5 out of range (1..4)"},
      {R"({"type": "sector-strength", "sector": 1, "relative": 1})", "/effects/0/relative", "a fraction"},
      {R"({"type": "sector-strength", "sector": 1, "relative": 0.001, "transition_deg": 100})",
       "/effects/0/transition_deg", "must be in [0, 90]"},
      {R"({"type": "trimcoil-sectors", "coils": ["TC9"], "sectors": [1]})", "/effects/0/coils/0", "no trim coil named 'TC9'"},
      {R"({"type": "trimcoil-sectors", "coils": ["TC6"], "sectors": [1, 1]})", "/effects/0/sectors/1", "listed twice"},
      {R"({"type": "trimcoil-sectors", "coils": ["TC6"], "sectors": []})", "/effects/0/sectors", "non-empty array"},
      {R"({"type": "gap-bow", "cavity": "g2", "sagitta_mm": 1})", "/effects/0/cavity", "no cavity named 'g2'"},
      {R"({"type": "gap-bow", "cavity": "g1", "sagitta_m": 1})", "/effects/0/sagitta_m", "expected 'sagitta_mm'"},
      {R"({"type": "gap-bow", "cavity": "g1", "sagitta_mm": 150})", "/effects/0/sagitta_mm", "a tenth of the gap length"},
      {R"({"type": "voltage-tilt", "cavity": "g1", "slope": 3})", "/effects/0/slope", "reverses the voltage"},
      {R"({"type": "voltage-tilt", "cavity": "g1", "slope": 0.1, "pivot_rho_n": 2})", "/effects/0/pivot_rho_n",
       "must be in [0, 1]"},
      {R"({"type": "probe-offset", "probe": "RRL", "ds_mm": 1})", "/effects/0/probe", "no probe named 'RRL'"},
      {R"({"type": "probe-offset", "probe": "P90", "dphi_rad": 1})", "/effects/0/dphi_rad", "expected 'dphi_deg'"},
      {R"({"type": "probe-offset", "probe": "P90", "ds_mm": 500})", "/effects/0/ds_mm", "must be within [-200, 200]"},
      {R"({"type": "injection-offset", "dE_MeV": -100})", "/effects/0/dE_MeV", "leaves no kinetic energy"},
      {R"({"type": "injection-offset", "dr_mm": -2000})", "/effects/0/dr_mm", "r <= 0"},
      {R"({"type": "injection-offset", "dpr_mrad": 1000})", "/effects/0/dpr_mrad", "no azimuthal momentum"},
      {R"({"type": "injection-offset", "dr": 1})", "/effects/0/dr", "expected 'dr_mm'"},
      {R"({"type": "injection-offset", "dr_mm": 1, "type2": 1})", "/effects/0/type2", "unknown key"},
      {R"(["gap-bow"])", "/effects/0", "expected a JSON object"},
  };
  for (const auto& c : cases) {
    INFO(c.effect);
    std::string msg;
    const int code = test::error_code([&] { with_effects(json::array({json::parse(c.effect)})); }, &msg);
    CHECK(code == static_cast<int>(ExitCode::data));
    CHECK_THAT(msg, Catch::StartsWith(std::string("fx.json: ") + c.path + ": "));
    CHECK_THAT(msg, Catch::Contains(c.text));
  }
  // Two effects on one element, two injection offsets, a phase offset without RF.
  std::string msg;
  test::error_code([&] { with_effects(json::parse(R"([{"type": "gap-bow", "cavity": "g1", "sagitta_mm": 1},
                                                       {"type": "gap-bow", "cavity": "g1", "sagitta_mm": 2}])")); },
                   &msg);
  CHECK_THAT(msg, Catch::StartsWith("fx.json: /effects/1/cavity: a second gap-bow on cavity 'g1' (the first is "
                                    "/effects/0/cavity)"));
  test::error_code([&] { with_effects(json::parse(R"([{"type": "injection-offset", "dr_mm": 1},
                                                       {"type": "injection-offset", "dr_mm": 2}])")); },
                   &msg);
  CHECK_THAT(msg, Catch::StartsWith("fx.json: /effects/1: a second injection-offset"));
  json no_rf = machine_doc();
  no_rf.erase("rf");
  test::error_code([&] { with_effects(json::parse(R"([{"type": "injection-offset", "dphase_deg": 5}])"), no_rf); },
                   &msg);
  CHECK_THAT(msg, Catch::StartsWith("fx.json: /effects/0/dphase_deg: a phase offset needs an RF frequency"));
  json no_inj = machine_doc();
  no_inj.erase("injection");
  test::error_code([&] { with_effects(json::parse(R"([{"type": "injection-offset", "dr_mm": 1}])"), no_inj); }, &msg);
  CHECK_THAT(msg, Catch::StartsWith("fx.json: /effects/0: injection-offset needs the machine's injection block"));
  // The sector count from the map: checked when the model is built.
  json no_sym = machine_doc();
  no_sym["field"].erase("symmetry");
  Machine m = with_effects(json::parse(R"([{"type": "sector-strength", "sector": 6, "relative": 0.001}])"), no_sym);
  TrackModel model = uniform();
  test::error_code([&] { apply_effects(model, m.effect_set, "fx.json"); }, &msg);
  CHECK(msg == "fx.json: /effects/0/sector: sector 6 out of range (1..4, the field map's sector count)");
}

// ---------------------------------------------------------------------------------------------
// All effects at once, switched off: the same numbers as no effects.

TEST_CASE("effects: zero-size effects give identical tracks", "[effects][track]") {
  const double e0 = energy_on(kB0, kR);
  TrackModel base = uniform();
  base.coils.emplace_back(TrimCoil{"TC6", "psi-bfield", 1000, 3000, 1e-3, {1}, {}, 0, "", {}, 0, 360}, 4);
  base.coils.emplace_back(TrimCoil{"TC7", "psi-bfield", 1000, 3000, 5e-4, {1}, {}, 0, "", {}, 0, 360}, 4);
  for (auto& c : base.coils) c.tabulate(0.2, 4.0);  // as apply_effects rebuilds them
  base.gaps.push_back(gap("g1", 90, 0.2, 1500, 2500, base.rf_MHz, 100, VoltageProfile::parse("2\n0 0.8 0.4\n1 1.2 0.4\n", "p")));
  base.probes = {test::probe("P90", 90), test::probe("P180", 180)};
  Machine m = with_effects(json::parse(R"([
    {"type": "field-harmonic", "amplitude_T": 0, "phase_deg": 30, "r_mm": 2000, "width_mm": 300},
    {"type": "sector-strength", "sector": 3, "relative": 0},
    {"type": "trimcoil-sectors", "coils": ["TC6", "TC7"], "sectors": [1, 2, 3, 4]},
    {"type": "gap-bow", "cavity": "g1", "sagitta_mm": 0},
    {"type": "voltage-tilt", "cavity": "g1", "slope": 0},
    {"type": "probe-offset", "probe": "P90"}
  ])"));
  TrackModel fx = base;
  apply_effects(fx, m.effect_set, "fx.json");
  REQUIRE(fx.effects.active);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run a = track(base, start(e0, kR), integ, 6.3), b = track(fx, start(e0, kR), integ, 6.3);
    REQUIRE(a.turns.size() == 13);
    REQUIRE(b.turns.size() == a.turns.size());
    for (size_t i = 0; i < a.turns.size(); ++i) {
      CHECK(b.turns[i].r_mm == a.turns[i].r_mm);
      CHECK(b.turns[i].t_ns == a.turns[i].t_ns);
      CHECK(b.turns[i].energy_MeV == a.turns[i].energy_MeV);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// field-harmonic and sector-strength: the field, its derivatives, and orbits.

TEST_CASE("effects: field derivatives match finite differences of the field", "[effects][field]") {
  // A radial-Gaussian second harmonic and two stronger sectors on top of a uniform field and a
  // trim coil: dB/dr and dB/dtheta feed the off-midplane field (physics.md, Br = z dBz/dr).
  TrackModel m = uniform();
  Machine mach = with_effects(json::parse(R"([
    {"type": "field-harmonic", "n": 2, "amplitude_T": 3e-3, "phase_deg": 20, "r_mm": 2100, "width_mm": 150},
    {"type": "field-harmonic", "n": 1, "amplitude_T": 1e-3, "phase_deg": -70},
    {"type": "sector-strength", "sector": 2, "relative": 0.01},
    {"type": "sector-strength", "sector": 3, "relative": -0.004}
  ])"));
  apply_effects(m, mach.effect_set, "fx.json");
  const double hr = 1e-6, ht = 1e-7;
  for (double r : {1.9, 2.05, 2.3})
    for (double th_deg : {10.0, 40.0, 45.0, 50.0, 88.0, 130.0, 139.0, 181.0, 225.5, 300.0, -44.0}) {
      INFO("r " << r << " theta " << th_deg);
      const double th = th_deg * kDeg;
      FieldSample f, rp, rm, tp, tm;
      REQUIRE(m.field(r, th, f));
      REQUIRE(m.field(r + hr, th, rp));
      REQUIRE(m.field(r - hr, th, rm));
      REQUIRE(m.field(r, th + ht, tp));
      REQUIRE(m.field(r, th - ht, tm));
      // Central differences: rounding error ~ 2 eps |B| / (2 h) = 2e-10 T/m (hr = 1e-6 m) and
      // 2e-9 T/rad (ht = 1e-7 rad) at |B| ~ 1 T; truncation h^2 |B'''| / 6 < 1e-11 for these
      // smooth harmonics (widths >= 0.15 m, >= 0.2 rad). 1e-8 is 5 times the larger bound.
      CHECK(f.dbz_dr_T_m == Approx((rp.bz_T - rm.bz_T) / (2 * hr)).epsilon(0).margin(1e-8));
      CHECK(f.dbz_dth_T == Approx((tp.bz_T - tm.bz_T) / (2 * ht)).epsilon(0).margin(1e-8));
    }
  // Spot values: the harmonic's phase and the Gaussian's centre and width.
  TrackModel h = uniform();
  apply_effects(h, with_effects(json::parse(R"([{"type": "field-harmonic", "n": 3, "amplitude_T": 0.01,
                                                 "phase_deg": 20, "r_mm": 2000, "width_mm": 100}])")).effect_set);
  FieldSample f;
  REQUIRE(h.field(2.0, 20 * kDeg, f));
  CHECK(f.bz_T == Approx(kB0 + 0.01).epsilon(1e-12));
  REQUIRE(h.field(2.1, 20 * kDeg + kPi / 3, f));
  CHECK(f.bz_T == Approx(kB0 - 0.01 * std::exp(-0.5)).epsilon(1e-12));
}

TEST_CASE("effects: a first harmonic in a uniform field grows the coherent amplitude by pi R a per turn",
          "[effects][field][physics]") {
  // nu_r = 1: x_k = c - pi R a sin(psi - phi) k at a probe at azimuth psi (file header).
  const double A = 2e-5, a = A / kB0, e0 = energy_on(kB0, kR);
  const double growth_mm = kPi * kR * a * 1e3;  // 0.126 mm per turn
  for (double phi : {0.0, 90.0}) {
    TrackModel m = uniform();
    m.probes = {test::probe("P90", 90), test::probe("P180", 180)};
    json e = {{"type", "field-harmonic"}, {"amplitude_T", A}, {"phase_deg", phi}};
    apply_effects(m, with_effects(json::array({e})).effect_set);
    for (const char* integ : kIntegrators) {
      INFO(integ << ", phase " << phi);
      const Run run = track(m, start(e0, kR), integ, 20.1);
      for (int p = 0; p < 2; ++p) {
        const double psi = p == 0 ? 90 : 180;
        const std::vector<double> r = run.r(p);
        REQUIRE(r.size() == 20);
        const double expected = -growth_mm * std::sin((psi - phi) * kDeg);
        INFO("probe at " << psi << ": slope " << slope(r) << " mm/turn, expected " << expected);
        // The linear theory drops terms of relative size x / R: the amplitude reaches
        // 20 x 0.126 mm = 2.5 mm, 1.3e-3 of R at the last turn (6e-4 on average over the fit).
        CHECK(slope(r) == Approx(expected).epsilon(0).margin(0.001 * growth_mm));
      }
    }
  }
}

TEST_CASE("effects: a first harmonic bump with nu_r^2 = 1 + k displaces the closed orbit by R a / k",
          "[effects][field][physics]") {
  // B = B0 (r / R)^k with k = 0.5; a Gaussian bump centred on the orbit (width 300 mm), so
  // a = A / B0 there. The particle starts on the predicted closed orbit x(0) = -R a / k, x' = 0,
  // and must stay on it: x(90) = 0, x(180) = +R a / k, x(270) = 0 on every turn (a wrong shift
  // would show as a free oscillation of the difference, 4 mm here).
  const double k = 0.5, A = 1e-3, a = A / kB0, e0 = energy_on(kB0, kR);
  const double shift_mm = kR * a / k * 1e3;  // 4 mm
  TrackModel m = uniform();
  PolarGrid g = m.map.grid();
  m.map = make_field_map(g, [&](double r, double) { return kB0 * std::pow(r / kR, k); }, "power law");
  m.probes = {test::probe("P90", 90), test::probe("P180", 180), test::probe("P270", 270)};
  apply_effects(m, with_effects(json::parse(R"([{"type": "field-harmonic", "amplitude_T": 1e-3, "phase_deg": 0,
                                                 "r_mm": 2000, "width_mm": 300}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run run = track(m, start(e0, kR - shift_mm * 1e-3), integ, 30.1);
    const double expected[3] = {kR * 1e3, kR * 1e3 + shift_mm, kR * 1e3};
    for (int p = 0; p < 3; ++p) {
      const std::vector<double> r = run.r(p);
      REQUIRE(r.size() == 30);
      for (size_t t = 0; t < r.size(); ++t) {
        INFO("probe " << p << " turn " << t + 1);
        // The linear theory drops second-order terms of size x^2 / R = (4 mm)^2 / 2 m = 0.008
        // mm (the bump's Gaussian changes by (4 / 300)^2 / 2 = 1e-4 over the excursion).
        CHECK(r[t] == Approx(expected[p]).epsilon(0).margin(0.01));
      }
    }
  }
}

TEST_CASE("effects: the same sector-strength on every sector is the scaled field", "[effects][field]") {
  const double eps = 0.003, e0 = energy_on(kB0, kR);
  TrackModel scaled = uniform(kB0 * (1 + eps)), fx = uniform();
  for (TrackModel* m : {&scaled, &fx}) m->probes = {test::probe("P90", 90), test::probe("P200", 200)};
  json list = json::array();
  for (int s = 1; s <= 4; ++s) list.push_back({{"type", "sector-strength"}, {"sector", s}, {"relative", eps}});
  apply_effects(fx, with_effects(list).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run a = track(scaled, start(e0, kR), integ, 10.2), b = track(fx, start(e0, kR), integ, 10.2);
    REQUIRE(a.turns.size() == 20);
    REQUIRE(b.turns.size() == 20);
    // The four sector windows sum to 1 up to rounding: the same field, so the same turns up to
    // rounding accumulated over 10 turns (1e-7 mm, 1e-8 ns).
    for (size_t i = 0; i < a.turns.size(); ++i) {
      CHECK(b.turns[i].r_mm == Approx(a.turns[i].r_mm).epsilon(0).margin(1e-7));
      CHECK(b.turns[i].t_ns == Approx(a.turns[i].t_ns).epsilon(0).margin(1e-8));
    }
    // Not vacuous: the stronger field bends to a radius (1 + eps) smaller, 6 mm here.
    CHECK(a.turns.back().r_mm < kR * 1e3 - 5);
  }
}

TEST_CASE("effects: one stronger sector drives the first harmonic of its window", "[effects][field][physics]") {
  // Sector 2 of 4 (centred on 90 deg) stronger by eps: dB / B0 = eps w(theta), w the sector's
  // window: a 90 deg box smoothed by the switch kernel S'(x / h) / h (half width h = 11.25 deg,
  // the default quarter pitch). Its first harmonic about 90 deg is
  // a1 = (2 / pi) sin(45 deg) K(1), K(1) = int S'(x) cos(h x) dx over [-1, 1]; at nu_r = 1 it grows
  // the coherent amplitude by -pi R eps a1 sin(psi - 90 deg) per turn at a probe at psi.
  const double eps = 1e-4, e0 = energy_on(kB0, kR), h = 11.25 * kDeg;
  double K = 0;
  const int n = 2000;
  for (int i = 0; i <= n; ++i) {  // Simpson's rule
    const double x = -1 + 2.0 * i / n, t = 0.5 * (x + 1);
    const double f = 15 * t * t * (1 - t) * (1 - t) * std::cos(h * x);
    K += f * (i == 0 || i == n ? 1 : i % 2 ? 4 : 2);
  }
  K *= 2.0 / n / 3;
  const double a1 = 2 / kPi * std::sin(kPi / 4) * K;
  const double growth_mm = kPi * kR * eps * a1 * 1e3;
  TrackModel m = uniform();
  m.probes = {test::probe("P90", 90), test::probe("P180", 180), test::probe("P0", 0)};
  apply_effects(m, with_effects(json::parse(R"([{"type": "sector-strength", "sector": 2, "relative": 1e-4}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run run = track(m, start(e0, kR), integ, 16.5);
    const double psi[3] = {90, 180, 0};
    for (int p = 0; p < 3; ++p) {
      const std::vector<double> r = run.r(p);
      REQUIRE(r.size() >= 16);
      const double expected = -growth_mm * std::sin((psi[p] - 90) * kDeg);
      INFO("probe at " << psi[p] << ": slope " << slope(r) << " mm/turn, expected " << expected);
      // Linear theory: neglected terms of relative size x / R, the amplitude reaching 16 x 0.28
      // mm = 4.5 mm, 2.2e-3 of R at the last turn (about 1e-3 on average over the fit).
      CHECK(slope(r) == Approx(expected).epsilon(0).margin(0.002 * growth_mm));
    }
  }
}

// ---------------------------------------------------------------------------------------------
// trimcoil-sectors

TEST_CASE("effects: trimcoil-sectors restricts a coil to its sectors", "[effects][trimcoil]") {
  // A flat coil (shape 1 on 1-3 m) of dB = 1e-3 T on sectors 1 and 3 of 4 (half the azimuth):
  // the momentum turns at q B / (gamma m), so one turn takes T = 2 pi gamma m / (q <B>_t), with
  // the time-averaged field <B>_t = B0 + dB / 2 up to O((dB / B0)^2) = 1e-6 (the field has 2-fold
  // symmetry, so the orbit spends half its time in each to first order). On all four sectors,
  // or without the effect: B0 + dB, 5e-4 apart.
  const double dB = 1e-3, e0 = energy_on(kB0, kR);
  const double gamma = 1 + e0 / kMass;
  auto period_ns = [&](double B) { return 2 * kPi * gamma * kMass * 1e6 / (kC * kC * B) * 1e9; };
  TrackModel base = uniform();
  base.coils.emplace_back(TrimCoil{"TC6", "psi-bfield", 1000, 3000, dB, {1}, {}, 0, "", {}, 0, 360}, 4);
  base.probes = {test::probe("P90", 90)};
  TrackModel odd = base, all = base, direct = base;
  apply_effects(odd, with_effects(json::parse(R"([{"type": "trimcoil-sectors", "coils": ["TC6"], "sectors": [1, 3]}])")).effect_set);
  apply_effects(all, with_effects(json::parse(R"([{"type": "trimcoil-sectors", "coils": ["TC6"], "sectors": [4, 3, 2, 1]}])")).effect_set);
  direct.coils[0] = TrimCoilField(TrimCoil{"TC6", "psi-bfield", 1000, 3000, dB, {1}, {}, 0, "", {1, 3}, 0, 360}, 4);
  CHECK_FALSE(odd.effects.active);  // a coil effect leaves the field path alone
  for (const char* integ : kIntegrators) {
    INFO(integ);
    auto period = [&](const TrackModel& m) {
      const Run run = track(m, start(e0, kR), integ, 40.2);
      const std::vector<double> t = run.col(0, &TurnRecord::t_ns);
      REQUIRE(t.size() == 40);
      return (t.back() - t.front()) / 39;
    };
    const double t_odd = period(odd);
    CHECK(t_odd == Approx(period_ns(kB0 + dB / 2)).epsilon(1e-6));
    CHECK(period(all) == Approx(period_ns(kB0 + dB)).epsilon(1e-6));
    CHECK(period(base) == Approx(period_ns(kB0 + dB)).epsilon(1e-6));
    CHECK(period(direct) == Approx(t_odd).epsilon(1e-12));
  }
}

// ---------------------------------------------------------------------------------------------
// gap-bow

TEST_CASE("effects: a bowed gap is crossed sagitta / r later at its middle, in both integrators",
          "[effects][rf]") {
  // A radial gap at 90 deg over 1.5-2.5 m (middle at the orbit radius 2 m), no voltage: the
  // circle meets the bowed line at psi with R sin(psi) + s (1 - u^2) = 0, u ~ 1e-5, so the
  // crossing moves from 90 deg by asin(s / R).
  const double e0 = energy_on(kB0, kR), sag_mm = 5;
  for (double sag : {sag_mm, -sag_mm}) {
    TrackModel m = uniform();
    m.gaps.push_back(gap("g1", 90, 0, 1500, 2500, m.rf_MHz));
    TrackModel straight = m;
    json e = {{"type", "gap-bow"}, {"cavity", "g1"}, {"sagitta_mm", sag}};
    json doc = machine_doc();
    apply_effects(m, with_effects(json::array({e}), doc).effect_set);
    const double expected = 90 + std::asin(sag * 1e-3 / kR) / kDeg;
    // Along the chord the crossing is at rho = sqrt(R^2 - s^2) (up to s u^2 ~ 5e-13 m).
    const double rho_n = (std::sqrt(kR * kR - sag * sag * 1e-6) - 1.5) / 1.0;
    for (const char* integ : kIntegrators) {
      INFO(integ << ", sagitta " << sag);
      const Run bowed = track(m, start(e0, kR), integ, 3), flat = track(straight, start(e0, kR), integ, 3);
      REQUIRE(bowed.kicks.size() == 3);
      // turnfit-track(1), "Accuracy and speed": rk4 at 2880 steps per turn is within 0.00011 mm
      // of its 23040-step run, i.e. 0.00011 mm / 2 m = 3e-6 deg along the orbit. The azimuth
      // integrator lands on the gap line; in a uniform field its steps are exact up to rounding
      // (1e-8 deg: 100 eps on 90 deg with margin).
      const double tol = std::string(integ) == "rk4" ? 3e-6 : 1e-8;
      for (const auto& k : bowed.kicks) {
        CHECK(k.kick.active);
        CHECK(k.kick.rho_n == Approx(rho_n).epsilon(0).margin(1e-9));  // d rho / d theta ~ s: tol * 5 mm
        CHECK(k.theta_deg == Approx(expected).epsilon(0).margin(tol));
      }
      for (const auto& k : flat.kicks) CHECK(k.theta_deg == Approx(90).epsilon(0).margin(tol));
    }
  }
}

TEST_CASE("effects: a bowed gap kicks along its local normal", "[effects][rf]") {
  // Chord 1.5-2.5 m at A = 90 deg, sagitta 50 mm: at rho = 2.25 m (u = 0.5) the line's slope is
  // d(bow)/d(rho) = -2 s u / (L / 2) = -0.1. A proton crossing perpendicular to the chord gains
  // 1 MeV on crest; the momentum component along the bowed line's tangent (from two points of
  // the parabola, built here from its definition) is kept, the rest lies along the normal.
  Gap g = gap("g", 90, 1.0, 1500, 2500, 10);
  const double s = 0.05, rho = 2.25, mid = 2.0, half = 0.5;
  g.set_bow(s);
  auto point = [&](double q, double& x, double& y) {  // e_rho = (0, 1), downstream e_n = (-1, 0)
    const double u = (q - mid) / half, n = s * (1 - u * u);
    x = -n;
    y = q;
  };
  double x, y, x1, y1, x2, y2;
  point(rho, x, y);
  CHECK(g.distance(x, y) == Approx(0).margin(1e-15));
  CHECK(g.bow_slope(rho) == Approx(-0.1).epsilon(1e-12));
  point(rho - 1e-6, x1, y1);
  point(rho + 1e-6, x2, y2);
  const double tl = std::hypot(x2 - x1, y2 - y1), tx = (x2 - x1) / tl, ty = (y2 - y1) / tl;
  const double e0 = 100, P0 = kinematics(kMass, 1, e0).betagamma, P1 = kinematics(kMass, 1, e0 + 1).betagamma;
  double px = -P0, py = 0;
  const GapKick k = g.kick(x, y, 0, kMass, 1, GapPhysics::turnfit, px, py, 0);
  REQUIRE(k.active);
  CHECK(k.de_MeV == Approx(1).epsilon(1e-12));
  CHECK(std::hypot(px, py) == Approx(P1).epsilon(1e-12));
  CHECK(px * tx + py * ty == Approx(-P0 * tx).epsilon(1e-9));
  // The straight gap would have left the radial momentum (along e_rho) at 0.
  CHECK(py == Approx(-P0 * tx * ty + std::sqrt(P1 * P1 - P0 * P0 * tx * tx) * tx).epsilon(1e-9));
  CHECK(std::fabs(py) > 1e-4 * P0);
}

TEST_CASE("effects: an accelerating bowed gap gives the same turns in both integrators", "[effects][rf]") {
  // 1 MV, the particle (a centred 2.4 m circle) crossing 400 mm outside the middle of a 40 mm
  // bow over 1.1-2.9 m (slope -0.04 there): the crossing moves by 13 mrad in azimuth and the
  // kick turns by the slope. rk4 at 11520 steps per turn is within 0.00001 mm of its 23040-step
  // run (turnfit-track(1), "Accuracy and speed"), the azimuth integrator exact up to rounding in
  // a uniform field: they agree to 1e-5 mm (the README promises 0.005 mm for azimuth against
  // rk4 on the Ring), and the bow moves the turns by far more than that.
  const double e1 = energy_on(kB0, 2.4);
  TrackModel m = uniform();
  m.gaps.push_back(gap("g1", 90, 1.0, 1100, 2900, m.rf_MHz, 90));
  m.probes = {test::probe("P180", 180), test::probe("P300", 300)};
  TrackModel straight = m;
  apply_effects(m, with_effects(json::parse(R"([{"type": "gap-bow", "cavity": "g1", "sagitta_mm": 40}])")).effect_set);
  const Run az = track(m, start(e1, 2.4), "azimuth", 5.3), rk = track(m, start(e1, 2.4), "rk4", 5.3, 11520);
  const Run flat = track(straight, start(e1, 2.4), "azimuth", 5.3);
  REQUIRE(az.turns.size() == 10);
  REQUIRE(rk.turns.size() == 10);
  double moved = 0;
  for (size_t i = 0; i < az.turns.size(); ++i) {
    CHECK(rk.turns[i].r_mm == Approx(az.turns[i].r_mm).epsilon(0).margin(1e-5));
    moved = std::max(moved, std::fabs(az.turns[i].r_mm - flat.turns[i].r_mm));
  }
  INFO("largest change by the bow " << moved << " mm");
  CHECK(moved > 0.3);
}

// ---------------------------------------------------------------------------------------------
// voltage-tilt

TEST_CASE("effects: a voltage tilt scales the gain by 1 + slope (rho_n - pivot) and tilts the deflection",
          "[effects][rf]") {
  // Profile V_n = 0.9 + 0.3 rho - 0.2 rho^2 (exact in the Hermite table), chord 1.5-2.5 m, so
  // rho = 1.8 m is rho_n = 0.3: V_n = 0.972, dV_n = 0.18. Tilt 0.2 about 0.5: factor 0.96.
  const VoltageProfile prof = VoltageProfile::parse("3\n0 0.9 0.3\n0.5 1.0 0.1\n1 1.0 -0.1\n", "quadratic");
  const double f_MHz = 10, vn = 0.972, dvn = 0.18, slope_t = 0.2, pivot = 0.5, rho_n = 0.3;
  const double factor = 1 + slope_t * (rho_n - pivot);
  Gap flat = gap("g", 90, 1.0, 1500, 2500, f_MHz, 0, prof), tilted = flat;
  tilted.set_tilt(slope_t, pivot);
  const double P0 = kinematics(kMass, 1, 100).betagamma;
  // On crest (t = 0, phase 0): energy gain.
  double px = -P0, py = 0;
  const GapKick a = flat.kick(0, 1.8, 0, kMass, 1, GapPhysics::turnfit, px, py, 0);
  px = -P0, py = 0;
  const GapKick b = tilted.kick(0, 1.8, 0, kMass, 1, GapPhysics::turnfit, px, py, 0);
  CHECK(a.rho_n == Approx(rho_n).epsilon(1e-12));
  CHECK(a.de_MeV == Approx(vn).epsilon(1e-12));
  CHECK(b.de_MeV == Approx(vn * factor).epsilon(1e-12));
  // At phase 90 deg (t = 1 / (4 f)): no gain, deflection -V dV/drho sin(phi) / (omega B rho)
  // with the tilted profile's slope d/drho_n [V_n (1 + s (rho_n - p))] = dV_n factor + V_n s.
  const double t = 1 / (4 * f_MHz * 1e6), omega = 2 * kPi * f_MHz * 1e6;
  px = -P0, py = 0;
  const GapKick c = tilted.kick(0, 1.8, t, kMass, 1, GapPhysics::turnfit, px, py, 0);
  const double brho = kinematics(kMass, 1, 100 + c.de_MeV).brho_Tm;
  const double dv_drho = 1e6 * (dvn * factor + vn * slope_t) / 1.0;
  CHECK(c.deflection_rad == Approx(-dv_drho / (omega * brho)).epsilon(1e-9));
  px = -P0, py = 0;
  const GapKick d = flat.kick(0, 1.8, t, kMass, 1, GapPhysics::turnfit, px, py, 0);
  CHECK(d.deflection_rad == Approx(-1e6 * dvn / (omega * brho)).epsilon(1e-9));
}

TEST_CASE("effects: voltage-tilt in tracking: the gain at the crossing's rho_n, both integrators", "[effects][rf]") {
  // A centred circle of 2.2 m crosses the radial gap (1.5-2.5 m) at rho_n = 0.7.
  const double e1 = energy_on(kB0, 2.2);
  TrackModel m = uniform();
  m.gaps.push_back(gap("g1", 90, 0.1, 1500, 2500, m.rf_MHz, 90));
  TrackModel plain = m;
  apply_effects(m, with_effects(json::parse(R"([{"type": "voltage-tilt", "cavity": "g1", "slope": 0.3,
                                                 "pivot_rho_n": 0.2}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run a = track(plain, start(e1, 2.2), integ, 1), b = track(m, start(e1, 2.2), integ, 1);
    REQUIRE(a.kicks.size() == 1);
    REQUIRE(b.kicks.size() == 1);
    CHECK(a.kicks[0].kick.rho_n == Approx(0.7).epsilon(0).margin(1e-9));
    CHECK(b.kicks[0].kick.de_MeV == Approx(a.kicks[0].kick.de_MeV * (1 + 0.3 * (0.7 - 0.2))).epsilon(1e-9));
  }
}

// ---------------------------------------------------------------------------------------------
// probe-offset

TEST_CASE("effects: probe-offset moves the probe and not its readout", "[effects][probe]") {
  // The readout converts its reading sigma = s - shift to a radius with the machine file's
  // geometry: hypot(sigma + shift, a) - shift. What the probe's own parameters would do is
  // therefore matched exactly where the readout's geometry is unchanged (a turn about the
  // machine centre; a shift along a radial probe), and not for a sideways move.
  const double e0 = energy_on(kB0, kR);
  auto run = [&](const TrackModel& m, const std::string& integ, const ParticleState& s0, double turns) {
    return track(m, s0, integ, turns);
  };
  // Turned about the machine centre: the same as phi_deg + dphi, an offset probe too.
  TrackModel base = uniform();
  base.probes = {test::probe("P90", 90, 40)};
  TrackModel turned = base, fx = base;
  turned.probes[0] = test::probe("P90", 90.7, 40);
  apply_effects(fx, with_effects(json::parse(R"([{"type": "probe-offset", "probe": "P90", "dphi_deg": 0.7}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run a = run(turned, integ, start(e0, kR + 0.3), 4.6), b = run(fx, integ, start(e0, kR + 0.3), 4.6),
              c = run(base, integ, start(e0, kR + 0.3), 4.6);
    REQUIRE(a.turns.size() == 5);
    REQUIRE(b.turns.size() == 5);
    for (size_t i = 0; i < a.turns.size(); ++i) {  // the same probe geometry: exact up to rounding
      CHECK(b.turns[i].r_mm == Approx(a.turns[i].r_mm).epsilon(0).margin(1e-9));
      CHECK(b.turns[i].s_mm == Approx(a.turns[i].s_mm).epsilon(0).margin(1e-9));
      CHECK(b.turns[i].t_ns == Approx(a.turns[i].t_ns).epsilon(0).margin(1e-9));
      CHECK(std::fabs(b.turns[i].r_mm - c.turns[i].r_mm) > 1);  // the off-centre circle
    }
  }
  // ds alone on a radial probe is the probe's own shift: every reading drops by ds.
  TrackModel radial = uniform();
  radial.probes = {test::probe("P90", 90)};
  TrackModel shifted = radial, ds = radial;
  shifted.probes[0].shift_m = -0.004;
  apply_effects(ds, with_effects(json::parse(R"([{"type": "probe-offset", "probe": "P90", "ds_mm": -4}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run s1 = run(shifted, integ, start(e0, kR + 0.3), 4.6), s2 = run(ds, integ, start(e0, kR + 0.3), 4.6),
              s0 = run(radial, integ, start(e0, kR + 0.3), 4.6);
    REQUIRE(s2.turns.size() == 5);
    for (size_t i = 0; i < s1.turns.size(); ++i) {  // exact up to rounding
      CHECK(s2.turns[i].r_mm == Approx(s1.turns[i].r_mm).epsilon(0).margin(1e-9));
      CHECK(s2.turns[i].s_mm == Approx(s1.turns[i].s_mm).epsilon(0).margin(1e-9));
      CHECK(s2.turns[i].r_mm == Approx(s0.turns[i].r_mm + 4).epsilon(0).margin(1e-9));
    }
  }
  // A radial probe moved sideways by da = 30 mm: the centred circle of radius R2 = 2.3 m
  // meets it at s = sqrt(R2^2 - da^2), which the readout, believing a = 0, reports as the
  // radius (1.96 mm low); the probe's own a = 30 mm would have reported R2.
  const double R2 = 2.3, e2 = energy_on(kB0, R2), da = 0.03;
  TrackModel side = radial, side_a = radial;
  side_a.probes[0] = test::probe("P90", 90, 30);
  apply_effects(side, with_effects(json::parse(R"([{"type": "probe-offset", "probe": "P90", "da_mm": 30}])")).effect_set);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    // rk4: turnfit-track(1), "Accuracy and speed": 2880 steps per turn within 0.00011 mm of
    // 23040 steps. azimuth: exact in a uniform field up to rounding (1e-8 mm).
    const double tol = std::string(integ) == "rk4" ? 1e-4 : 1e-8;
    const Run a = run(side, integ, start(e2, R2), 2.6), b = run(side_a, integ, start(e2, R2), 2.6);
    REQUIRE(a.turns.size() == 3);
    REQUIRE(b.turns.size() == 3);
    for (size_t i = 0; i < 3; ++i) {
      CHECK(a.turns[i].r_mm == Approx(std::sqrt(R2 * R2 - da * da) * 1e3).epsilon(0).margin(tol));
      CHECK(b.turns[i].r_mm == Approx(R2 * 1e3).epsilon(0).margin(tol));
    }
  }
  // A radial probe at 90 deg turned by 2 deg about its point Q at s = 2 m: the centred circle
  // of radius R2 = 2.3 m meets the new line at distance d from Q, d^2 + 2 R cos(dphi) d + R^2 -
  // R2^2 = 0 (R = |Q|), and the probe, whose scale turns with it, reads 2000 mm + d (and, radial
  // for its readout, reports that as the radius).
  TrackModel pivot = radial;
  apply_effects(pivot, with_effects(json::parse(R"([{"type": "probe-offset", "probe": "P90", "dphi_deg": 2,
                                                     "pivot_s_mm": 2000}])")).effect_set);
  const double cd = std::cos(2 * kDeg);
  const double d = -2 * cd + std::sqrt(4 * cd * cd - 4 + R2 * R2);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    // rk4: turnfit-track(1), "Accuracy and speed": 2880 steps per turn within 0.00011 mm of
    // 23040 steps. azimuth: exact in a uniform field up to rounding (1e-8 mm).
    const double tol = std::string(integ) == "rk4" ? 1e-4 : 1e-8;
    const Run r = run(pivot, integ, start(e2, R2), 2.6);
    REQUIRE(r.turns.size() == 3);
    for (const auto& t : r.turns) {
      CHECK(t.s_mm == Approx(2000 + d * 1e3).epsilon(0).margin(tol));
      CHECK(t.r_mm == Approx(2000 + d * 1e3).epsilon(0).margin(tol));
    }
  }
}

// ---------------------------------------------------------------------------------------------
// injection-offset

TEST_CASE("effects: injection-offset equals the same change made in injection", "[effects][injection]") {
  Machine fx = with_effects(json::parse(R"([{"type": "injection-offset", "dr_mm": 3, "dpr_mrad": 2, "dz_mm": 1,
                                              "dpz_mrad": -0.5, "dE_MeV": 0.4, "dphase_deg": 9}])"));
  json doc = machine_doc();
  const double P = kinematics(kMass, 1, 100.4).betagamma;
  doc["injection"]["r_mm"] = 2003;
  doc["injection"]["energy_MeV"] = 100.4;
  doc["injection"]["pr_betagamma"] = P * 2e-3;
  doc["injection"]["z_mm"] = 1;
  doc["injection"]["pz_betagamma"] = -P * 0.5e-3;
  doc["injection"]["t_ns"] = 9 / (360 * 10e6) * 1e9;  // 2.5 ns at 10 MHz
  Machine moved = machine_from_json(doc, "moved.json", "");
  const Injection a = effective_injection(fx), b = effective_injection(moved);
  CHECK(a.r_mm == b.r_mm);
  CHECK(a.energy_MeV == b.energy_MeV);
  CHECK(a.pr_betagamma == Approx(b.pr_betagamma).epsilon(1e-14));
  CHECK(a.z_mm == b.z_mm);
  CHECK(a.pz_betagamma == Approx(b.pz_betagamma).epsilon(1e-14));
  CHECK(a.t_ns == Approx(2.5).epsilon(1e-14));
  CHECK(a.phi_deg == b.phi_deg);
  // Without the effect: the machine's own injection.
  CHECK(effective_injection(with_effects(json::array())).r_mm == 2000);
  std::string msg;
  json none = machine_doc();
  none.erase("injection");
  CHECK(test::error_code([&] { effective_injection(machine_from_json(none, "n.json", "")); }, &msg) ==
        static_cast<int>(ExitCode::data));
}

TEST_CASE("effects: an injection offset in a uniform field is the displaced circle", "[effects][injection][physics]") {
  // Start at (R + dr, 0) with p_r / p = sin(alpha): the orbit is the circle of radius R about
  // c = (R + dr - R cos(alpha), R sin(alpha)); along azimuth psi it is at
  // r = u.c + sqrt(R^2 - |c|^2 + (u.c)^2), u = (cos psi, sin psi): a coherent oscillation
  // dr cos(psi) + R alpha sin(psi) to first order.
  const double e0 = energy_on(kB0, kR), dr = 3e-3, alpha = std::asin(2e-3);
  json doc = machine_doc();
  doc["injection"] = {{"energy_MeV", e0}, {"r_mm", kR * 1e3}, {"phi_deg", 0}};
  doc["particle"] = {{"species", "proton"}};
  Machine mach = with_effects(json::parse(R"([{"type": "injection-offset", "dr_mm": 3, "dpr_mrad": 2}])"), doc);
  const ParticleState s0 = injection_state(effective_injection(mach), kMass);
  TrackModel m = uniform();
  m.probes = {test::probe("P90", 90), test::probe("P180", 180), test::probe("P270", 270)};
  const double cx = kR + dr - kR * std::cos(alpha), cy = kR * std::sin(alpha);
  for (const char* integ : kIntegrators) {
    INFO(integ);
    const Run run = track(m, s0, integ, 4.9);
    for (int p = 0; p < 3; ++p) {
      const double psi = (90.0 + 90 * p) * kDeg, uc = std::cos(psi) * cx + std::sin(psi) * cy;
      const double expected = (uc + std::sqrt(kR * kR - cx * cx - cy * cy + uc * uc)) * 1e3;
      const std::vector<double> r = run.r(p);
      REQUIRE(r.size() == 5);
      // rk4: within 0.00011 mm of 23040 steps (turnfit-track(1)); azimuth: exact in a uniform
      // field up to rounding over 5 turns (1e-7 mm).
      for (double x : r) CHECK(x == Approx(expected).epsilon(0).margin(std::string(integ) == "rk4" ? 1e-4 : 1e-7));
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Through a machine file: make_track_model applies the effects.

TEST_CASE("effects: make_track_model applies a machine file's effects", "[effects][machine][track]") {
  // The CLI cases' uniform 1 T machine (10 MeV, r = 458.155 mm, probe X90).
  Machine m = load_machine(test::test_file("machine/track/circle.json"));
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  TrackSettings st;
  st.turns = 2;
  std::vector<TurnRecord> plain, moved;
  track_particle(make_track_model(m), s0, st, plain);
  m.doc["effects"] = json::parse(R"([{"type": "probe-offset", "probe": "X90", "ds_mm": 2.5},
                                     {"type": "field-harmonic", "n": 1, "amplitude_T": 0}])");
  revalidate(m);
  const TrackModel model = make_track_model(m);
  CHECK(model.effects.active);
  CHECK(model.probes[0].shift_m == 2.5e-3);
  track_particle(model, s0, st, moved);
  REQUIRE(plain.size() == 2);
  REQUIRE(moved.size() == 2);
  // A radial probe shifted by 2.5 mm reads 2.5 mm less: exact up to rounding.
  for (size_t i = 0; i < 2; ++i) CHECK(moved[i].r_mm == Approx(plain[i].r_mm - 2.5).epsilon(0).margin(1e-9));
  // What --opal-compat warns about: the ones without an OPAL input, in file order.
  const auto notes = effects_without_opal_input(
      with_effects(json::parse(R"([{"type": "gap-bow", "cavity": "g1", "sagitta_mm": 1},
                                   {"type": "probe-offset", "probe": "P90", "ds_mm": 1},
                                   {"type": "field-harmonic", "amplitude_T": 1e-5}])")).effect_set);
  REQUIRE(notes.size() == 2);
  CHECK_THAT(notes[0], Catch::StartsWith("gap-bow (/effects/0)"));
  CHECK_THAT(notes[1], Catch::StartsWith("field-harmonic (/effects/2)"));
}
