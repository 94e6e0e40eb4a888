// What a probe measures is the bunch's centre (issue 15): the bunch quadrature's moments, the
// centroid shift against a fine quadrature of the phase spread, and the problem's "bunch" key.
#include <catch2/catch.hpp>

#include <cmath>
#include <map>
#include <vector>

#include "../support.hpp"
#include "ring8_problem.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/track/bunch.hpp"

using namespace turnfit;
using turnfit::test::TempDir;
using turnfit::test::load_turn_problem;
using turnfit::test::ring8;
using turnfit::test::turns_as_peaks;

namespace {

/// ring8's map and cavity profiles beside a machine file written into tmp.
void copy_ring8_files(const TempDir& tmp) {
  for (const char* f : {"field.map", "main-cavity.dat", "flattop-cavity.dat"})
    tmp.file(f, std::string(std::istreambuf_iterator<char>(std::ifstream(ring8(f)).rdbuf()), {}));
}

double sum_w(const std::vector<QuadratureNode>& q, double (*f)(const BunchOffset&)) {
  double s = 0;
  for (const auto& n : q) s += n.weight * f(n.offset);
  return s;
}

}  // namespace

TEST_CASE("bunch quadrature: the Gaussian's truncated moments, a sample's mean and covariance", "[bunch]") {
  Bunch b;
  b.emittance_r_mm_mrad = 1;
  b.beta_r_m = 3;
  b.alpha_r = 0.5;
  b.sigma_E_MeV = 0.03;
  b.sigma_phase_deg = 2;
  b.cutoff_sigma = 0;  // untruncated: the classic a = sqrt 3, weight 1/6
  auto q = bunch_quadrature(b);
  REQUIRE(q.size() == 9);  // centre and +-a on u1, u2 (radial), u5 (energy), u6 (phase)
  CHECK(q[1].weight == Approx(1.0 / 6));
  CHECK(sum_w(q, [](const BunchOffset&) { return 1.0; }) == Approx(1));
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dphase_deg; }) == Approx(0).margin(1e-15));
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dphase_deg * o.dphase_deg; }) == Approx(4));
  CHECK(sum_w(q, [](const BunchOffset& o) { return std::pow(o.dphase_deg, 4); }) == Approx(3 * 16));
  // Twiss: <dr^2> = eps beta, <dr dpr> = -eps alpha, <dpr^2> = eps (1 + alpha^2) / beta.
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dr_mm * o.dr_mm; }) == Approx(3));
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dr_mm * o.dpr_mrad; }) == Approx(-0.5));
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dpr_mrad * o.dpr_mrad; }) == Approx(1.25 / 3));

  // Truncated at 3 sigma as turnfit-synth draws it: E[u^2] = 1 - 2 c phi(c) / (2 Phi(c) - 1).
  b.cutoff_sigma = 3;
  q = bunch_quadrature(b);
  const double c = 3, phi = std::exp(-c * c / 2) / std::sqrt(2 * M_PI), inside = std::erf(c / std::sqrt(2.0));
  const double m2 = 1 - 2 * c * phi / inside, m4 = 3 - 2 * (c * c * c + 3 * c) * phi / inside;
  CHECK(sum_w(q, [](const BunchOffset& o) { return o.dE_MeV * o.dE_MeV; }) == Approx(0.03 * 0.03 * m2).epsilon(1e-9));
  CHECK(sum_w(q, [](const BunchOffset& o) { return std::pow(o.dE_MeV, 4); }) == Approx(std::pow(0.03, 4) * m4).epsilon(1e-9));
  // ... and the sample truncated the same way has those moments (200000 draws: 1 % at most).
  const std::vector<BunchOffset> s = gaussian_bunch(b, 200000, 5);
  double s2 = 0;
  for (const auto& o : s) s2 += o.dE_MeV * o.dE_MeV;
  CHECK(s2 / static_cast<double>(s.size()) == Approx(0.03 * 0.03 * m2).epsilon(0.01));

  // A sample: its mean and covariance exactly (a sheared, offset cloud with one empty column).
  std::vector<BunchOffset> sample;
  for (int i = 0; i < 50; ++i) {
    const double u = std::sin(1.3 * i), v = std::cos(0.7 * i * i);
    sample.push_back({0.2 + u, 0.5 * u - v, 0, 0, 0.01 * v, 3 * u * v});
  }
  const auto qs = bunch_quadrature(sample);
  CHECK(qs.size() == 7);  // three directions with spread
  auto mean = [&](double (*f)(const BunchOffset&)) {
    double m = 0;
    for (const auto& o : sample) m += f(o);
    return m / static_cast<double>(sample.size());
  };
  auto dr = [](const BunchOffset& o) { return o.dr_mm; };
  auto dph = [](const BunchOffset& o) { return o.dphase_deg; };
  auto dr_dph = [](const BunchOffset& o) { return o.dr_mm * o.dphase_deg; };
  auto dpr2 = [](const BunchOffset& o) { return o.dpr_mrad * o.dpr_mrad; };
  CHECK(sum_w(qs, dr) == Approx(mean(dr)));
  CHECK(sum_w(qs, dph) == Approx(mean(dph)).margin(1e-12));
  CHECK(sum_w(qs, dr_dph) == Approx(mean(dr_dph)));
  CHECK(sum_w(qs, dpr2) == Approx(mean(dpr2)));
  CHECK(bunch_quadrature(Bunch{}).empty());
}

