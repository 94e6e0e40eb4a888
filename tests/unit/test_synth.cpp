// turnfit-synth: wire signal and detector model, turn overlap from tracking, run-to-run drift
// (the paper's repeatability), trim coil phase scans against the phase equation, determinism.
#include <catch2/catch.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <fstream>
#include <map>
#include <numeric>
#include <sstream>

#include "../support.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/synth/synth.hpp"
#include "turnfit/synth/synth_app.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

using namespace turnfit;
using turnfit::test::error_code;
using turnfit::test::shared_file;

namespace {

/// The synth test machine (isochronous uniform field, four 1 MV gaps on crest, one trim coil).
Machine iso_machine() { return load_machine(std::string(TURNFIT_TEST_DIR) + "/cli/data/synth_iso.json"); }

SynthSettings quick_settings(double turns = 12, size_t particles = 64) {
  SynthSettings s;
  s.track.turns = turns;
  s.particles = particles;
  s.threads = 1;
  return s;
}

/// Peaks of a profile: local maxima above `level` (of the normalized intensity), each refined to
/// the intensity-weighted mean over +-half_mm above the surrounding minimum (a plain centroid
/// peak finder, enough for separated turns).
std::vector<double> find_peaks(const SynthProfile& p, double level, double half_mm) {
  std::vector<double> out;
  const auto& x = p.position_mm;
  const auto& y = p.intensity;
  const long n = static_cast<long>(y.size()), w = static_cast<long>(std::lround(half_mm / p.step_mm));
  for (long k = 0; k < n; ++k) {
    if (y[k] < level) continue;
    bool top = true;
    for (long j = std::max(0L, k - w); j <= std::min(n - 1, k + w) && top; ++j) top = y[j] < y[k] || (y[j] == y[k] && j >= k);
    if (!top) continue;
    double lo = y[k];
    for (long j = std::max(0L, k - w); j <= std::min(n - 1, k + w); ++j) lo = std::min(lo, y[j]);
    double s = 0, sw = 0;
    for (long j = std::max(0L, k - w); j <= std::min(n - 1, k + w); ++j) {
      s += (y[j] - lo) * x[j];
      sw += y[j] - lo;
    }
    out.push_back(s / sw);
  }
  return out;
}

double rms(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x * x;
  return std::sqrt(s / static_cast<double>(v.size()));
}

}  // namespace

TEST_CASE("synth: wire signal is the beam's share inside the wire, times the current", "[synth]") {
  std::vector<double> x;
  for (int k = 0; k < 400; ++k) x.push_back(-10 + 0.05 * k + 0.025);
  WireModel w;
  w.current_uA = 88;
  w.wire_mm = 0.033;
  // One crossing standing for the whole beam, Gaussian of 1 mm: the reading at the centre is
  // I w / (sqrt(2 pi) sigma) (a thin wire), and the readings sum to I w / dx.
  const auto s = wire_signal(x, {0.0}, {1.0}, 1, w);
  const double peak = *std::max_element(s.begin(), s.end());
  CHECK(peak == Approx(88e3 * 0.033 / std::sqrt(2 * kPi) * std::exp(-0.5 * 0.025 * 0.025)).epsilon(1e-4));
  CHECK(std::accumulate(s.begin(), s.end(), 0.0) * 0.05 == Approx(88e3 * 0.033).epsilon(1e-6));
  CHECK(std::max_element(s.begin(), s.end()) - s.begin() == 199);  // x = -0.025, nearest the centre
  // Linear in the current (the signal-to-noise ratio follows it).
  w.current_uA = 58;
  const auto s58 = wire_signal(x, {0.0}, {1.0}, 1, w);
  CHECK(s58[199] / s[199] == Approx(58.0 / 88.0).epsilon(1e-12));
  // Two crossings of half the beam each: each contributes its share.
  const auto two = wire_signal(x, {-3.0, 3.0}, {1.0, 1.0}, 2, w);
  CHECK(std::accumulate(two.begin(), two.end(), 0.0) * 0.05 == Approx(58e3 * 0.033).epsilon(1e-6));
  // A wide wire on a narrow beam takes all of it: w / dx readings of the full current.
  w.wire_mm = 2;
  const auto wide = wire_signal(x, {0.0}, {0.1}, 1, w);
  CHECK(wide[199] == Approx(58e3).epsilon(1e-9));
  // Silverman's rule: 1.06 sigma n^(-1/5).
  CHECK(silverman_bandwidth(2.0, 1000) == Approx(1.06 * 2.0 / std::pow(1000.0, 0.2)).epsilon(1e-12));
  CHECK(silverman_bandwidth(2.0, 1) == 0);
}

TEST_CASE("synth: detector noise, baseline and normalization have the model's statistics", "[synth]") {
  WireModel w;
  w.electronic_nA = 0.8;
  w.shot_nA = 0.2;
  w.baseline_nA = 3;
  w.baseline_drift_nA = 0;
  SynthProfile p;
  const size_t n = 20000;
  p.step_mm = 0.5;
  p.position_mm.resize(n);
  p.signal_nA.assign(n, 0.0);
  for (size_t k = n / 2; k < n; ++k) p.signal_nA[k] = 400;  // a flat top of 400 nA
  measure_profile(p, w, 5, 0);
  std::vector<double> zero, top;
  for (size_t k = 0; k < n; ++k) (k < n / 2 ? zero : top).push_back(p.intensity[k] * p.scale_nA - p.signal_nA[k] - 3);
  // Electronic noise alone without beam; shot-like noise adds variance shot * signal.
  // Monte Carlo bounds: the rms of n = 10000 normal draws has relative standard error
  // 1/sqrt(2n) = 0.0071, so 0.03 is 4.2 standard errors; their mean has standard error
  // 0.8/sqrt(n) = 0.008 nA, so 0.03 nA is 3.75 standard errors (a seed fixed: deterministic).
  CHECK(rms(zero) == Approx(0.8).epsilon(0.03));
  CHECK(rms(top) == Approx(std::sqrt(0.8 * 0.8 + 0.2 * 400)).epsilon(0.03));
  CHECK(std::fabs(std::accumulate(zero.begin(), zero.end(), 0.0) / zero.size()) < 0.03);
  CHECK(*std::max_element(p.intensity.begin(), p.intensity.end()) == 1.0);
  // Same seed and stream: the same readings; another probe (stream): others.
  SynthProfile q = p, r = p;
  measure_profile(q, w, 5, 0);
  measure_profile(r, w, 5, 1);
  CHECK(q.intensity == p.intensity);
  CHECK(r.intensity != p.intensity);
  // A baseline drift is a ramp from the offset at the first reading to offset + drift at the last.
  w.electronic_nA = w.shot_nA = 0;
  w.baseline_drift_nA = 2;
  SynthProfile d;
  d.position_mm.resize(11);
  d.signal_nA.assign(11, 10.0);
  measure_profile(d, w, 9, 0);
  REQUIRE(d.drift_nA != 0);
  CHECK(d.intensity.front() * d.scale_nA == Approx(13).epsilon(1e-12));
  CHECK(d.intensity.back() * d.scale_nA == Approx(13 + d.drift_nA).epsilon(1e-12));
  CHECK(d.intensity[5] * d.scale_nA == Approx(13 + 0.5 * d.drift_nA).epsilon(1e-12));
}

TEST_CASE("synth: signal-to-noise grows with the beam current", "[synth]") {
  // The paper's repeatability currents: the same beam at 58 and 108 uA.
  Machine m = iso_machine();
  auto noise_at = [&](double uA) {
    SynthSettings s = quick_settings(6, 64);
    s.wire.current_uA = uA;
    s.phases = false;
    s.drift = DriftModel{0, 0, 0};
    const SynthResult r = synthesize(m, s);
    const SynthProfile& p = r.profiles.at(0);
    std::vector<double> res;
    double top = 0;
    for (size_t k = 0; k < p.intensity.size(); ++k) {
      const double base = p.baseline_nA + p.drift_nA * k / (p.intensity.size() - 1.0);
      res.push_back(p.intensity[k] * p.scale_nA - p.signal_nA[k] - base);
      top = std::max(top, p.signal_nA[k]);
    }
    return std::make_pair(top, rms(res));
  };
  const auto [s58, n58] = noise_at(58);
  const auto [s108, n108] = noise_at(108);
  CHECK(s108 / s58 == Approx(108.0 / 58.0).epsilon(1e-9));  // the signal scales with the current
  CHECK(s108 / n108 > 1.15 * (s58 / n58));                  // the noise grows less
}

