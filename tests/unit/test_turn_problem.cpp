// The turn-pattern problem (issue 15): one thread pool for the library, models built from files
// read once, and the in-process evaluation equal to turnfit-track + turnfit-compare.
#include <catch2/catch.hpp>

#include <atomic>
#include <cmath>
#include <fstream>
#include <random>
#include <set>
#include <stdexcept>

#include "../support.hpp"
#include "ring8_problem.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/optimize/nsga2.hpp"
#include "turnfit/optimize/problem_file.hpp"
#include "turnfit/optimize/localsearch.hpp"
#include "turnfit/optimize/turn_problem.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;
using turnfit::test::TempDir;
using turnfit::test::load_turn_problem;
using turnfit::test::moved_ring8;
using turnfit::test::ring8;
using turnfit::test::turns_as_peaks;

namespace {

/// The nominal ring8 machine's own turns as a peaks file: the problem's start then matches exactly.
std::string nominal_peaks(const TempDir& tmp) { return turns_as_peaks(load_machine(ring8("machine.json")), tmp, "peaks.csv"); }

/// The peaks here are turnfit-track's turns, the reference particle's: "bunch": "reference"
/// unless `extra` says otherwise.
std::string problem_text(const std::string& peaks, const std::string& variables, const std::string& extra = "") {
  const std::string bunch = extra.find("\"bunch\"") == std::string::npos ? ", \"bunch\": \"reference\"" : "";
  return "{\"format\": \"turnfit-problem/1\", \"machine\": \"" + ring8("machine.json") + "\", \"peaks\": \"" + peaks +
         "\", \"variables\": " + variables + bunch + extra + "}";
}

}  // namespace

TEST_CASE("parallel_for: every index once on any thread count, the first exception rethrown", "[parallel]") {
  for (unsigned threads : {1u, 2u, 3u, 8u}) {
    std::vector<std::atomic<int>> hits(1000);
    parallel_for(hits.size(), threads, [&](size_t i, unsigned w) {
      CHECK(w < threads);
      hits[i]++;
    });
    for (auto& h : hits) CHECK(h.load() == 1);
  }
  parallel_for(0, 4, [](size_t, unsigned) { FAIL("no index in an empty range"); });
  std::atomic<int> after{0};
  CHECK_THROWS_WITH(parallel_for(100, 3,
                                 [&](size_t i, unsigned) {
                                   if (i == 5) throw std::runtime_error("item 5");
                                   ++after;
                                 }),
                    "item 5");
  CHECK(after.load() < 100);  // handing out stopped (exactly how many ran depends on timing)
  CHECK_THROWS_WITH(run_workers(2, [](unsigned w) {
                      if (w == 1) throw std::runtime_error("worker 1");
                    }),
                    "worker 1");
  CHECK(resolve_thread_count(3) == 3);
  CHECK(resolve_thread_count(0) >= 1);
}

TEST_CASE("model files read once build the same model: ring8's turns bit for bit", "[turn-problem]") {
  Machine m = load_machine(ring8("machine.json"));
  const ModelFiles files = read_model_files(m);
  REQUIRE(files.map);
  CHECK(files.profiles.size() == 2);  // main-cavity.dat and flattop-cavity.dat (each read once)
  const TrackSettings st = machine_track_settings(m);
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  std::vector<TurnRecord> a, b;
  track_particle(make_track_model(m), s0, st, a);
  track_particle(make_track_model(m, {}, &files), s0, st, b);
  REQUIRE(a.size() == b.size());
  REQUIRE(a.size() > 180);
  for (size_t i = 0; i < a.size(); ++i) {
    CHECK(a[i].r_mm == b[i].r_mm);  // the same inputs and code path: bit-identical
    CHECK(a[i].t_ns == b[i].t_ns);
  }
  // A main field other than the one read (another scale) is read again, not taken from `files`.
  m.field.scale = 1.001;
  const TrackModel scaled = make_track_model(m, {}, &files);
  FieldSample fa, fb;
  REQUIRE(scaled.map.sample(3.0, 0.1, fa));
  REQUIRE(files.map->sample(3.0, 0.1, fb));
  CHECK(fa.bz_T == Approx(1.001 * fb.bz_T).epsilon(1e-12));  // scaling is a product: exact to rounding
}