TEST_CASE("centroid shift: ring8's phase spread, against a 41-point quadrature of the phase", "[bunch][turn-problem]") {
  // A bunch with only a phase spread: its centre is a one-dimensional mean over the phase,
  // which a fine trapezoid over the (3-sigma truncated) Gaussian gives to 1e-6 mm.
  TempDir tmp;
  nlohmann::json mj = nlohmann::json::parse(std::ifstream(ring8("machine.json")));
  mj["bunch"] = {{"sigma_phase_deg", 2.0}, {"cutoff_sigma", 3.0}};
  copy_ring8_files(tmp);
  const std::string machine = tmp.file("machine.json", mj.dump());
  const Machine m = load_machine(machine);
  const std::string peaks = turns_as_peaks(m, tmp, "peaks.csv");
  auto p = load_turn_problem(tmp.file("p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"machine.json\", "
                                                "\"peaks\": \"peaks.csv\", \"variables\": [\"vchange\"]}"));
  REQUIRE(p->bunch_mode() == "centroid");  // the default with a bunch
  REQUIRE(p->bunch_nodes().size() == 3);
  const CentroidShift& cs = p->current_centroid_shift();  // set at loading, at the start
  REQUIRE(cs.x == p->start());
  CHECK(cs.unknown == 0);

  const TrackModel model = make_track_model(m);
  const int n = 41;
  std::vector<std::map<std::pair<int, int>, double>> r(n);
  std::vector<double> w(n);
  parallel_for(n, 2, [&](size_t i, unsigned) {
    const double u = -3 + 6.0 * static_cast<double>(i) / (n - 1);
    w[i] = (i == 0 || i + 1 == n ? 0.5 : 1) * std::exp(-u * u / 2);
    BunchOffset o;
    o.dphase_deg = 2 * u;
    std::vector<TurnRecord> t;
    track_particle(model, offset_state(effective_injection(m), m.particle.mass_MeV, model.rf_MHz, o),
                   machine_track_settings(m), t);
    for (const auto& x : t) r[i][{x.probe, x.turn}] = x.r_mm;
  });
  double wsum = 0;
  for (double v : w) wsum += v;
  double worst = 0, largest = 0;
  size_t compared = 0;
  const auto& ref = r[n / 2];  // u = 0: the reference particle
  for (const auto& [key, r0] : ref) {
    double mean = 0;
    bool all = true;
    for (int i = 0; i < n && all; ++i) {
      auto it = r[i].find(key);
      all = it != r[i].end();
      if (all) mean += w[i] / wsum * it->second;
    }
    const auto& sh = cs.shift_mm[static_cast<size_t>(key.first)];
    if (!all || static_cast<size_t>(key.second) > sh.size()) continue;
    const double quad = sh[static_cast<size_t>(key.second - 1)];
    worst = std::max(worst, std::fabs(quad - (mean - r0)));
    largest = std::max(largest, std::fabs(mean - r0));
    ++compared;
  }
  INFO("largest shift " << largest << " mm, worst quadrature error " << worst << " mm");
  CHECK(compared > 150);
  CHECK(largest > 0.05);  // the centre runs well inside the reference particle
  CHECK(worst < 2e-4);    // three particles give the 41-point mean (measured 3.3e-5 mm)

  // The problem predicts the centre: its residuals against the reference particle's turns are the shift.
  const TurnPatternResult res = p->simulate(p->start());
  REQUIRE(res.ok);
  double dmax = 0;
  for (size_t i = 0; i < res.delta_mm.size(); ++i)
    if (res.matched[i]) dmax = std::max(dmax, std::fabs(res.delta_mm[i]));
  CHECK(dmax == Approx(cs.max_abs_mm).epsilon(1e-9));
}