TEST_CASE("synth: profiles peak at the tracked turns, overlap comes from the tracking", "[synth]") {
  Machine m = iso_machine();
  SynthSettings s = quick_settings(12, 200);
  s.phases = false;
  s.drift = DriftModel{0, 0, 0};
  const SynthResult r = synthesize(m, s);
  REQUIRE(r.profiles.size() == 1);
  const SynthProfile& p = r.profiles[0];
  CHECK(p.probe == "P0");
  CHECK(p.step_mm == 0.5);
  // The first reading sits half a step inside the probe's start (2000 mm): exact arithmetic
  // (was a bare Approx, +-0.024 mm).
  CHECK(p.position_mm.front() == Approx(2000.25).epsilon(0).margin(1e-9));
  // Every turn (25-45 mm apart here, beam rms ~1 mm) is one peak where the bunch crossed.
  const auto peaks = find_peaks(p, 0.2, 4.0);
  std::vector<double> truth;
  for (const auto& c : r.centroids) truth.push_back(c.r_mm);
  REQUIRE(peaks.size() == truth.size());
  std::vector<double> d;
  for (size_t i = 0; i < peaks.size(); ++i) d.push_back(peaks[i] - truth[i]);
  CHECK(rms(d) < 0.25);

  // With a twentieth of the voltage the turns come ~1.5 mm apart, closer than the beam is wide:
  // the profile shows fewer peaks than turns and no reading between turns falls to the baseline.
  Machine low = m;
  for (size_t i = 0; i < low.cavities.size(); ++i)
    apply_sets(low, {"/cavities/" + std::to_string(i) + "/voltage_MV=0.05"});
  const SynthResult lr = synthesize(low, s);
  const SynthProfile& lp = lr.profiles.at(0);
  const size_t turns = lr.centroids.size();
  REQUIRE(turns >= 10);
  const auto lpk = find_peaks(lp, 0.2, 0.75);
  CHECK(lpk.size() < turns / 2);
  double lo_between = 1;
  const double first = lr.centroids.front().r_mm, last = lr.centroids.back().r_mm;
  for (size_t k = 0; k < lp.position_mm.size(); ++k)
    if (lp.position_mm[k] > first && lp.position_mm[k] < last) lo_between = std::min(lo_between, lp.intensity[k]);
  CHECK(lo_between > 0.2);
  // ...while the separated turns of the nominal voltage fall to the baseline between peaks.
  double lo_sep = 1;
  for (size_t k = 0; k < p.position_mm.size(); ++k)
    if (p.position_mm[k] > truth.front() && p.position_mm[k] < truth.back()) lo_sep = std::min(lo_sep, p.intensity[k]);
  CHECK(lo_sep < 0.02);
}

TEST_CASE("synth: the same inputs give the same outputs on any thread count", "[synth]") {
  Machine m = iso_machine();
  m.trimcoils[0].bmax_T = 0;
  SynthSettings s = quick_settings(20, 48);
  s.threads = 1;
  const SynthResult a = synthesize(m, s);
  s.threads = 3;
  const SynthResult b = synthesize(m, s);
  REQUIRE(a.profiles.size() == 1);
  CHECK(a.profiles[0].intensity == b.profiles[0].intensity);
  REQUIRE(a.phases.size() == 1);
  CHECK(a.phases[0].dsinphi == b.phases[0].dsinphi);
  s.seed = 2;
  const SynthResult c = synthesize(m, s);
  CHECK(c.profiles[0].intensity != a.profiles[0].intensity);
  CHECK(c.phases[0].dsinphi != a.phases[0].dsinphi);
}

TEST_CASE("synth: run-to-run drift draws the model's rms and moves the machine", "[synth]") {
  DriftModel dm;
  dm.r_mm = 0.7;
  dm.pr_mrad = 0.3;
  dm.voltage_rel = 1e-4;
  double sr = 0, sp = 0, sv = 0, mr = 0;
  const int n = 4000;
  for (int i = 0; i < n; ++i) {
    const Drift d = draw_drift(dm, static_cast<std::uint64_t>(i));
    sr += d.dr_mm * d.dr_mm;
    sp += d.dpr_mrad * d.dpr_mrad;
    sv += d.dvoltage_rel * d.dvoltage_rel;
    mr += d.dr_mm;
  }
  // Monte Carlo bounds, n = 4000 draws: an rms has relative standard error 1/sqrt(2n) = 0.0112,
  // so 0.05 is 4.5 standard errors; the mean of dr has standard error 0.7/sqrt(n) = 0.011 mm,
  // so 0.05 mm is 4.5 standard errors.
  CHECK(std::sqrt(sr / n) == Approx(0.7).epsilon(0.05));
  CHECK(std::sqrt(sp / n) == Approx(0.3).epsilon(0.05));
  CHECK(std::sqrt(sv / n) == Approx(1e-4).epsilon(0.05));
  CHECK(std::fabs(mr / n) < 0.05);
  Machine m = iso_machine();
  Drift d;
  d.dr_mm = 0.5;
  d.dpr_mrad = 0.2;
  d.dvoltage_rel = 1e-3;
  apply_drift(m, d);
  CHECK(m.injection->r_mm == Approx(2097.5).epsilon(1e-12));
  const double P = kinematics(m.particle.mass_MeV, 1, 72).betagamma;
  CHECK(m.injection->pr_betagamma == Approx(P * 0.2e-3).epsilon(1e-12));
  for (const auto& c : m.cavities) CHECK(c.voltage_MV == Approx(1.001).epsilon(1e-12));
}