TEST_CASE("turn-pattern problem: the machine's own turns give zero, a set variable equals the same machine tracked",
          "[turn-problem]") {
  TempDir tmp;
  const std::string peaks = nominal_peaks(tmp);
  const std::string file =
      tmp.file("p.json", problem_text(peaks, "[\"rinit\", {\"name\": \"vmaincav2\", \"sigma\": 0.002}, \"tc05mb\"]",
                                      ", \"objectives\": [\"RRI2:1-16:linf\", \"RRL:l2\"]"));
  auto p = load_turn_problem(file);
  REQUIRE(p->n_variables() == 3);
  CHECK(p->n_objectives() == 2);
  CHECK(p->n_constraints() == 1);
  CHECK(p->variables()[1].sigma == 0.002);
  CHECK(p->sigma_mm().empty());  // none given: a fit estimates it
  const std::vector<double> x0 = p->start();
  Evaluation e0 = p->evaluate(x0);
  REQUIRE(e0.ok);
  // The start is the machine that made the peaks: every residual vanishes (the peaks carry 17 digits).
  CHECK(e0.f[0] == 0);
  CHECK(e0.f[1] == 0);
  CHECK(e0.g[0] == 0);

  // rinit + 0.8 mm: the same as setting it on the machine and tracking it (set_dvar, one at a time).
  std::vector<double> x = x0;
  x[0] += 0.8;
  const TurnPatternResult r = p->simulate(x);
  REQUIRE(r.ok);
  Machine m = load_machine(ring8("machine.json"));
  set_dvar(m, "rinit", x[0]);
  std::vector<TurnRecord> turns;
  track_particle(make_track_model(m), injection_state(effective_injection(m), m.particle.mass_MeV),
                 machine_track_settings(m), turns);
  REQUIRE(r.simulated.points.size() == turns.size());
  double worst = 0;
  for (const auto& t : turns) {
    const int q = r.simulated.probe_index(m.probes[static_cast<size_t>(t.probe)].name);
    REQUIRE(q >= 0);
    auto [b, end] = r.simulated.probe_range(q);
    bool found = false;
    for (size_t i = b; i < end; ++i)
      if (r.simulated.points[i].turn == t.turn) {
        CHECK(r.simulated.points[i].r_mm == t.r_mm);  // same machine, same code: bit-identical
        found = true;
      }
    CHECK(found);
  }
  for (size_t i = 0; i < r.delta_mm.size(); ++i)
    if (r.matched[i]) worst = std::max(worst, std::fabs(r.delta_mm[i]));
  CHECK(worst > 0.1);  // an injection 0.8 mm out starts a betatron oscillation the nominal lacks
  const Evaluation e = p->evaluate(x);
  REQUIRE(e.ok);
  CHECK(e.f[0] == Approx(r.objectives[0].value).epsilon(0));
}

TEST_CASE("turn-pattern problem: \"paper\" takes ring8's 48 variables, bounds from the file", "[turn-problem]") {
  TempDir tmp;
  const std::string peaks = nominal_peaks(tmp);
  auto p = load_turn_problem(tmp.file("p.json", problem_text(peaks, "\"paper\"")));
  CHECK(p->n_variables() == 48);
  CHECK(p->n_objectives() == 6);  // the paper's six by default
  auto q = load_turn_problem(
      tmp.file("q.json", problem_text(peaks, "[{\"name\": \"rinit\", \"lower\": 2040, \"upper\": 2050}]")));
  CHECK(q->lower()[0] == 2040);
  CHECK(q->upper()[0] == 2050);
  std::vector<double> x = {2049.5};  // inside the file's bounds, outside the machine's own (2044.08 +- 5 mm)
  CHECK(q->evaluate(x).ok);
  x = {2051};
  const Evaluation bad = q->evaluate(x);
  CHECK_FALSE(bad.ok);
  CHECK(bad.reason.find("outside its bounds") != std::string::npos);
}

