// Bunches: Gaussian generation (moments, truncation, determinism), offsets to start states,
// thread-count independence, centroids and probe histograms.
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <numeric>

#include "../support.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/track/bunch.hpp"

using namespace turnfit;
using turnfit::test::error_code;
using turnfit::test::test_file;

namespace {

Bunch twiss_bunch() {
  Bunch b;
  b.emittance_r_mm_mrad = 2.0;
  b.beta_r_m = 3.0;
  b.alpha_r = 1.5;
  b.emittance_z_mm_mrad = 0.5;
  b.beta_z_m = 8.0;
  b.sigma_E_MeV = 0.1;
  b.sigma_phase_deg = 2.0;
  b.cutoff_sigma = 3;
  return b;
}

/// Variance of a standard normal truncated to |u| <= c: 1 - 2 c phi(c) / (2 Phi(c) - 1).
double truncated_variance(double c) {
  const double phi = std::exp(-0.5 * c * c) / std::sqrt(2 * kPi);
  return 1 - 2 * c * phi / std::erf(c / std::sqrt(2.0));
}

}  // namespace

TEST_CASE("bunch: Gaussian moments follow the Twiss parameters, truncated at the cutoff", "[bunch]") {
  const Bunch b = twiss_bunch();
  const size_t n = 200000;
  const auto offs = gaussian_bunch(b, n, 7);
  double xx = 0, xpxp = 0, xxp = 0, zz = 0, ee = 0, pp = 0, xmax = 0, emax = 0;
  for (const auto& o : offs) {
    xx += o.dr_mm * o.dr_mm;
    xpxp += o.dpr_mrad * o.dpr_mrad;
    xxp += o.dr_mm * o.dpr_mrad;
    zz += o.dz_mm * o.dz_mm;
    ee += o.dE_MeV * o.dE_MeV;
    pp += o.dphase_deg * o.dphase_deg;
    xmax = std::max(xmax, std::fabs(o.dr_mm));
    emax = std::max(emax, std::fabs(o.dE_MeV));
  }
  const double k = truncated_variance(3.0);  // 0.9733
  // Twiss: <x^2> = eps beta, <x'^2> = eps gamma_T = eps (1 + alpha^2) / beta, <x x'> = -eps alpha
  // (each times k for the truncation). Tolerance: 4 standard errors of the estimate, so that
  // it stays below half the truncation's 2.7 % (a bunch cut at the wrong sigma, or not cut, fails):
  // a variance's relative error is sqrt(2/n) = 0.32 % (less for the truncated normal, whose
  // kurtosis is below 3), a covariance's sqrt((1 + rho^2)/n)/|rho| = 0.35 % for
  // rho = -alpha/sqrt(1 + alpha^2) = -0.83.
  const double var_tol = 4 * std::sqrt(2.0 / n);
  const double rho = -1.5 / std::sqrt(1 + 1.5 * 1.5);
  const double cov_tol = 4 * std::sqrt((1 + rho * rho) / n) / std::fabs(rho);
  REQUIRE(var_tol < 0.5 * (1 - k));
  CHECK(xx / n == Approx(k * 2.0 * 3.0).epsilon(var_tol));
  CHECK(xpxp / n == Approx(k * 2.0 * (1 + 1.5 * 1.5) / 3.0).epsilon(var_tol));
  CHECK(xxp / n == Approx(-k * 2.0 * 1.5).epsilon(cov_tol));
  CHECK(zz / n == Approx(k * 0.5 * 8.0).epsilon(var_tol));
  CHECK(ee / n == Approx(k * 0.01).epsilon(var_tol));
  CHECK(pp / n == Approx(k * 4.0).epsilon(var_tol));
  // The cutoff bounds each normal variate: x = sqrt(eps beta) u1, |u1| <= 3.
  CHECK(xmax <= 3 * std::sqrt(2.0 * 3.0) + 1e-12);
  CHECK(emax <= 3 * 0.1 + 1e-12);
  CHECK(xmax > 2.5 * std::sqrt(2.0 * 3.0));  // the tails are really there
}