namespace {

/// Pairwise RRL differences of runs 1..10 of the PSI Ring example (see the cases below).
struct DriftStats {
  double sigma = 0, mae = 0, mean_abs = 0;     // over the 45 pairs
  double se_sigma = 0, se_mae = 0, se_mean = 0;  // their standard errors (5 disjoint pairs)
};

DriftStats psi_drift_stats(const std::string& map) {
  nlohmann::json doc = read_json(std::string(TURNFIT_TEST_DIR) + "/../examples/psi-ring/aeo.json");
  const std::string dir = std::string(TURNFIT_TEST_DIR) + "/../examples/psi-ring";
  // The shared data wherever it is (TURNFIT_SHARED), not only beside the project.
  doc["field"]["map"] = map;
  for (auto& c : doc["cavities"]) {
    const std::string prof = c["profile"].get<std::string>();
    c["profile"] = shared_file("data/psi-ring/" + prof.substr(prof.rfind('/') + 1));
  }
  doc["bunch"] = {{"sigma_E_MeV", 1e-9}};  // one particle: the centroid without sampling noise
  Machine m = machine_from_json(doc, "aeo.json", dir);
  SynthSettings s = quick_settings(190, 1);
  s.phases = false;
  std::vector<std::map<int, double>> runs;
  for (std::uint64_t seed = 1; seed <= 10; ++seed) {
    s.seed = seed;
    const SynthResult r = synthesize(m, s);
    std::map<int, double> rrl;
    for (const auto& c : r.centroids)
      if (r.probe_names[static_cast<size_t>(c.probe)] == "RRL" && c.turn <= 182) rrl[c.turn] = c.r_mm;
    REQUIRE(rrl.size() == 174);  // RRL turns 9-182 of the paper (a probe counts every crossing of its line)
    runs.push_back(rrl);
  }
  // Per pair: variance of the differences, their mean absolute value, |their mean|.
  auto pair = [&](size_t a, size_t b) {
    double s1 = 0, s2 = 0, sa = 0;
    for (const auto& [turn, r] : runs[a]) {
      const double d = runs[b].at(turn) - r;
      s1 += d;
      s2 += d * d;
      sa += std::fabs(d);
    }
    const double n = static_cast<double>(runs[a].size()), mean = s1 / n;
    return std::array<double, 3>{s2 / n - mean * mean, sa / n, std::fabs(mean)};
  };
  std::array<double, 3> all{0, 0, 0};
  int pairs = 0;
  for (size_t a = 0; a < runs.size(); ++a)
    for (size_t b = a + 1; b < runs.size(); ++b) {
      const auto v = pair(a, b);
      for (int i = 0; i < 3; ++i) all[i] += v[i];
      ++pairs;
    }
  DriftStats st;
  st.sigma = std::sqrt(all[0] / pairs);
  st.mae = all[1] / pairs;
  st.mean_abs = all[2] / pairs;
  // The 45 pairs share runs; the 5 disjoint pairs (1,2) ... (9,10) are independent draws, and
  // the standard error of their mean, sd/sqrt(5), bounds that of the 45-pair mean (which uses
  // the same runs and more of their combinations) from above.
  std::array<std::vector<double>, 3> dis;
  for (size_t a = 0; a + 1 < runs.size(); a += 2) {
    const auto v = pair(a, a + 1);
    for (int i = 0; i < 3; ++i) dis[i].push_back(v[i]);
  }
  auto se = [](const std::vector<double>& v) {
    const double n = static_cast<double>(v.size()), mean = std::accumulate(v.begin(), v.end(), 0.0) / n;
    double ss = 0;
    for (double x : v) ss += (x - mean) * (x - mean);
    return std::sqrt(ss / (n - 1) / n);
  };
  st.se_sigma = se(dis[0]) / (2 * st.sigma);  // of sigma = sqrt(mean variance)
  st.se_mae = se(dis[1]);
  st.se_mean = se(dis[2]);
  return st;
}

}  // namespace

TEST_CASE("synth: run-to-run drift moves the PSI Ring's RRL turns as much as the paper measured", "[synth][psi]") {
  // Frey et al. (seed paper, repeatability): RRL peak positions at 58 and 108 uA against 88 uA
  // differ by sigma 0.51 and 0.58 mm, mean -0.09 and +0.003 mm, MAE 0.40 mm. Here: the turn
  // positions of runs 1..10 of the example machine, compared pairwise (45 pairs): the spread is
  // a random betatron oscillation, so a single pair varies a lot (turnfit-synth(1): sigma 0.01
  // to 1.2 mm) and the mean over pairs is what the defaults are set to.
  // Bounds: the paper's figures widened by 3 standard errors of the mean over pairs (computed
  // from the 5 independent pairs, see psi_drift_stats). Ten runs cannot pin the spread better
  // than that: the [regression] case below pins this run's digits.
  TURNFIT_REQUIRE_SHARED(map, "data/psi-ring/bfield.dat");
  const DriftStats st = psi_drift_stats(map);
  CAPTURE(st.sigma, st.mae, st.mean_abs, st.se_sigma, st.se_mae, st.se_mean);
  CHECK(st.sigma > 0.51 - 3 * st.se_sigma);
  CHECK(st.sigma < 0.58 + 3 * st.se_sigma);
  CHECK(st.mae == Approx(0.40).epsilon(0).margin(3 * st.se_mae));
  CHECK(st.mean_abs < 0.09 + 3 * st.se_mean);  // the paper's means are near 0: no systematic shift
}

TEST_CASE("synth: PSI Ring drift statistics of seeds 1-10 as turnfit-synth(1) states them (regression)",
          "[synth][psi][regression]") {
  // Guards the drift model's defaults (DriftModel), the seeding of runs and the tracking of the
  // PSI Ring example: the fixed seeds make the statistics deterministic. turnfit-synth(1) (Run-to-run
  // drift and repeatability) states this unit test's result, sigma 0.49, MAE 0.39, mean 0.06 mm;
  // trusted because they agree with the paper's repeatability (case above) and with the 66-pair
  // figures of the man page (0.48, 0.44, 0.09). Bounds: half the printed last digit (0.005 mm).
  TURNFIT_REQUIRE_SHARED(map, "data/psi-ring/bfield.dat");
  const DriftStats st = psi_drift_stats(map);
  CHECK(st.sigma == Approx(0.49).epsilon(0).margin(0.005));
  CHECK(st.mae == Approx(0.39).epsilon(0).margin(0.005));
  CHECK(st.mean_abs == Approx(0.06).epsilon(0).margin(0.005));
}

namespace {
/// The coil's field recovered from a noiseless phase scan with the phase equation, against the
/// coil's shape (see phase_equation_scan).
struct PhaseEquationResult {
  double worst = 0, peak = 0, sum_est = 0, sum_true = 0, worst_eq2 = 0, peak_eq2 = 0, tail_change = 0, tail = 0;
};

PhaseEquationResult phase_equation_scan() {
  // Isochronous field B = B0 gamma(r) (field index k = gamma^2 - 1), gaps on crest. A field
  // change dB at fixed energy moves the orbit by dr/r = -dB / (B (1 + k)) and the revolution
  // frequency by dw/w = dB / (B gamma^2); per turn the RF phase slips by -2 pi h dw/w and the
  // energy gain qV cos(phi) sets turns per radius, so (cos phi cancels)
  //   d sin(phi)/dr = -2 pi h dB (dE/dr) / (B gamma^2 qV),  dE/dr = m c^2 gamma^3 beta^2 / r,
  // i.e. dB = -(q B V r / (2 pi h m c^2 gamma beta^2)) d sin(phi)/dr: the paper's Eq. 2 up to
  // the slowly varying gamma^2 / (2 pi h) (Eq. 2 states a proportionality).
  // A quarter of the voltage (1 MeV a turn): the huge kicks of the test machine's 1 MV gaps
  // drive a coherent radial oscillation of several mm (nu_r = gamma is near 1), which a phase
  // probe at one azimuth sees as radius errors of that size.
  Machine m = iso_machine();
  for (size_t i = 0; i < m.cavities.size(); ++i) apply_sets(m, {"/cavities/" + std::to_string(i) + "/voltage_MV=0.25"});
  SynthSettings s = quick_settings(160, 1);
  s.profiles = false;
  s.drift = DriftModel{0, 0, 0};
  s.phase.step_mm = 10;
  s.phase.noise_deg = 0;
  s.phase.excitation_T = 1e-4;
  const SynthResult r = synthesize(m, s);
  REQUIRE(r.phases.size() == 1);
  const PhaseScan& ps = r.phases[0];
  CHECK(ps.coil == "TCX");
  CHECK(ps.excitation_T == 1e-4);
  CHECK(ps.dsinphi == ps.dsinphi_true);
  REQUIRE(ps.r_mm.size() > 100);
  CHECK(ps.r_mm.front() <= 2110);
  CHECK(ps.r_mm.back() >= 3300);
  const TrimCoilField coil(m.trimcoils[0], 8);
  const double mass = m.particle.mass_MeV, rinf = kSpeedOfLight / (2 * kPi * 50.65e6 / 6);
  const double b0 = 2 * kPi * 50.65e6 / 6 * mass * 1e6 / kSpeedOfLight / kSpeedOfLight;  // omega m / q [T]
  double worst = 0, worst_eq2 = 0, peak = 0, peak_eq2 = 0, sum_est = 0, sum_true = 0;
  std::vector<double> eq2, truth;
  // Slopes over +-30 mm (3 turns): the residual oscillation still moves single turns by ~1 mm.
  const size_t K = 3;
  for (size_t j = K; j + K < ps.r_mm.size(); ++j) {
    const double r_m = ps.r_mm[j] * 1e-3;
    if (r_m < 2.4 || r_m > 3.0) continue;
    const double beta = r_m / rinf, gamma = 1 / std::sqrt(1 - beta * beta), B = b0 * gamma;
    const double u = 2 * kPi * 50.65e6 * 0.1 / (2 * beta * kSpeedOfLight), V = std::sin(u) / u;  // MV per turn
    const double a = ps.r_mm[j - K] * 1e-3, b = ps.r_mm[j + K] * 1e-3;
    const double dsdr = (ps.dsinphi[j + K] - ps.dsinphi[j - K]) / (b - a);
    const double est = -(B * V * r_m) / (2 * kPi * 6 * mass * gamma * beta * beta) * dsdr;
    double shape = 0;  // the coil's mean over the same interval
    for (int i = 0; i <= 200; ++i) {
      double v, dv;
      coil.shape_exact(a + (b - a) * i / 200, v, dv);
      shape += v / 201;
    }
    const double want = 1e-4 * shape;
    worst = std::max(worst, std::fabs(est - want));
    peak = std::max(peak, want);
    sum_est += est;
    sum_true += want;
    // The paper's Eq. 2 factor, E the kinetic energy: its shape, normalized at the end.
    const double E = mass * (gamma - 1);
    eq2.push_back(-(B * V * r_m) / (E * gamma * (gamma + 1)) * dsdr);
    truth.push_back(shape);
  }
  for (size_t i = 0; i < eq2.size(); ++i) peak_eq2 = std::max(peak_eq2, eq2[i]);
  REQUIRE(peak_eq2 > 0);  // Eq. 2's sign: a stronger field gives a falling sin(phi)
  for (size_t i = 0; i < eq2.size(); ++i) worst_eq2 = std::max(worst_eq2, std::fabs(eq2[i] / peak_eq2 - truth[i]));
  PhaseEquationResult res;
  res.worst = worst;
  res.peak = peak;
  res.sum_est = sum_est;
  res.sum_true = sum_true;
  res.worst_eq2 = worst_eq2;
  res.peak_eq2 = peak_eq2;
  res.tail = ps.dsinphi.back();
  res.tail_change = std::fabs(ps.dsinphi.back() - ps.dsinphi[ps.dsinphi.size() - 5]);
  return res;
}
}  // namespace