TEST_CASE("turn-pattern problem: designs simulated together give what each gives alone, bit for bit",
          "[turn-problem]") {
  // A finite-difference Jacobian's designs go through simulate_many: their reference particles
  // share the grid steps (the group stepper, a model per design). 20 designs (two groups): the
  // start, every third of the 48 variables of "paper" moved (trim coils, voltages, phases,
  // probes, injection), the injection angle moved (its particle starts at another azimuth: a
  // group of its own), one design outside its bounds (refused, with simulate's reason) and one
  // that loses its particle.
  TempDir tmp;
  auto p = load_turn_problem(tmp.file("p.json", problem_text(nominal_peaks(tmp), "\"paper\"")));
  const std::vector<double> x0 = p->start();
  REQUIRE(x0.size() == 48);
  std::vector<std::vector<double>> xs = {x0};
  auto moved = [&](size_t j) {
    std::vector<double> x = x0;
    x[j] = x0[j] + 0.2 * (p->upper()[j] - x0[j]);
    return x;
  };
  for (size_t j = 0; j < x0.size(); j += 3) xs.push_back(moved(j));
  size_t phi = x0.size();
  for (size_t j = 0; j < x0.size(); ++j)
    if (p->variables()[j].name == "phiinit") phi = j;
  REQUIRE(phi < x0.size());
  REQUIRE(phi % 3 != 0);  // not among the designs above
  xs.push_back(moved(phi));
  std::vector<double> out_of_bounds = x0;
  out_of_bounds[0] = p->upper()[0] + 1;
  xs.push_back(out_of_bounds);
  std::vector<double> lost = x0;
  for (size_t j = 0; j < lost.size(); ++j)  // every coil at its upper bound: the turns run off the map
    if (p->variables()[j].name.rfind("tc", 0) == 0) lost[j] = p->upper()[j];
  xs.push_back(lost);
  REQUIRE(xs.size() == 20);
  const std::vector<TurnPatternResult> together = p->simulate_many(xs);
  REQUIRE(together.size() == xs.size());
  int failed = 0;
  for (size_t i = 0; i < xs.size(); ++i) {
    INFO("design " << i);
    const TurnPatternResult alone = p->simulate(xs[i]);
    REQUIRE(together[i].ok == alone.ok);
    CHECK(together[i].reason == alone.reason);
    failed += !alone.ok;
    if (!alone.ok) continue;
    CHECK(together[i].end.status == alone.end.status);
    REQUIRE(together[i].simulated.points.size() == alone.simulated.points.size());
    for (size_t k = 0; k < alone.simulated.points.size(); ++k)
      CHECK(together[i].simulated.points[k].r_mm == alone.simulated.points[k].r_mm);
    REQUIRE(together[i].delta_mm.size() == alone.delta_mm.size());
    // (A turn the design does not reach has no residual: NaN in both.)
    const auto same = [](double a, double b) { return a == b || (std::isnan(a) && std::isnan(b)); };
    for (size_t k = 0; k < alone.delta_mm.size(); ++k) CHECK(same(together[i].delta_mm[k], alone.delta_mm[k]));
    for (size_t k = 0; k < alone.objectives.size(); ++k)
      CHECK(same(together[i].objectives[k].value, alone.objectives[k].value));
    // Each moved design gives turns of its own (a lane that took another's model would not).
    if (i > 0 && i < 18) CHECK(together[i].delta_mm != together[0].delta_mm);
  }
  CHECK(failed == 1);
  CHECK(together[18].reason.find("outside its bounds") != std::string::npos);
  CHECK(together[19].end.lost);
}