TEST_CASE("bunch: particle i depends only on the seed and i", "[bunch]") {
  const Bunch b = twiss_bunch();
  const auto a = gaussian_bunch(b, 100, 42), c = gaussian_bunch(b, 37, 42), d = gaussian_bunch(b, 100, 43);
  for (size_t i = 0; i < c.size(); ++i) {
    CHECK(a[i].dr_mm == c[i].dr_mm);
    CHECK(a[i].dphase_deg == c[i].dphase_deg);
  }
  size_t same = 0;
  for (size_t i = 0; i < a.size(); ++i) same += a[i].dr_mm == d[i].dr_mm;
  CHECK(same == 0);
  // Neighbouring particles are not correlated (a bad per-index seeding would show here).
  double s = 0, s2 = 0;
  const auto big = gaussian_bunch(b, 20000, 1);
  for (size_t i = 0; i + 1 < big.size(); ++i) {
    s += big[i].dr_mm * big[i + 1].dr_mm;
    s2 += big[i].dr_mm * big[i].dr_mm;
  }
  // Lag-1 autocorrelation of independent samples: standard error 1/sqrt(n) = 0.007; 0.03 is
  // 4 of them.
  CHECK(std::fabs(s / s2) < 0.03);
}

TEST_CASE("bunch: offsets become start states around the injection", "[bunch]") {
  Injection inj;
  inj.energy_MeV = 72;
  inj.r_mm = 2000;
  inj.pr_betagamma = 0.01;
  inj.phi_deg = 30;
  const double mass = 938.27208816, f = 50.65;
  const ParticleState ref = injection_state(inj, mass);
  BunchOffset o;
  const ParticleState same = offset_state(inj, mass, f, o);
  CHECK(same.x == ref.x);
  CHECK(same.px == ref.px);
  o.dE_MeV = 1.5;
  o.dr_mm = 3;
  o.dphase_deg = 36;
  const ParticleState s = offset_state(inj, mass, f, o);
  CHECK(kinetic_energy(s, mass) == Approx(73.5).epsilon(1e-12));
  CHECK(std::hypot(s.x, s.y) == Approx(2.003).epsilon(1e-12));
  // 36 deg of a 50.65 MHz RF period later.
  CHECK(s.t - ref.t == Approx(0.1 / (f * 1e6)).epsilon(1e-12));
  // p_r / p is kept (no angle offset): the angle does not change with the energy.
  const double P = std::sqrt(s.px * s.px + s.py * s.py), P0 = std::sqrt(ref.px * ref.px + ref.py * ref.py);
  const double th = 30 * kPi / 180;
  CHECK((s.px * std::cos(th) + s.py * std::sin(th)) / P ==
        Approx((ref.px * std::cos(th) + ref.py * std::sin(th)) / P0).epsilon(1e-12));
  o = BunchOffset();
  o.dE_MeV = -80;
  CHECK(error_code([&] { offset_state(inj, mass, f, o); }) == 65);
  o = BunchOffset();
  o.dphase_deg = 1;
  CHECK(error_code([&] { offset_state(inj, mass, 0, o); }) == 65);
}