TEST_CASE("synth: phase scans follow the phase equation: d(delta sin phi)/dr gives the coil's field", "[synth]") {
  // Invariants of the phase equation (the derivation above, turnfit-synth(1) Trim coil phase
  // scans): a positive excitation makes sin(phi) fall across the coil and stay lower outside it,
  // so the recovered field has the coil's sign. The scale and shape are in the [regression]
  // case below: the man page's "5% in scale and 12% of the peak in shape" reports that test, so
  // it is not an independent bound, and the scan is noiseless, so no noise bound applies.
  const PhaseEquationResult r = phase_equation_scan();
  CAPTURE(r.worst, r.peak, r.sum_est, r.sum_true, r.worst_eq2, r.tail, r.tail_change);
  CHECK(r.sum_true > 0);
  CHECK(r.sum_est > 0);  // the sign of dB from -(...) d sin(phi)/dr
  CHECK(r.peak_eq2 > 0);  // Eq. 2's sign
  CHECK(r.tail < 0);      // sin(phi) stays lower beyond the coil
}

TEST_CASE("synth: phase scans follow the phase equation: the recovered field's scale and shape (regression)",
          "[synth][regression]") {
  // Values from this program's own output (the isochronous test machine, 0.25 MV gaps, TCX at
  // 1e-4 T, no noise): measured scale error 0.09%, shape error 8.6% of the peak, Eq. 2's shape
  // 8.4%, the change of delta sin(phi) over the last 4 readings beyond the coil 1.27% of it.
  // Guards the phase-scan pipeline (phase reading at the probe line, interpolation onto the
  // probe radii, the difference of two runs). Trusted because the scale agrees with the
  // first-order analytic relation (exact to first order, derived above) to 0.09%, and the shape
  // error has a known cause: the residual coherent radial oscillation (several mm at nu_r ~ 1)
  // differentiated over +-3 turns. Bounds: the measured value plus about 10% of it, for rounding
  // differences between compilers over 160 tracked turns (an allowance, not a source). Was 5%
  // and 12% citing turnfit-synth(1), whose sentence reports this test (circular); the
  // flat-beyond check was 2% (no source).
  const PhaseEquationResult r = phase_equation_scan();
  CAPTURE(r.worst, r.peak, r.sum_est, r.sum_true, r.worst_eq2, r.tail, r.tail_change);
  CHECK(r.sum_est == Approx(r.sum_true).epsilon(0.001));  // scale, measured 0.09%
  CHECK(r.worst < 0.095 * r.peak);                           // shape, turn by turn, measured 8.6%
  CHECK(r.worst_eq2 < 0.093);                                // Eq. 2's shape, measured 8.4%
  CHECK(r.tail_change < 0.014 * std::fabs(r.tail));          // flat beyond the coil, measured 1.27%
}

TEST_CASE("synth: a phase scan excites the coil where the model's effects put it", "[synth]") {
  // A trimcoil-sectors effect confines TCX to the odd sectors; its phase scan must equal the scan
  // of a machine whose TCX sits on those sectors by description (the excitation once replaced
  // the coil by its all-sector description, doubling the excitation of such coils).
  Machine by_effect = iso_machine(), by_description = iso_machine();
  by_effect.doc["trimcoils"][0]["bmax_T"] = 4e-4;  // a nominal field, so the two runs differ
  by_effect.doc["effects"] = nlohmann::json::parse(R"([{"type": "trimcoil-sectors", "coils": ["TCX"], "sectors": [1, 3, 5, 7]}])");
  revalidate(by_effect);
  by_description.doc["trimcoils"][0]["bmax_T"] = 4e-4;
  by_description.doc["trimcoils"][0]["sectors"] = {1, 3, 5, 7};
  revalidate(by_description);
  SynthSettings s = quick_settings(60, 1);
  s.profiles = false;
  s.drift = DriftModel{0, 0, 0};
  s.phase.noise_deg = 0;
  const PhaseScan a = synthesize(by_effect, s).phases.at(0), b = synthesize(by_description, s).phases.at(0);
  REQUIRE(a.r_mm == b.r_mm);
  double biggest = 0;
  for (size_t i = 0; i < a.r_mm.size(); ++i) {
    CHECK(a.dsinphi_true[i] == Approx(b.dsinphi_true[i]).epsilon(0).margin(1e-12));
    biggest = std::max(biggest, std::fabs(b.dsinphi_true[i]));
  }
  CHECK(biggest > 1e-3);  // the scan sees the coil
}

TEST_CASE("synth: phase-probe noise has the model's rms", "[synth]") {
  Machine m = iso_machine();
  SynthSettings s = quick_settings(40, 1);
  s.profiles = false;
  s.phase.step_mm = 5;
  s.phase.noise_deg = 0.15;
  const SynthResult r = synthesize(m, s);
  const PhaseScan& ps = r.phases.at(0);
  std::vector<double> d;
  for (size_t j = 0; j < ps.dsinphi.size(); ++j) d.push_back(ps.dsinphi[j] - ps.dsinphi_true[j]);
  // Two independent readings per radius near the crest: sqrt(2) 0.15 deg in radians.
  // d = cos(phi) (n1 - n0) to first order, phi within degrees of the crest (cos(phi) ~ 1): rms
  // sqrt(2) 0.15 deg. The sample rms of n readings has relative standard error 1/sqrt(2n) (n = 244:
  // 4.5%): the bound is 3 standard errors, 13.6% (was a fixed 15%, 3.3 of them; measured -2.5%).
  const double n_read = static_cast<double>(d.size()), se = 1 / std::sqrt(2 * n_read);
  CAPTURE(n_read, se);
  REQUIRE(n_read >= 100);
  CHECK(rms(d) == Approx(std::sqrt(2.0) * 0.15 * kPi / 180).epsilon(3 * se));
}