TEST_CASE("turn-pattern problem: bad files are named with their key", "[turn-problem]") {
  TempDir tmp;
  const std::string peaks = nominal_peaks(tmp);
  auto code_and_message = [&](const std::string& text, std::string* msg) {
    const std::string f = tmp.file("bad.json", text);
    return test::error_code([&] { load_problem(f, "", -1); }, msg);
  };
  std::string msg;
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\", \"nosuchvar\"]"), &msg) == 65);
  CHECK(msg.find("variables/1") != std::string::npos);
  CHECK(msg.find("nosuchvar") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"objectives\": [\"RRX:1-5:linf\"]"), &msg) == 65);
  CHECK(msg.find("objectives") != std::string::npos);
  CHECK(msg.find("RRX") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"objectives\": [\"RRL:300-400:linf\"]"), &msg) == 65);
  CHECK(msg.find("objectives") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[{\"name\": \"rinit\", \"lower\": 2050, \"upper\": 2060}]"), &msg) == 65);
  CHECK(msg.find("outside") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"sigma_mm\": {\"RRL\": 0.1}"), &msg) == 65);
  CHECK(msg.find("sigma_mm/RRI2") != std::string::npos);
  CHECK(code_and_message(problem_text(tmp.path + "/none.csv", "[\"rinit\"]"), &msg) == 66);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"constraints\": [\"energy\"]"), &msg) == 65);
  CHECK(msg.find("constraints/0") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"scan_noise\": {\"drive_mm\": -0.1}"), &msg) == 65);
  CHECK(msg.find("scan_noise/drive_mm") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"scan_noise\": {\"drive_mm\": 0.3, \"corr\": 5}"), &msg) == 65);
  CHECK(msg.find("scan_noise/corr") != std::string::npos);
  CHECK(code_and_message(problem_text(peaks, "[\"rinit\"]", ", \"scan_noise\": {\"drive_mm\": 0.3, \"corr_mm\": 0}"), &msg) == 65);
  CHECK(msg.find("scan_noise/corr_mm") != std::string::npos);
  // A fit cannot estimate the independent sigma beside a correlated drive error: it says so.
  {
    const std::string f = tmp.file("sn.json", problem_text(peaks, "[\"rinit\"]", ", \"scan_noise\": {\"drive_mm\": 0.3}"));
    auto lp = load_problem(f, "", -1);
    auto* tp = dynamic_cast<TurnPatternProblem*>(lp.problem.get());
    REQUIRE(tp);
    CHECK(tp->scan_noise().drive_mm == 0.3);
    CHECK(tp->scan_noise().corr_mm == 10);
    LocalSearchSettings ls;
    ls.max_iterations = 1;
    CHECK(test::error_code([&] { local_search(*tp, tp->start(), ls); }, &msg) == 65);
    CHECK(msg.find("scan_noise needs sigma_mm") != std::string::npos);
  }
}

TEST_CASE("turn-pattern problem under NSGA-II: the same front on 1 and 2 threads", "[turn-problem]") {
  TempDir tmp;
  const std::string peaks = nominal_peaks(tmp);
  auto p = load_turn_problem(
      tmp.file("p.json", problem_text(peaks, "[\"rinit\", \"prinit\"]", ", \"objectives\": [\"RRI2:linf\", \"RRL:linf\"]")));
  Nsga2Settings s;
  s.population = 8;
  s.generations = 2;
  s.seed = 4;
  const Nsga2Result a = run_nsga2(*p, s, 1, {}, {});
  const Nsga2Result b = run_nsga2(*p, s, 2, {}, {});
  REQUIRE(a.population.size() == b.population.size());
  for (size_t i = 0; i < a.population.size(); ++i) {
    CHECK(a.population[i].x == b.population[i].x);
    CHECK(a.population[i].f == b.population[i].f);
  }
}