TEST_CASE("turn-pattern problem: the \"bunch\" key", "[bunch][turn-problem]") {
  TempDir tmp;
  const std::string peaks = turns_as_peaks(load_machine(ring8("machine.json")), tmp, "peaks.csv");
  auto text = [&](const std::string& bunch) {
    return "{\"format\": \"turnfit-problem/1\", \"machine\": \"" + ring8("machine.json") + "\", \"peaks\": \"" + peaks +
           "\", \"variables\": [\"rinit\"]" + bunch + "}";
  };
  auto p = load_turn_problem(tmp.file("a.json", text(", \"bunch\": \"reference\"")));
  CHECK(p->bunch_mode() == "reference");
  CHECK(p->bunch_nodes().empty());
  const TurnPatternResult r = p->simulate(p->start());
  REQUIRE(r.ok);
  CHECK(r.objectives[0].value == 0);  // the reference particle's own turns
  CHECK(p->update_centroid_shift(p->start(), 1) == 0);

  auto c = load_turn_problem(tmp.file("b.json", text("")));
  CHECK(c->bunch_mode() == "centroid");  // ring8 has a bunch block
  CHECK(c->bunch_nodes().size() == 13);
  // The shift follows the design: moved, it changes a little; back at the start, not at all.
  std::vector<double> x = c->start();
  x[0] += 1.0;
  const double moved = c->update_centroid_shift(x, 2);
  INFO("rinit + 1 mm moves the shift by " << moved << " mm");
  CHECK(moved > 0);
  CHECK(moved < 0.05);
  CHECK(c->update_centroid_shift(x, 1) == 0);  // deterministic, whatever the thread count

  std::string msg;
  CHECK(test::error_code([&] { load_problem(tmp.file("c.json", text(", \"bunch\": \"centre\"")), "", -1); }, &msg) == 65);
  CHECK(msg.find("bunch") != std::string::npos);
  nlohmann::json mj = nlohmann::json::parse(std::ifstream(ring8("machine.json")));
  mj.erase("bunch");
  copy_ring8_files(tmp);
  tmp.file("nobunch.json", mj.dump());
  const std::string nb = "{\"format\": \"turnfit-problem/1\", \"machine\": \"nobunch.json\", \"peaks\": \"" + peaks +
                         "\", \"variables\": [\"rinit\"]";
  CHECK(load_turn_problem(tmp.file("d.json", nb + "}"))->bunch_mode() == "reference");
  CHECK(test::error_code([&] { load_problem(tmp.file("e.json", nb + ", \"bunch\": \"centroid\"}"), "", -1); }, &msg) == 65);
  CHECK(msg.find("no bunch") != std::string::npos);
}