TEST_CASE("bunch: files of offsets: any subset of the columns, strict numbers", "[bunch]") {
  const test::TempDir tmp;  // removed again at the end (a mkdtemp folder here was left behind by every run)
  const std::string dir = tmp.path;
  auto write = [&](const std::string& name, const std::string& text) {
    std::ofstream(dir + "/" + name) << text;
    return dir + "/" + name;
  };
  const BunchFile file = read_bunch_file(write("ok.csv", "# two particles\ndE_MeV,dr_mm\n0.5,1\n-0.5,-1\n"));
  const auto& offs = file.offsets;
  REQUIRE(offs.size() == 2);
  CHECK(file.lines == std::vector<long>{3, 4});
  CHECK(offs[0].dE_MeV == 0.5);
  CHECK(offs[1].dr_mm == -1);
  CHECK(offs[1].dpr_mrad == 0);
  std::string msg;
  CHECK(error_code([&] { read_bunch_file(write("bad.csv", "dr_mm,dx\n1,2\n")); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("unknown column 'dx'"));
  CHECK(error_code([&] { read_bunch_file(write("nan.csv", "dr_mm\n1\nnan\n")); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains(":3"));
  CHECK(error_code([&] { read_bunch_file(write("empty.csv", "dr_mm\n")); }) == 65);
  CHECK(error_code([&] { read_bunch_file(dir + "/missing.csv"); }) == 66);
  // A row no particle can start from is named by its file and line (the probe of issue 18 had
  // only "particle 1", and no file).
  Injection inj;
  inj.energy_MeV = 72;
  inj.r_mm = 2000;
  const BunchFile starved = read_bunch_file(write("starved.csv", "dE_MeV\n0.5\n\n-80\n"));
  CHECK(offset_states(inj, 938.272, 50.65, starved, 1).size() == 1);  // the bad row not reached
  CHECK(error_code([&] { offset_states(inj, 938.272, 50.65, starved); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("starved.csv:4: ") && Catch::Contains("no kinetic energy"));
  CHECK(error_code([&] { offset_states(inj, 938.272, 50.65, std::vector<BunchOffset>(starved.offsets)); }, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("(particle 1)"));
}

TEST_CASE("bunch: results do not depend on the thread count, a zero bunch is the reference particle",
          "[bunch]") {
  Machine mach = load_machine(test_file("machine/bunch/iso.json"));
  TrackModel model = make_track_model(mach);
  TrackSettings st;
  st.turns = 12;
  const auto offs = gaussian_bunch(*mach.bunch, 40, 3);
  std::vector<ParticleState> starts;
  for (const auto& o : offs) starts.push_back(offset_state(*mach.injection, mach.particle.mass_MeV, model.rf_MHz, o));
  const BunchResult a = track_bunch(model, starts, st, 1), b = track_bunch(model, starts, st, 2);
  REQUIRE(a.centroids.size() == b.centroids.size());
  REQUIRE(a.centroids.size() == 12);  // injected on the probe: turn N is the N-th return
  for (size_t i = 0; i < a.centroids.size(); ++i) {
    CHECK(a.centroids[i].r_mm == b.centroids[i].r_mm);  // bit for bit
    CHECK(a.centroids[i].r_rms_mm == b.centroids[i].r_rms_mm);
    CHECK(a.centroids[i].particles == 40);
  }
  CHECK(a.histograms[0].counts == b.histograms[0].counts);
  const auto total = std::accumulate(a.histograms[0].counts.begin(), a.histograms[0].counts.end(), std::uint64_t{0});
  CHECK(total + a.histograms[0].outside == 40 * 12);
  CHECK(a.particle_turns == Approx(40 * 12));
  CHECK(a.lost.empty());

  // The same reference particle 5 times: centroids are its crossings, spread zero.
  std::vector<ParticleState> refs(5, injection_state(*mach.injection, mach.particle.mass_MeV));
  std::vector<TurnRecord> single;
  track_particle(model, refs[0], st, single);
  const BunchResult r = track_bunch(model, refs, st, 2);
  REQUIRE(r.centroids.size() == single.size());
  for (size_t i = 0; i < single.size(); ++i) {
    CHECK(r.centroids[i].r_mm == Approx(single[i].r_mm).epsilon(1e-14));
    CHECK(r.centroids[i].t_ns == Approx(single[i].t_ns).epsilon(1e-14));
    CHECK(r.centroids[i].phase_deg == Approx(single[i].phase_deg).epsilon(0).margin(1e-9));
    CHECK(r.centroids[i].r_rms_mm < 1e-9);
  }
  // Each crossing falls in the bin holding its radius.
  const ProbeHistogram& h = r.histograms[0];
  for (const auto& t : single) {
    const size_t k = static_cast<size_t>(std::floor((t.r_mm - h.lo_mm) / h.step_mm));
    CHECK(h.counts[k] == 5);
  }
}

TEST_CASE("bunch: particles that leave the map are counted and reported", "[bunch]") {
  Machine mach = load_machine(test_file("machine/bunch/iso.json"));
  TrackModel model = make_track_model(mach);
  TrackSettings st;
  st.turns = 5;
  BunchOffset in, out;
  out.dE_MeV = 400;  // its circle reaches beyond the map's outer edge at 4.6 m
  std::vector<ParticleState> starts = {offset_state(*mach.injection, mach.particle.mass_MeV, model.rf_MHz, in),
                                       offset_state(*mach.injection, mach.particle.mass_MeV, model.rf_MHz, out)};
  const BunchResult r = track_bunch(model, starts, st, 2);
  REQUIRE(r.lost.size() == 1);
  CHECK(r.lost[0].first == 1);
  CHECK_THAT(r.lost[0].second.status, Catch::Contains("left the field map"));
  CHECK(r.centroids.front().particles == 1);
}

TEST_CASE("bunch machine: N turns give N crossings of the probe on the injection azimuth", "[bunch][track]") {
  // 11.25 deg map cells divided into 12 steps: the last grid node lands within rounding of the
  // end of the run, which once stopped a hair short of the probe.
  Machine mach = load_machine(test_file("machine/bunch/iso.json"));
  TrackModel model = make_track_model(mach);
  for (int n : {1, 19, 20, 21, 33}) {
    for (const char* integ : {"azimuth", "rk4"}) {
      TrackSettings st;
      st.integrator = integ;
      st.turns = n;
      std::vector<TurnRecord> turns;
      track_particle(model, injection_state(*mach.injection, mach.particle.mass_MeV), st, turns);
      INFO(integ << ", " << n << " turns");
      CHECK(turns.size() == static_cast<size_t>(n));
    }
  }
}

TEST_CASE("bunch: machine-file validation of the bunch block", "[bunch][machine]") {
  nlohmann::json doc = read_json(test_file("machine/bunch/iso.json"));
  auto code_with = [&](const std::string& ptr, const nlohmann::json& v, std::string* msg = nullptr) {
    nlohmann::json d = doc;
    d[nlohmann::json::json_pointer(ptr)] = v;
    return error_code([&] { machine_from_json(d, "m.json", test_file("machine/bunch")); }, msg);
  };
  std::string msg;
  CHECK(code_with("/bunch/cutoff_sigma", 0.1, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("/bunch/cutoff_sigma"));
  CHECK(code_with("/bunch/cutoff_sigma", 0) == 0);
  CHECK(code_with("/bunch/beta_r_m", 0, &msg) == 65);  // an emittance without its beta
  CHECK_THAT(msg, Catch::Contains("/bunch/beta_r_m"));
  CHECK(code_with("/bunch/sigma_E_MeV", -1) == 65);
  CHECK(code_with("/bunch/emittance_x", 1, &msg) == 65);
  CHECK_THAT(msg, Catch::Contains("unknown key"));
  CHECK(code_with("/tracking/step_deg", 1e-5) == 65);
  CHECK(code_with("/tracking/step_deg", 46) == 65);
  CHECK(code_with("/tracking/step_deg", 0.5) == 0);
}

TEST_CASE("bunch: histogram bins span the radii of an offset probe", "[bunch]") {
  TrackModel m;
  ProbeLine p;
  p.a_m = 0.6;
  p.s_min_m = 2.13;
  p.s_max_m = 4.6;
  p.step_m = 0.5e-3;
  p.shift_m = 0.002;
  m.probes.push_back(p);
  const auto h = empty_histograms(m);
  // Recorded radius = true radius - shift, true radius = |(s + shift, a)|.
  CHECK(h[0].lo_mm == Approx(std::hypot(2132.0, 600.0) - 2).epsilon(1e-12));
  const double hi = std::hypot(4602.0, 600.0) - 2;
  CHECK(h[0].counts.size() == static_cast<size_t>(std::ceil((hi - h[0].lo_mm) / 0.5 - 1e-9)));
  TurnRecord t;
  t.r_mm = h[0].lo_mm + 0.75;  // second bin
  std::vector<ProbeHistogram> hs = h;
  add_crossing(hs, t);
  CHECK(hs[0].counts[1] == 1);
  t.r_mm = h[0].lo_mm - 0.1;
  add_crossing(hs, t);
  CHECK(hs[0].outside == 1);
}