TEST_CASE("local search (LM): a noiseless truth with four settings changed comes back", "[turn-problem][localsearch]") {
  // The truth: ring8 with injection radius, angle, radial momentum and the main voltages'
  // common change moved by a fifth of their bound ranges; its own turns are the measurement
  // (noiseless, 17 digits). From the nominal machine the fit must return the truth's values:
  // they are determined (the turns depend on each), and without noise the only error left is
  // the convergence tolerance (relative cost change 1e-9).
  TempDir tmp;
  const std::vector<std::string> names = {"phiinit", "prinit", "rinit", "vchange"};
  std::vector<double> xt;
  const Machine truth = moved_ring8(names, {0.2, -0.2, 0.2, 0.2}, xt);
  const std::string peaks = turns_as_peaks(truth, tmp, "truth.csv");
  auto p = load_turn_problem(tmp.file("p.json", problem_text(peaks, "[\"phiinit\", \"prinit\", \"rinit\", \"vchange\"]",
                                                              ", \"sigma_mm\": 0.01")));
  LocalSearchSettings s;
  s.threads = 2;
  const LocalSearchResult r = local_search(*p, p->start(), s);
  CHECK(r.before.linf_mm > 1);
  CHECK(r.after.linf_mm < 1e-3);  // noiseless: a micrometre is far above the convergence limit
  for (size_t j = 0; j < names.size(); ++j) {
    CHECK(r.variables[j].determined);
    const double range = p->upper()[j] - p->lower()[j];
    CHECK(std::fabs(r.x[j] - xt[j]) < 1e-4 * range);  // 1e-4 of the range: far inside the 20 % moved
  }
  CHECK(r.sigma_source == "problem file (sigma_mm)");
  CHECK(r.evaluations > 0);
  // The polish never returns a design worse than the least-squares one.
  REQUIRE(r.x_minimax.size() == r.x.size());
  CHECK(r.minimax.linf_mm <= r.after.linf_mm);
  CHECK(r.minimax_evaluations > 0);
}

TEST_CASE("Lawson's minimax step: the Chebyshev solution of linear models", "[localsearch]") {
  // A constant fitted to 1, 2, 5: least squares gives 8/3 (worst 7/3), minimax the midrange 3
  // (worst 2). Residuals (model - data) r + J d with r = -data, J = 1.
  Eigen::MatrixXd J(3, 1);
  J << 1, 1, 1;
  Eigen::VectorXd r(3);
  r << -1, -2, -5;
  const Eigen::VectorXd d = lawson_minimax_step(J, r, 0, 2000);
  CHECK(d(0) == Approx(3).margin(1e-3));  // Lawson converges linearly: 2000 sweeps give ~1e-4
  // A line a + b t through (0, 0), (1, 1), (2, 0): the minimax line is 0.5 (the three residuals
  // equioscillate at 0.5); least squares gives 1/3 (worst 2/3).
  Eigen::MatrixXd A(3, 2);
  A << 1, 0, 1, 1, 1, 2;
  Eigen::VectorXd y(3);
  y << 0, -1, 0;  // r = -data
  const Eigen::VectorXd e = lawson_minimax_step(A, y, 0, 2000);
  CHECK(e(0) == Approx(0.5).margin(1e-3));
  CHECK(e(1) == Approx(0).margin(1e-3));
  CHECK((y + A * e).cwiseAbs().maxCoeff() == Approx(0.5).margin(1e-3));
  // The ridge shortens the step toward 0.
  const Eigen::VectorXd g = lawson_minimax_step(J, r, 1, 2000);
  CHECK(std::fabs(g(0)) < 3 - 0.1);
}

namespace {
// A least-squares fit of the columns J to data with noise e (residual z = e minus its projection),
// its covariance C = (J^T J)^-1 and the sandwich's ratio to it, per variable.
std::vector<double> hac_ratio(const Eigen::MatrixXd& J, const Eigen::VectorXd& e, size_t ndata,
                              const std::vector<std::pair<size_t, size_t>>& blocks, std::vector<double>& lag1,
                              std::vector<double>& bw) {
  const Eigen::MatrixXd C = (J.transpose() * J).inverse();
  const Eigen::VectorXd z = e - J * (C * (J.transpose() * e));
  const std::vector<double> zv(z.data(), z.data() + z.size());
  const Eigen::MatrixXd R = hac_covariance(C, J, zv, ndata, blocks, lag1, bw);
  std::vector<double> out;
  for (Eigen::Index j = 0; j < J.cols(); ++j) out.push_back(std::sqrt(R(j, j) / C(j, j)));
  return out;
}
}  // namespace