TEST_CASE("centroid: a turn cut by the probe's end is the mean of the part the probe sees", "[bunch]") {
  // A probe records only the particles that cross it within its extent. With a radial
  // emittance alone a turn's crossings are (nearly) linear in the two variates, so a fine grid
  // over them gives the visible part's mean, which centroid_turns predicts from its 5 nodes by a
  // Gaussian cut at the end. Turns clear of the end keep the plain quadrature bit for bit.
  const Machine m = load_machine(ring8("machine.json"));
  TrackSettings st = machine_track_settings(m);
  st.turns = 9;
  Bunch b;
  b.emittance_r_mm_mrad = 4;
  b.beta_r_m = 3;
  b.cutoff_sigma = 0;  // untruncated, as the grid below
  const std::vector<QuadratureNode> nodes = bunch_quadrature(b);
  REQUIRE(nodes.size() == 5);
  const Injection inj = effective_injection(m);
  const TrackModel full = make_track_model(m);
  const ParticleState ref = injection_state(inj, m.particle.mass_MeV);
  const int turn = 6;

  // The grid: 41 x 41 points over u1, u2 in [-4, 4], Gaussian trapezoid weights.
  const int g = 41;
  std::vector<ParticleState> starts;
  std::vector<double> w;
  for (int i = 0; i < g; ++i)
    for (int j = 0; j < g; ++j) {
      const double u1 = -4 + 8.0 * i / (g - 1), u2 = -4 + 8.0 * j / (g - 1);
      BunchOffset o;
      o.dr_mm = std::sqrt(b.emittance_r_mm_mrad * b.beta_r_m) * u1;
      o.dpr_mrad = std::sqrt(b.emittance_r_mm_mrad / b.beta_r_m) * u2;
      starts.push_back(offset_state(inj, m.particle.mass_MeV, full.rf_MHz, o));
      w.push_back(std::exp(-0.5 * (u1 * u1 + u2 * u2)));
    }
  TrackModel unlimited = full;
  unlimited.probes[0].s_min_m = -1e9;
  unlimited.probes[0].s_max_m = 1e9;
  std::vector<std::vector<TurnRecord>> t(starts.size());
  std::vector<TrackEnd> ends(starts.size());
  parallel_for(2, 2, [&](size_t c, unsigned) {
    const size_t a = c * starts.size() / 2, e = (c + 1) * starts.size() / 2;
    track_particles(unlimited, starts.data() + a, e - a, st, t.data() + a, ends.data() + a);
  });
  auto crossing = [](const std::vector<TurnRecord>& v, int probe, int k) -> const TurnRecord* {
    for (const auto& x : v)
      if (x.probe == probe && x.turn == k) return &x;
    return nullptr;
  };
  double sw = 0, ms = 0, mr = 0, vs = 0;
  for (size_t i = 0; i < starts.size(); ++i) {
    const TurnRecord* x = crossing(t[i], 0, turn);
    REQUIRE(x);
    sw += w[i];
    ms += w[i] * x->s_mm;
    mr += w[i] * x->r_mm;
  }
  ms /= sw;
  mr /= sw;
  for (size_t i = 0; i < starts.size(); ++i) vs += w[i] / sw * std::pow(crossing(t[i], 0, turn)->s_mm - ms, 2);
  const double sd = std::sqrt(vs);
  INFO("RRI2 turn " << turn << ": mean s " << ms << " mm, spread " << sd << " mm");
  REQUIRE(sd > 1);

  const CentroidTurns plain = centroid_turns(full, ref, inj, m.particle.mass_MeV, nodes, st, 2);
  for (double cut : {0.3, -0.8, 1.6}) {
    // The probe ends `cut` spreads beyond the turn's mean.
    TrackModel cutm = full;
    cutm.probes[0].s_max_m = (ms + cut * sd) * 1e-3;
    double vw = 0, vr = 0;
    for (size_t i = 0; i < starts.size(); ++i) {
      const TurnRecord* x = crossing(t[i], 0, turn);
      if (x->s_mm > ms + cut * sd) continue;
      vw += w[i];
      vr += w[i] * x->r_mm;
    }
    vr /= vw;
    const CentroidTurns ct = centroid_turns(cutm, ref, inj, m.particle.mass_MeV, nodes, st, 2);
    const TurnRecord* c = nullptr;
    for (size_t k = 0; k < ct.reference.size(); ++k)
      if (ct.reference[k].probe == 0 && ct.reference[k].turn == turn) {
        c = &ct.centre[k];
        CHECK(ct.known[k]);
      }
    INFO("cut at " << cut << " spreads: the whole turn's mean r " << mr << ", the part seen " << vr);
    if (cut < 0) {
      // The reference particle itself is beyond the end: the probe has no turn to predict.
      CHECK(c == nullptr);
      continue;
    }
    REQUIRE(c);
    INFO("predicted " << c->r_mm);
    CHECK(std::fabs(vr - mr) > 0.05 * sd);                     // the cut matters ...
    CHECK(std::fabs(c->r_mm - vr) < 0.02 * std::fabs(vr - mr));  // ... and is predicted
    // The turns before are many spreads inside: the same records as with the whole extent.
    size_t same = 0;
    for (size_t k = 0; k < ct.reference.size(); ++k) {
      if (ct.reference[k].probe != 0 || ct.reference[k].turn >= turn) continue;
      for (size_t q = 0; q < plain.reference.size(); ++q)
        if (plain.reference[q].probe == 0 && plain.reference[q].turn == ct.reference[k].turn) {
          CHECK(ct.centre[k].r_mm == plain.centre[q].r_mm);
          ++same;
        }
    }
    CHECK(same == static_cast<size_t>(turn - 1));
  }
}