TEST_CASE("synth: bad inputs are data errors naming the machine key", "[synth]") {
  Machine m = iso_machine();
  SynthSettings s = quick_settings(4, 8);
  std::string msg;
  // Changed in the document: synthesize rebuilds the machine from it (drift).
  Machine nob = m;
  nob.doc.erase("bunch");
  revalidate(nob);
  CHECK(error_code([&] { synthesize(nob, s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("/bunch"));
  Machine flat = m;
  flat.doc["bunch"] = {{"particles", 8}};
  revalidate(flat);
  CHECK(error_code([&] { synthesize(flat, s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("no spread"));
  Machine norf = m;
  norf.doc["rf"]["frequency_MHz"] = 0;
  norf.doc["cavities"] = nlohmann::json::array();
  norf.doc["bunch"].erase("sigma_phase_deg");
  revalidate(norf);
  s.profiles = false;
  CHECK(error_code([&] { synthesize(norf, s); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("/rf/frequency_MHz"));
}

TEST_CASE("synth: truth.json holds the hidden values", "[synth]") {
  Machine m = iso_machine();
  apply_sets(m, {"rinit=2097.4"});
  m.effects = nlohmann::json::array({{{"type", "first-harmonic"}, {"amplitude_T", 1e-4}}});
  SynthSettings s = quick_settings(6, 16);
  s.seed = 17;
  s.wire.current_uA = 108;
  const SynthResult r = synthesize(m, s);
  const nlohmann::json t = truth_json(m, s, r);
  CHECK(t["format"] == "turnfit-synth-truth/1");
  CHECK(t["seed"] == 17);
  CHECK(t["current_uA"] == 108.0);
  // The value set, written to JSON and read back: exact to the double's round trip (was a bare
  // Approx, +-0.025 mm).
  CHECK(t["dvars"]["rinit"].get<double>() == Approx(2097.4).epsilon(0).margin(1e-9));
  CHECK(t["effects"][0]["type"] == "first-harmonic");
  CHECK(t["drift"]["dr_mm"].get<double>() == r.drift.dr_mm);
  CHECK(t["drift"]["dr_mm"].get<double>() != 0);
  CHECK(t["turns"]["P0"].size() == r.centroids.size());
  CHECK(t["phase"]["coils"]["TCX"]["excitation_T"] == s.phase.excitation_T);
  // The truth, not the drifted run (whose dr_mm is non-zero, checked above): exact.
  CHECK(t["machine_doc"]["injection"]["r_mm"].get<double>() == Approx(2097.4).epsilon(0).margin(1e-9));
}

TEST_CASE("synth: bunch_mean is the mean of the particles tracked, in truth.json", "[synth]") {
  Machine m = iso_machine();
  SynthSettings s = quick_settings(6, 50);
  s.phases = false;
  s.seed = 23;
  SynthResult r = synthesize(m, s);
  // The particles synth tracked: the machine's Gaussian, drawn from the run's seed.
  const std::vector<BunchOffset> offs = gaussian_bunch(*m.bunch, 50, 23);
  double mr = 0, mp = 0, mz = 0, mpz = 0, me = 0, mph = 0;
  for (const auto& o : offs) {
    mr += o.dr_mm / 50;
    mp += o.dpr_mrad / 50;
    mz += o.dz_mm / 50;
    mpz += o.dpz_mrad / 50;
    me += o.dE_MeV / 50;
    mph += o.dphase_deg / 50;
  }
  const BunchMean& b = r.bunch_mean;
  CHECK(b.particles == 50);
  CHECK(b.offset.dr_mm == Approx(mr).epsilon(1e-12));
  CHECK(b.offset.dpr_mrad == Approx(mp).epsilon(1e-12));
  CHECK(b.offset.dz_mm == Approx(mz).margin(1e-15));  // the iso bunch has no vertical emittance
  CHECK(b.offset.dpz_mrad == Approx(mpz).margin(1e-15));
  CHECK(b.offset.dE_MeV == Approx(me).epsilon(1e-12));
  CHECK(b.offset.dphase_deg == Approx(mph).epsilon(1e-12));
  // A 50-particle sample of 2 deg rms is off the reference by ~0.28 deg rms: a test that can see it.
  CHECK(std::fabs(mph) > 1e-3);
  CHECK(b.dt_ns == Approx(mph / (360 * 50.65) * 1e3).epsilon(1e-12));
  // Isochronous uniform field: the bunch's mean, dt late, runs the orbit the reference particle's
  // azimuth reaches dt later, 360 f_rf / h degrees per unit of time behind: dphi = -dphase / h.
  CHECK(b.dphi_deg == Approx(-mph / 6).epsilon(2e-3));
  CHECK(b.at_reference_time.dphase_deg == 0);
  CHECK(b.at_reference_time.dE_MeV == b.offset.dE_MeV);

  const nlohmann::json t = truth_json(m, s, r);
  REQUIRE(t.contains("bunch_mean"));
  CHECK(t["bunch_mean"]["particles"] == 50);
  CHECK(t["bunch_mean"]["dphase_deg"].get<double>() == b.offset.dphase_deg);
  CHECK(t["bunch_mean"]["dpr_mrad"].get<double>() == b.offset.dpr_mrad);
  CHECK(t["bunch_mean"]["dt_ns"].get<double>() == b.dt_ns);
  CHECK(t["bunch_mean"]["at_reference_time"]["dphi_deg"].get<double>() == b.dphi_deg);
  CHECK(t["bunch_mean"]["at_reference_time"]["dr_mm"].get<double>() == b.at_reference_time.dr_mm);

  // A bunch file: the first --particles rows are tracked, and their mean is recorded.
  test::TempDir tmp;
  m.bunch->file = tmp.file("bunch.csv", "dr_mm,dpr_mrad,dE_MeV,dphase_deg\n"
                                        "0.4,0.1,0.01,3\n"
                                        "-0.1,0.3,0.03,-1\n"
                                        "5,5,5,5\n");
  s.drift = DriftModel{0, 0, 0};  // the machine as set (a drift revalidates it from its document)
  s.particles = 2;
  r = synthesize(m, s);
  CHECK(r.bunch_mean.particles == 2);
  CHECK(r.bunch_mean.offset.dr_mm == Approx(0.15));
  CHECK(r.bunch_mean.offset.dpr_mrad == Approx(0.2));
  CHECK(r.bunch_mean.offset.dE_MeV == Approx(0.02));
  CHECK(r.bunch_mean.offset.dphase_deg == Approx(1));
  // Without profiles no bunch is tracked and truth.json has no bunch_mean.
  s.profiles = false;
  s.phases = true;
  r = synthesize(m, s);
  CHECK(r.bunch_mean.particles == 0);
  CHECK_FALSE(truth_json(m, s, r).contains("bunch_mean"));
}

TEST_CASE("synth: bunch_mean at the reference's time starts on the mean particle's path (ring8)", "[synth]") {
  const Machine m = load_machine(std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/machine.json");
  const TrackModel model = make_track_model(m);
  TrackSettings st = machine_track_settings(m);
  st.turns = 12;
  const Injection inj = effective_injection(m);
  const double mass = m.particle.mass_MeV;
  // A mean far beyond a real bunch's (1.5 deg late, 0.3 mm out, 0.2 mrad, 10 keV), so the
  // first-order move's own error (second order) stays far below what it corrects.
  const std::vector<BunchOffset> offs = {{0.5, 0.1, 0, 0, 0.02, 2.5}, {0.1, 0.3, 0, 0, 0.0, 0.5}};
  const BunchMean b = bunch_mean(model, inj, mass, offs);
  CHECK(b.offset.dphase_deg == Approx(1.5));
  // -dphase / h on average over a turn; at the injection azimuth the scalloped orbit's local
  // angular speed differs from its mean by a few per cent.
  CHECK(b.dphi_deg == Approx(-1.5 / 6).epsilon(0.05));

  auto radii = [&](const Injection& in, const BunchOffset& o) {
    std::vector<TurnRecord> turns;
    track_particle(model, offset_state(in, mass, model.rf_MHz, o), st, turns);
    return turns;
  };
  const std::vector<TurnRecord> mean = radii(inj, b.offset);
  Injection moved = inj;
  moved.phi_deg += b.dphi_deg;
  const std::vector<TurnRecord> at = radii(moved, b.at_reference_time);
  // The azimuth alone, r and p_r/p as at the injection azimuth: off the path.
  BunchOffset phi_only = b.offset;
  phi_only.dphase_deg = 0;
  const std::vector<TurnRecord> only = radii(moved, phi_only);
  REQUIRE(mean.size() == at.size());
  REQUIRE(mean.size() == only.size());
  REQUIRE(mean.size() >= 10);
  double d_at = 0, d_only = 0, dt_at = 0;
  for (size_t k = 0; k < mean.size(); ++k) {
    REQUIRE(mean[k].probe == at[k].probe);
    REQUIRE(mean[k].turn == at[k].turn);
    d_at = std::max(d_at, std::fabs(at[k].r_mm - mean[k].r_mm));
    d_only = std::max(d_only, std::fabs(only[k].r_mm - mean[k].r_mm));
    dt_at = std::max(dt_at, std::fabs(at[k].t_ns - mean[k].t_ns));
  }
  INFO("max |dr| moved along the path " << d_at << " mm, azimuth alone " << d_only << " mm; max |dt| " << dt_at
                                        << " ns");
  CHECK(d_only > 0.02);
  CHECK(d_at < 0.05 * d_only);
  CHECK(dt_at < 1e-3);  // the same arrival times: the start time is the reference's
}

// ---- Scan errors (issue 16): the per-turn error model of a wire scan ----

namespace {

/// A single turn: the whole beam in one crossing at r0 of width h, read on a grid of `step`
/// over r0 +- 15 mm (12 widths and more for h <= 1.25 mm), a thin wire.
SynthProfile single_turn(double r0, double step, WireModel& w) {
  w.wire_mm = 1e-3;
  SynthProfile p;
  p.step_mm = step;
  for (double x = r0 - 15; x <= r0 + 15 + 1e-9; x += step) p.position_mm.push_back(x);
  return p;
}

/// Centroid of the noiseless signal over the whole profile.
double signal_centroid(const SynthProfile& p) {
  double s = 0, sx = 0;
  for (size_t k = 0; k < p.signal_nA.size(); ++k) {
    s += p.signal_nA[k];
    sx += p.signal_nA[k] * p.position_mm[k];
  }
  return sx / s;
}

}  // namespace

TEST_CASE("synth: without scan errors the profile is today's (regression)", "[synth][regression]") {
  // Guards the promise that --scan-errors none (the default) leaves every output as it was: the
  // figures were printed by the library before the scan-error model existed (commit bda7adb, the
  // iso machine, 10 turns, 64 particles, seed 11), 17 digits. Bounds: 1e-9 relative, room for
  // another CPU's last bits; a scan error of even 1e-3 mm moves the sums by far more.
  Machine m = iso_machine();
  SynthSettings s;
  s.track = machine_track_settings(m, "");
  s.track.turns = 10;
  s.particles = 64;
  s.threads = 1;
  s.phases = false;
  s.seed = 11;
  REQUIRE_FALSE(s.scan.active());
  const SynthResult r = synthesize(m, s);
  const SynthProfile& p = r.profiles.at(0);
  CHECK(p.intensity.size() == 1600);
  CHECK(p.scale_nA == Approx(634.13294087884674).epsilon(1e-9));
  CHECK(p.drift_nA == Approx(-0.21668534099313205).epsilon(1e-9));
  double sum = 0, sx = 0;
  for (size_t k = 0; k < p.intensity.size(); ++k) {
    sum += p.intensity[k];
    sx += p.intensity[k] * p.position_mm[k];
  }
  CHECK(sum == Approx(96.392283919810808).epsilon(1e-9));
  CHECK(sx == Approx(226694.16007253301).epsilon(1e-9));
  CHECK(p.signal_nA[777] == Approx(1.0569817493009948).epsilon(1e-9));
  CHECK(p.intensity[777] == Approx(0.0067532082181689171).epsilon(1e-9));
  CHECK(p.scan.drive_mm.empty());
  CHECK(p.scan.readout_mm.empty());
  CHECK(p.scan.intensity_factor.empty());
}

TEST_CASE("synth: scan errors off are no errors at all", "[synth]") {
  // A model whose every rms is 0 draws nothing, whatever its correlation lengths; no errors
  // applied give wire_signal's numbers exactly; the "none" preset is the drift of today.
  ScanErrorModel off;
  off.intensity_corr_mm = 77;
  off.drive_corr_mm = 3;
  CHECK_FALSE(off.active());
  std::vector<double> x;
  for (int k = 0; k < 50; ++k) x.push_back(0.5 * k);
  const ScanErrors e = draw_scan_errors(off, x, 3, 0);
  CHECK(e.drive_mm.empty());
  CHECK(e.readout_mm.empty());
  CHECK(e.intensity_factor.empty());
  WireModel w;
  SynthProfile p;
  p.position_mm = x;
  apply_scan_errors(p, {10.2, 13.0}, {1.1, 0.9}, 2, w, e);
  CHECK(p.signal_nA == wire_signal(x, {10.2, 13.0}, {1.1, 0.9}, 2, w));
  const SynthPreset none = synth_preset("none");
  CHECK_FALSE(none.scan.active());
  CHECK(none.drift.r_mm == DriftModel{}.r_mm);
  CHECK(none.drift.pr_mrad == DriftModel{}.pr_mrad);
  CHECK(none.drift.voltage_rel == DriftModel{}.voltage_rel);
  // The whole synthesis: an inactive model with other correlation lengths, the same bytes.
  Machine m = iso_machine();
  SynthSettings s = quick_settings(8, 40);
  s.phases = false;
  const SynthResult a = synthesize(m, s);
  s.scan = off;
  const SynthResult b = synthesize(m, s);
  CHECK(a.profiles.at(0).intensity == b.profiles.at(0).intensity);
}

TEST_CASE("synth: the Ornstein-Uhlenbeck process has its rms and correlation length", "[synth]") {
  // Exponential covariance rms^2 exp(-|dx|/corr): 200000 samples every 0.5 mm of a process with
  // a 5 mm correlation length hold about n / (2 corr / step) = 10000 independent values, so the
  // rms has a relative standard error near 1/sqrt(2 * 10000) = 0.7% (0.04 is 5.6 of them) and a
  // correlation coefficient one of about 1/sqrt(10000) = 0.01 (0.04 is 4 of them).
  const size_t n = 200000;
  const std::vector<double> v = ou_process(n, 0.5, 0.3, 5, 42, 9);
  double ss = 0, m = 0;
  for (double x : v) {
    ss += x * x;
    m += x;
  }
  const double var = ss / n;
  CHECK(std::sqrt(var) == Approx(0.3).epsilon(0.04));
  CHECK(std::fabs(m / n) < 0.3 * 0.04);
  auto corr = [&](size_t lag) {
    double c = 0;
    for (size_t k = lag; k < n; ++k) c += v[k] * v[k - lag];
    return c / static_cast<double>(n - lag) / var;
  };
  CHECK(corr(1) == Approx(std::exp(-0.1)).margin(0.04));
  CHECK(corr(10) == Approx(std::exp(-1.0)).margin(0.04));  // one correlation length
  CHECK(corr(40) == Approx(std::exp(-4.0)).margin(0.04));
  // Correlation length 0: independent values (the readout jitter).
  const std::vector<double> white = ou_process(n, 0.5, 1.0, 0, 42, 9);
  double c1 = 0, sw = 0;
  for (size_t k = 1; k < n; ++k) c1 += white[k] * white[k - 1];
  for (double x : white) sw += x * x;
  CHECK(std::sqrt(sw / n) == Approx(1.0).epsilon(0.02));  // 1/sqrt(2n) = 0.16%: 12 standard errors
  CHECK(std::fabs(c1 / sw) < 0.01);                       // standard error 1/sqrt(n) = 0.0022
  // The same address, the same numbers; another stream, others.
  CHECK(ou_process(100, 0.5, 0.3, 5, 42, 9) == std::vector<double>(v.begin(), v.begin() + 100));
  CHECK(ou_process(100, 0.5, 0.3, 5, 42, 10) != std::vector<double>(v.begin(), v.begin() + 100));
}

TEST_CASE("synth: a beam-current gradient moves a turn's centroid by sigma^2 d ln I/dx", "[synth]") {
  // The signal of one Gaussian turn of rms s times a linear current 1 + g (x - r0): its centroid
  // is r0 + g s^2 exactly (the first moment of x G(x) g (x - r0) over the zeroth), s^2 = h^2 +
  // w^2/12 for a wire of width w. On a 0.25 mm grid over +-15 mm the sums are the integrals to
  // far below 1e-9 (Gaussian sums converge as exp(-2 pi^2 s^2 / step^2)).
  WireModel w;
  SynthProfile p = single_turn(3000, 0.25, w);
  const double h = 1.2, g = 0.04, s2 = h * h + w.wire_mm * w.wire_mm / 12;
  ScanErrors e;
  for (double x : p.position_mm) e.intensity_factor.push_back(1 + g * (x - 3000));
  apply_scan_errors(p, {3000}, {h}, 1, w, e);
  CHECK(signal_centroid(p) - 3000 == Approx(g * s2).epsilon(1e-6));
  CHECK(p.scan.intensity_factor == e.intensity_factor);
  // The signal is the current's share: doubled current, doubled reading, reading by reading.
  SynthProfile q = single_turn(3000, 0.25, w);
  q.signal_nA = wire_signal(q.position_mm, {3000}, {h}, 1, w);
  for (size_t k = 0; k < p.signal_nA.size(); ++k) REQUIRE(p.signal_nA[k] == Approx(q.signal_nA[k] * e.intensity_factor[k]));
  // A random fluctuation: f has the model's rms over a long scan (as ou_process above), and the
  // current never goes negative.
  ScanErrorModel sm;
  sm.intensity_rel = 0.05;
  sm.intensity_corr_mm = 5;
  std::vector<double> x;
  for (int k = 0; k < 100000; ++k) x.push_back(0.5 * k);
  const ScanErrors r = draw_scan_errors(sm, x, 8, 1);
  REQUIRE(r.intensity_factor.size() == x.size());
  CHECK(r.drive_mm.empty());
  CHECK(r.readout_mm.empty());
  double ss = 0;
  for (double f : r.intensity_factor) ss += (f - 1) * (f - 1);
  CHECK(std::sqrt(ss / x.size()) == Approx(0.05).epsilon(0.06));  // ~5000 independent values: 1% standard error
  CHECK(*std::min_element(r.intensity_factor.begin(), r.intensity_factor.end()) > 0);
}

TEST_CASE("synth: a probe drive error moves the turns to where the wire really was", "[synth]") {
  // The wire recorded at x is at x + D(x): a turn at r appears where x + D(x) = r. A constant D
  // moves it by -D; a linear D = c + s (x - r0) puts it at r0 - c / (1 + s) (the signal in x is
  // the turn's Gaussian in (1 + s)(x - r0) + c, still symmetric about that point).
  WireModel w;
  SynthProfile p = single_turn(2500, 0.25, w);
  ScanErrors e;
  e.drive_mm.assign(p.position_mm.size(), 0.4);
  apply_scan_errors(p, {2500}, {1.0}, 1, w, e);
  CHECK(signal_centroid(p) - 2500 == Approx(-0.4).epsilon(1e-7));
  const double c = 0.3, sl = 0.02;
  e.drive_mm.clear();
  for (double x : p.position_mm) e.drive_mm.push_back(c + sl * (x - 2500));
  apply_scan_errors(p, {2500}, {1.0}, 1, w, e);
  CHECK(signal_centroid(p) - 2500 == Approx(-c / (1 + sl)).epsilon(1e-7));
  // Drive and readout errors add: the wire is at x + drive + readout.
  e.drive_mm.assign(p.position_mm.size(), 0.25);
  e.readout_mm.assign(p.position_mm.size(), -0.1);
  apply_scan_errors(p, {2500}, {1.0}, 1, w, e);
  CHECK(signal_centroid(p) - 2500 == Approx(-0.15).epsilon(1e-7));

  // In a synthesis: a drive error far longer than a turn is wide moves each turn's peak by minus
  // its value there (truth.json's drive_mm), with everything else the same (the same bunch,
  // baseline: the peaks of the run without it are the reference; no wire noise, which stays put
  // while the signal moves). Tolerance 0.01 mm: over a peak's +-10 mm the drive changes by
  // 0.3 sqrt(2 * 10 / 1e5) = 0.004 mm rms; the rest is the centroid window's grid position.
  Machine m = iso_machine();
  SynthSettings s = quick_settings(12, 200);
  s.phases = false;
  s.drift = DriftModel{0, 0, 0};
  s.wire.electronic_nA = s.wire.shot_nA = s.wire.baseline_drift_nA = 0;  // the signal alone
  const SynthResult off = synthesize(m, s);
  s.scan.drive_mm = 0.3;
  s.scan.drive_corr_mm = 1e5;
  const SynthResult on = synthesize(m, s);
  // Centroids over +-10 mm (5 turn widths: a narrower window cuts the turn's tails by amounts
  // that change when the turn moves against the grid; the turns are 25-45 mm apart).
  const auto p0 = find_peaks(off.profiles[0], 0.2, 10.0), p1 = find_peaks(on.profiles[0], 0.2, 10.0);
  REQUIRE(p0.size() == off.centroids.size());
  REQUIRE(p1.size() == p0.size());
  const nlohmann::json t = truth_json(m, s, on);
  REQUIRE(t["turns"]["P0"].size() == p0.size());
  double moved = 0;
  for (size_t i = 0; i < p0.size(); ++i) {
    const double d = t["turns"]["P0"][i]["drive_mm"].get<double>();
    CAPTURE(i, p0[i], p1[i], d);
    CHECK(p1[i] - p0[i] == Approx(-d).margin(0.01));
    moved = std::max(moved, std::fabs(d));
  }
  CHECK(moved > 0.05);  // the drawn drive error moved some turn visibly (it is 0.3 mm rms)
  // Nothing else changed: the bunch, the drift, the baseline.
  CHECK(on.centroids.size() == off.centroids.size());
  for (size_t i = 0; i < on.centroids.size(); ++i) CHECK(on.centroids[i].r_mm == off.centroids[i].r_mm);
  CHECK(on.profiles[0].baseline_nA == off.profiles[0].baseline_nA);
}

TEST_CASE("synth: readout jitter of known rms scatters a turn's centroid as predicted", "[synth]") {
  // Each reading k records x_k while the wire is at x_k + e_k, e_k independent of rms eps. The
  // centroid of a Gaussian turn S of rms s read every step moves to first order by
  //   dc = sum x_k S'(x_k) e_k / sum S(x_k),  so  var = eps^2 sum x^2 S'^2 / (sum S)^2
  //      = eps^2 * 3 step / (8 sqrt(pi) s)
  // (sums as integrals: sum x^4/s^4 S^2 = A^2 3 sqrt(pi) s / (4 step), sum S = A sqrt(2 pi) s / step).
  // For eps = 0.1, s = 1, step = 0.5: 0.0325 mm. Over N = 800 seeds the rms of the centroids has
  // a relative standard error 1/sqrt(2N) = 2.5%; the bound, 10%, is 4 of them and leaves 1% for
  // the second order in eps/s. Their mean (no bias) has standard error 0.0325/sqrt(800) = 0.0012.
  WireModel w;
  const double step = 0.5, h = 1.0, eps = 0.1;
  SynthProfile p = single_turn(2200, step, w);
  const double s = std::sqrt(h * h + w.wire_mm * w.wire_mm / 12);
  const double want = eps * std::sqrt(3 * step / (8 * std::sqrt(kPi) * s));
  ScanErrorModel sm;
  sm.readout_mm = eps;
  const int N = 800;
  double ss = 0, sum = 0;
  for (int seed = 1; seed <= N; ++seed) {
    const ScanErrors e = draw_scan_errors(sm, p.position_mm, static_cast<std::uint64_t>(seed), 0);
    REQUIRE(e.readout_mm.size() == p.position_mm.size());
    apply_scan_errors(p, {2200}, {h}, 1, w, e);
    const double d = signal_centroid(p) - 2200;
    ss += d * d;
    sum += d;
  }
  CAPTURE(want, std::sqrt(ss / N), sum / N);
  CHECK(std::sqrt(ss / N) == Approx(want).epsilon(0.10));
  CHECK(std::fabs(sum / N) < 4 * want / std::sqrt(N));
}

TEST_CASE("synth: scan errors are the same for a seed, on any thread count, and change nothing else", "[synth]") {
  Machine m = iso_machine();
  SynthSettings s = quick_settings(12, 48);
  s.phases = false;
  s.scan = synth_preset("paper").scan;
  REQUIRE(s.scan.active());
  s.threads = 1;
  const SynthResult a = synthesize(m, s);
  s.threads = 3;
  const SynthResult b = synthesize(m, s);
  CHECK(a.profiles.at(0).intensity == b.profiles.at(0).intensity);
  CHECK(a.profiles[0].scan.drive_mm == b.profiles[0].scan.drive_mm);
  CHECK(a.profiles[0].scan.drive_mm.size() == a.profiles[0].position_mm.size());
  CHECK(a.profiles[0].scan.readout_mm.size() == a.profiles[0].position_mm.size());
  CHECK(a.profiles[0].scan.intensity_factor.size() == a.profiles[0].position_mm.size());
  s.seed = 2;
  const SynthResult c = synthesize(m, s);
  CHECK(c.profiles[0].scan.drive_mm != a.profiles[0].scan.drive_mm);
  CHECK(c.profiles[0].intensity != a.profiles[0].intensity);
  // Each source and each probe has its own stream: another probe draws other errors, and the
  // three sources of one probe differ.
  std::vector<double> x;
  for (int k = 0; k < 200; ++k) x.push_back(0.5 * k);
  ScanErrorModel all;
  all.intensity_rel = 0.1;
  all.drive_mm = 0.1;
  all.readout_mm = 0.1;
  all.intensity_corr_mm = all.drive_corr_mm = 0;  // all white: the same numbers if they shared a stream
  const ScanErrors e0 = draw_scan_errors(all, x, 5, 0), e1 = draw_scan_errors(all, x, 5, 1);
  auto far = [](const std::vector<double>& u, const std::vector<double>& v, double shift) {
    double d = 0;  // largest difference of u - shift and v
    for (size_t k = 0; k < u.size(); ++k) d = std::max(d, std::fabs(u[k] - shift - v[k]));
    return d;
  };
  CHECK(far(e0.drive_mm, e1.drive_mm, 0) > 0.1);
  CHECK(far(e0.drive_mm, e0.readout_mm, 0) > 0.1);
  CHECK(far(e0.intensity_factor, e0.drive_mm, 1) > 0.1);
  // Switching them on leaves the bunch, the drift and the baseline of the run alone.
  s.seed = 1;
  s.threads = 1;
  SynthSettings plain = s;
  plain.scan = ScanErrorModel{};
  const SynthResult d = synthesize(m, plain);
  CHECK(d.drift.dr_mm == a.drift.dr_mm);
  CHECK(d.profiles[0].drift_nA == a.profiles[0].drift_nA);
  REQUIRE(d.centroids.size() == a.centroids.size());
  for (size_t i = 0; i < d.centroids.size(); ++i) CHECK(d.centroids[i].r_mm == a.centroids[i].r_mm);
}

TEST_CASE("synth: presets, their overrides and what truth.json records", "[synth]") {
  const SynthPreset paper = synth_preset("paper"), none = synth_preset("none");
  CHECK(paper.name == "paper");
  CHECK(paper.scan.active());
  // The paper preset moves part of the repeatability from the drift to the scan.
  CHECK(paper.drift.r_mm < none.drift.r_mm);
  CHECK(paper.drift.pr_mrad < none.drift.pr_mrad);
  CHECK(paper.scan.drive_mm > 0);
  std::string msg;
  CHECK(error_code([] { synth_preset("papers"); }, &msg) == 64);
  CHECK_THAT(msg, Catch::Contains("--scan-errors") && Catch::Contains("papers"));
  const auto names = synth_preset_names();
  CHECK(std::find(names.begin(), names.end(), "paper") != names.end());

  // Overrides take the preset's place one by one; --no-drift zeroes the drift of any preset.
  SynthOptions o;
  o.scan_errors = "paper";
  o.drive_mm = 0.11;
  o.drift_r_mm = 0.2;
  SynthPreset got = synth_models(o);
  CHECK(got.name == "paper");
  CHECK(got.scan.drive_mm == 0.11);
  CHECK(got.scan.readout_mm == paper.scan.readout_mm);
  CHECK(got.scan.intensity_rel == paper.scan.intensity_rel);
  CHECK(got.drift.r_mm == 0.2);
  CHECK(got.drift.pr_mrad == paper.drift.pr_mrad);
  o.no_drift = true;
  got = synth_models(o);
  CHECK(got.drift.r_mm == 0);
  CHECK(got.drift.voltage_rel == 0);
  SynthOptions plain;
  plain.readout_mm = 0.02;
  got = synth_models(plain);
  CHECK(got.name == "none");
  CHECK(got.scan.readout_mm == 0.02);
  CHECK(got.scan.drive_mm == 0);
  CHECK(got.drift.r_mm == none.drift.r_mm);

  // truth.json: the settings and the preset's name, each probe's realized rms, each turn's drive
  // error; without scan errors, none of it (the file of a run without them is unchanged).
  Machine m = iso_machine();
  SynthSettings s = quick_settings(6, 16);
  s.phases = false;
  s.scan = paper.scan;
  s.drift = paper.drift;
  s.preset = "paper";
  const SynthResult r = synthesize(m, s);
  const nlohmann::json t = truth_json(m, s, r);
  REQUIRE(t.contains("scan_errors"));
  CHECK(t["scan_errors"]["preset"] == "paper");
  CHECK(t["scan_errors"]["drive_mm"].get<double>() == paper.scan.drive_mm);
  CHECK(t["scan_errors"]["drive_corr_mm"].get<double>() == paper.scan.drive_corr_mm);
  CHECK(t["scan_errors"]["readout_mm"].get<double>() == paper.scan.readout_mm);
  CHECK(t["scan_errors"]["intensity_rel"].get<double>() == paper.scan.intensity_rel);
  CHECK(t["scan_errors"]["intensity_corr_mm"].get<double>() == paper.scan.intensity_corr_mm);
  CHECK(t["scan_errors"]["profiles"]["P0"]["drive_rms_mm"].get<double>() > 0);
  CHECK(t["drift"]["model"]["r_mm"].get<double>() == paper.drift.r_mm);
  for (const auto& turn : t["turns"]["P0"]) CHECK(turn.contains("drive_mm"));
  std::ostringstream os;
  write_synth_profile(os, r.profiles[0], s.wire, s.seed, false, s.scan, s.preset);
  CHECK_THAT(os.str(), Catch::Contains("# scan errors: preset=paper"));
  s.scan = ScanErrorModel{};
  s.preset = "none";
  const SynthResult r0 = synthesize(m, s);
  const nlohmann::json t0 = truth_json(m, s, r0);
  CHECK_FALSE(t0.contains("scan_errors"));
  for (const auto& turn : t0["turns"]["P0"]) CHECK_FALSE(turn.contains("drive_mm"));
  std::ostringstream os0;
  write_synth_profile(os0, r0.profiles[0], s.wire, s.seed, false, s.scan, s.preset);
  CHECK_THAT(os0.str(), !Catch::Contains("scan errors"));
}