TEST_CASE("hac_covariance: white residuals keep the statistical sigma, AR(1) ones widen it as (1+rho)/(1-rho)",
          "[localsearch]") {
  std::mt19937_64 rng(20261130);
  std::normal_distribution<double> g(0, 1);
  std::vector<double> lag1, bw;
  // A mean and a slope fitted to 2000 turns of one probe.
  const Eigen::Index m = 2000;
  Eigen::MatrixXd J(m, 2);
  for (Eigen::Index i = 0; i < m; ++i) J.row(i) << 1, static_cast<double>(i) / static_cast<double>(m);
  Eigen::VectorXd white(m), ar(m);
  double prev = 0;
  const double rho = 0.8;
  for (Eigen::Index i = 0; i < m; ++i) {
    white(i) = g(rng);
    prev = rho * prev + std::sqrt(1 - rho * rho) * g(rng);  // unit variance, lag-1 correlation rho
    ar(i) = prev;
  }
  const std::vector<std::pair<size_t, size_t>> one = {{0, static_cast<size_t>(m)}};
  // White: the ratio is 1 within the sandwich's own scatter (a few percent at 2000 rows).
  std::vector<double> rw = hac_ratio(J, white, static_cast<size_t>(m), one, lag1, bw);
  REQUIRE(lag1.size() == 1);
  CHECK(std::fabs(lag1[0]) < 0.1);
  CHECK(bw[0] < 3);
  for (double r : rw) CHECK(r == Approx(1).margin(0.15));
  // AR(1), rho 0.8: the mean's variance is (1 + rho) / (1 - rho) = 9 times the independent
  // one's, so its sigma 3 times (the slope's likewise); Bartlett's kernel at Andrews' bandwidth
  // comes within about 15 % of that (it is biased low). Without the kernel (bandwidth 0) the
  // ratio would be near 1.
  std::vector<double> ra = hac_ratio(J, ar, static_cast<size_t>(m), one, lag1, bw);
  CHECK(lag1[0] == Approx(rho).margin(0.05));
  CHECK(bw[0] > 10);
  CHECK(ra[0] > 2.4);
  CHECK(ra[0] < 3.3);
  CHECK(ra[1] > 2.4);
  CHECK(ra[1] < 3.3);
  // Two probes, each correlated within: the blocks are summed apart. Half the rows each, the
  // same residual: the ratio stays that of each half's correlation (about 3), not more.
  const std::vector<std::pair<size_t, size_t>> two = {{0, static_cast<size_t>(m / 2)}, {static_cast<size_t>(m / 2), static_cast<size_t>(m)}};
  std::vector<double> r2 = hac_ratio(J, ar, static_cast<size_t>(m), two, lag1, bw);
  REQUIRE(lag1.size() == 2);
  CHECK(r2[0] > 2.2);
  CHECK(r2[0] < 3.3);
  // A prior row (after the data rows) counts by its information: a variable only the prior
  // holds keeps the prior's sigma whatever the data's residual.
  Eigen::MatrixXd Jp = Eigen::MatrixXd::Zero(m + 1, 3);
  Jp.topLeftCorner(m, 2) = J;
  Jp(m, 2) = 1;  // the third variable: its prior row alone, sigma 1
  Eigen::VectorXd e3(m + 1);
  e3.head(m) = ar;
  e3(m) = 0.3;
  std::vector<double> r3 = hac_ratio(Jp, e3, static_cast<size_t>(m), one, lag1, bw);
  CHECK(r3[2] == Approx(1).margin(1e-12));
  CHECK(r3[0] > 2.4);
  // Sizes that do not agree are a software error.
  CHECK_THROWS(hac_covariance(Eigen::MatrixXd::Identity(2, 2), J, std::vector<double>(3, 0.0), 3, one, lag1, bw));
}

TEST_CASE("hac_covariance: a residual that oscillates with a column widens that column's sigma as Monte Carlo does",
          "[localsearch]") {
  // Columns cos(w i) and sin(w i) at a fractional tune of 0.4 (w = 0.8 pi: the turns alternate),
  // fitted to noise resonant at w (AR(2) with poles r e^(+-iw), r = 0.9). The residual's lag-1
  // correlation is negative, so a bandwidth from the residual would be 0; each variable's
  // influence series is slow, and its sandwich sigma comes near the spread of the estimates
  // over many draws, several times the statistical sigma.
  const Eigen::Index m = 600;
  const double w = 0.8 * M_PI, r = 0.9;
  Eigen::MatrixXd J(m, 2);
  for (Eigen::Index i = 0; i < m; ++i) J.row(i) << std::cos(w * static_cast<double>(i)), std::sin(w * static_cast<double>(i));
  const Eigen::MatrixXd C = (J.transpose() * J).inverse();
  std::mt19937_64 rng(7);
  std::normal_distribution<double> g(0, 1);
  auto draw = [&] {
    Eigen::VectorXd e(m);
    double e1 = 0, e2 = 0;
    for (Eigen::Index i = -200; i < m; ++i) {  // 200 steps to forget the start
      const double v = 2 * r * std::cos(w) * e1 - r * r * e2 + g(rng);
      e2 = e1;
      e1 = v;
      if (i >= 0) e(i) = v;
    }
    return e;
  };
  // The estimates' spread over 400 draws (each scaled by its own residual variance, as the
  // fit's statistical sigma would be).
  const int draws = 400;
  double s2 = 0, ratio_sum = 0, stat_ratio_sum = 0, lag_sum = 0;
  std::vector<double> lag1, bw;
  const std::vector<std::pair<size_t, size_t>> one = {{0, static_cast<size_t>(m)}};
  for (int d = 0; d < draws; ++d) {
    const Eigen::VectorXd e = draw();
    const Eigen::VectorXd th = C * (J.transpose() * e);
    s2 += th(0) * th(0);
    const Eigen::VectorXd z = e - J * th;
    const double var = z.squaredNorm() / static_cast<double>(m - 2);
    const std::vector<double> zv(z.data(), z.data() + z.size());
    const Eigen::MatrixXd R = hac_covariance(C, J, zv, static_cast<size_t>(m), one, lag1, bw);
    ratio_sum += std::sqrt(R(0, 0));
    stat_ratio_sum += std::sqrt(C(0, 0) * var);
    lag_sum += lag1[0];
  }
  const double truth = std::sqrt(s2 / draws), hac = ratio_sum / draws, stat = stat_ratio_sum / draws;
  CHECK(lag_sum / draws < -0.3);  // the residual alternates
  CHECK(stat < 0.5 * truth);      // the statistical sigma claims far too much
  CHECK(hac > 0.7 * truth);       // the sandwich comes near the truth (Bartlett is biased low)
  CHECK(hac < 1.3 * truth);
}

TEST_CASE("identifiability in words: equivalent variables, a free one, correlated pairs", "[localsearch]") {
  // Columns a, b, c act identically (only their sum matters), d does nothing, e acts alone;
  // 40 residuals, strong enough (column norms ~ 60 sigma per bound range) to fix what they fix.
  const Eigen::Index m = 40;
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(m, 5);
  for (Eigen::Index i = 0; i < m; ++i) {
    const double t = static_cast<double>(i) / static_cast<double>(m - 1);
    J(i, 0) = J(i, 1) = J(i, 2) = 10 * std::sin(3 * t);
    J(i, 4) = 10 * std::cos(7 * t);
  }
  Eigen::MatrixXd corr = Eigen::MatrixXd::Identity(5, 5);
  corr(0, 4) = corr(4, 0) = 0.97;
  const auto words = describe_identifiability({"a", "b", "c", "d", "e"}, J, corr);
  std::string all;
  for (const auto& w : words) all += w + "\n";
  INFO(all);
  REQUIRE(words.size() == 3);
  CHECK(words[0].rfind("a, b and c: only their sum (in bound ranges) is determined", 0) == 0);
  CHECK(words[1] == "d: not determined by the turns (they do not depend on it)");
  CHECK(words[2] == "a and e: 0.970 correlated");
  // Unequal weights are named with their coefficients.
  J.col(1) *= 3;
  const auto w2 = describe_identifiability({"a", "b", "c", "d", "e"}, J, Eigen::MatrixXd::Identity(5, 5));
  for (const auto& w : w2) all += w + "\n";
  INFO(all);
  REQUIRE(w2.size() == 2);
  CHECK(w2[0].find("only 0.33 a + 1 b + 0.33 c is determined") != std::string::npos);
}
