// The paper's coordinate-wise local search (--method coordinate): its acceptance rule on hand-made
// residuals, a noiseless ring8 truth recovered, a start at the truth left alone, and the same path
// on any thread count.
#include <catch2/catch.hpp>

#include <cmath>
#include <fstream>
#include <limits>

#include "../support.hpp"
#include "ring8_problem.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/optimize/coordinate_search.hpp"
#include "turnfit/optimize/problem_file.hpp"
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

/// A ring8 problem over `names` whose measurement is ring8 tracked with each variable moved by
/// frac[j] of its bound range (noiseless, 17 digits). xt receives the truth.
std::unique_ptr<TurnPatternProblem> truth_problem(const TempDir& tmp, const std::vector<std::string>& names,
                                                  const std::vector<double>& frac, std::vector<double>& xt,
                                                  const std::string& variables = "") {
  const Machine truth = moved_ring8(names, frac, xt);
  const std::string peaks = turns_as_peaks(truth, tmp, "truth.csv");
  std::string vars = "[";
  for (size_t j = 0; j < names.size(); ++j) vars += (j ? ", \"" : "\"") + names[j] + "\"";
  vars += "]";
  if (!variables.empty()) vars = variables;
  return load_turn_problem(tmp.file("p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"" +
                                                  ring8("machine.json") + "\", \"peaks\": \"" + peaks +
                                                  "\", \"bunch\": \"reference\", \"variables\": " + vars + "}"));
}

/// Hand-made residuals on two probes A (points 0 .. na-1) and B (the rest), all matched.
struct Residuals {
  TurnTable table;
  TurnPatternResult r;
  Residuals(size_t na, const std::vector<double>& delta) {
    table.probes = {"A", "B"};
    r.ok = true;
    for (size_t i = 0; i < delta.size(); ++i) {
      TurnPoint pt;
      pt.probe = i < na ? 0 : 1;
      pt.turn = static_cast<int>(i < na ? i + 1 : i - na + 1);
      table.points.push_back(pt);
      r.delta_mm.push_back(delta[i]);
      r.matched.push_back(std::isnan(delta[i]) ? 0 : 1);
    }
  }
  CoordinateNorms norms() const { return coordinate_norms(r, table); }
};

}  // namespace

TEST_CASE("coordinate search: the four norms of the paper's rule, probes weighted equally", "[coordinate]") {
  // A: one turn at -3 mm; B: 1, -2, 0.5 mm and one unmatched turn (left out).
  const Residuals res(1, {-3, 1, -2, 0.5, std::numeric_limits<double>::quiet_NaN()});
  const CoordinateNorms c = res.norms();
  CHECK(c.linf_mm == 3);
  CHECK(c.second_mm == 2);
  CHECK(c.third_mm == 1);
  // Mean square per probe: A 9, B (1 + 4 + 0.25) / 3 = 1.75; equal weights: sqrt((9 + 1.75) / 2).
  CHECK(c.wl2_mm == Approx(std::sqrt(5.375)).epsilon(1e-15));
  // Fewer than three matched turns: the missing ranks are 0.
  const CoordinateNorms one = Residuals(1, {0.7}).norms();
  CHECK(one.linf_mm == Approx(0.7).epsilon(0));
  CHECK(one.second_mm == 0);
  CHECK(one.third_mm == 0);
  CHECK(one.wl2_mm == Approx(0.7).epsilon(1e-15));
}

TEST_CASE("coordinate search: a step that lowers l2 but worsens one norm by more than 0.01 mm is refused",
          "[coordinate]") {
  const double tol = 0.01, eps = 1e-6;
  // One probe, four turns. The trial flattens three turns (weighted l2 0.35 -> 0.26 mm) but its
  // worst turn goes from 0.50 to 0.52 mm: the paper's rule refuses it.
  const CoordinateNorms cur = Residuals(0, {0.50, 0.30, 0.30, 0.30}).norms();
  const CoordinateNorms worse = Residuals(0, {0.52, 0.0, 0.0, 0.0}).norms();
  REQUIRE(worse.wl2_mm < cur.wl2_mm - 0.05);
  REQUIRE(worse.linf_mm > cur.linf_mm + tol);
  CHECK_FALSE(coordinate_accepts(cur, worse, tol, eps));
  // The same trial with the worst turn 0.005 mm higher: within the tolerance, and l2 improves.
  CHECK(coordinate_accepts(cur, Residuals(0, {0.505, 0.0, 0.0, 0.0}).norms(), tol, eps));
  // The second largest worsens by 0.02 mm while the worst improves: refused.
  CHECK_FALSE(coordinate_accepts(cur, Residuals(0, {0.40, 0.32, 0.10, 0.10}).norms(), tol, eps));
  // Only the third largest improves, l2 worsens within the tolerance: accepted (one norm is enough).
  CoordinateNorms third = cur;
  third.third_mm -= 0.02;
  third.wl2_mm += 0.005;
  CHECK(coordinate_accepts(cur, third, tol, eps));
  third.wl2_mm += 0.01;  // now l2 worsens by 0.015 mm: refused
  CHECK_FALSE(coordinate_accepts(cur, third, tol, eps));
  // Nothing changes, or changes by less than the improvement threshold: refused.
  CHECK_FALSE(coordinate_accepts(cur, cur, tol, eps));
  CHECK_FALSE(coordinate_accepts(cur, Residuals(0, {0.50, 0.30, 0.30, 0.3 - 1e-7}).norms(), tol, eps));
  // A NaN norm is never accepted.
  CoordinateNorms nan = cur;
  nan.linf_mm = std::numeric_limits<double>::quiet_NaN();
  nan.wl2_mm = 0;
  CHECK_FALSE(coordinate_accepts(cur, nan, tol, eps));
}

namespace {

// The three variables of the ring8 cases: injection angle and radius, the main voltages' common
// change. Each changes the turn pattern its own way (LM calls them determined), so a search
// moving one at a time can reach the truth. The moves are irrational-looking fractions of the
// ranges so the truth does not sit on the search's step lattice (0.05 x 2^-k of the range).
const std::vector<std::string> kNames = {"phiinit", "rinit", "vchange"};
const std::vector<double> kMoves = {0.0837, -0.1213, 0.0641};

}  // namespace

TEST_CASE("coordinate search: a noiseless ring8 truth with three settings moved comes back", "[coordinate]") {
  TempDir tmp;
  std::vector<double> xt;
  auto p = truth_problem(tmp, kNames, kMoves, xt);
  CoordinateSettings s;  // the paper's rule and turnfit's default steps
  s.threads = 2;
  int last_sweep = 0;
  s.progress = [&](int sweep, double) { last_sweep = sweep; };
  const CoordinateResult r = coordinate_search(*p, p->start(), s);
  INFO("termination: " << r.termination << ", evaluations " << r.evaluations << ", sweeps " << r.sweeps);
  CHECK(r.before.linf_mm > 5);  // 6-12 % of the ranges: a start many millimetres off
  CHECK(r.norms_before.linf_mm == r.before.linf_mm);
  // Noiseless: the search ends only when a whole sweep at min_step (1e-6 of each range) keeps
  // nothing; the truth's own residuals are 0, so the stopping point is within a few min_steps
  // of it in these well-separated variables. 1e-5 of a range (10 min_steps) allows for the
  // coupling between them; 1e-3 mm is what such offsets give at most on the worst turn.
  CHECK(r.termination.rfind("converged", 0) == 0);
  CHECK(r.after.linf_mm < 1e-3);
  CHECK(r.norms_after.linf_mm == Approx(r.after.linf_mm).epsilon(1e-12));
  for (size_t j = 0; j < kNames.size(); ++j) {
    INFO(kNames[j] << ": truth " << xt[j] << ", found " << r.x[j]);
    CHECK(std::fabs(r.x[j] - xt[j]) < 1e-5 * (p->upper()[j] - p->lower()[j]));
  }
  CHECK(r.accepted == r.trace.size());
  CHECK(r.accepted > 0);
  CHECK(last_sweep == static_cast<int>(r.sweeps));
  CHECK(r.discarded == 0);  // lookahead 1: nothing is simulated from a stale point
  // The kept steps: each passes the rule against the point before it.
  // The kept steps: each passes the rule against the point before it; the result is the best.
  CoordinateNorms prev = r.norms_before;
  for (const CoordinateStep& st : r.trace) {
    CHECK(coordinate_accepts(prev, st.norms, s.tolerance_mm, s.improvement_mm));
    CHECK(st.norms.linf_mm >= r.norms_after.linf_mm);
    prev = st.norms;
  }

  SECTION("the same path on 1 thread, and with 3 variables simulated at once") {
    // Capped after 41 designs: the 1-thread run must take the first steps of the 2-thread run
    // exactly (bit for bit); lookahead 3 simulates more designs for the same path.
    CoordinateSettings c = s;
    c.progress = nullptr;
    c.threads = 1;
    c.max_evaluations = 41;
    const CoordinateResult one = coordinate_search(*p, p->start(), c);
    CHECK(one.termination == "max_evaluations");
    CHECK(one.evaluations == 41);  // the start and 20 blocks of two trials
    REQUIRE(one.trace.size() > 3);
    REQUIRE(one.trace.size() <= r.trace.size());
    for (size_t i = 0; i < one.trace.size(); ++i) {
      CHECK(one.trace[i].evaluation == r.trace[i].evaluation);
      CHECK(one.trace[i].variable == r.trace[i].variable);
      CHECK(one.trace[i].value == r.trace[i].value);
      CHECK(one.trace[i].norms.linf_mm == r.trace[i].norms.linf_mm);
      CHECK(one.trace[i].norms.wl2_mm == r.trace[i].norms.wl2_mm);
    }
    c.threads = 2;
    const CoordinateResult two = coordinate_search(*p, p->start(), c);
    CHECK(two.x == one.x);
    CHECK(two.accepted == one.accepted);
    CHECK(two.sweeps == one.sweeps);
    CHECK(two.step == one.step);
    CHECK(two.after.linf_mm == one.after.linf_mm);
    c.lookahead = 3;
    c.max_evaluations = 60;
    const CoordinateResult ahead = coordinate_search(*p, p->start(), c);
    CHECK(ahead.discarded > 0);
    REQUIRE(ahead.trace.size() > 3);
    for (size_t i = 0; i < ahead.trace.size() && i < r.trace.size(); ++i) {
      CHECK(ahead.trace[i].variable == r.trace[i].variable);
      CHECK(ahead.trace[i].value == r.trace[i].value);
      CHECK(ahead.trace[i].norms.linf_mm == r.trace[i].norms.linf_mm);
    }
  }
}

TEST_CASE("coordinate search: a start at the truth does not move", "[coordinate]") {
  // Negative control: the measurement is the start's own turns. No norm can drop below 0, so
  // no step may be kept; the search halves its steps down to min_step and stops.
  TempDir tmp;
  std::vector<double> xt;
  auto p = truth_problem(tmp, kNames, {0, 0, 0}, xt);
  CoordinateSettings s;
  s.threads = 2;
  const CoordinateResult r = coordinate_search(*p, p->start(), s);
  CHECK(r.before.linf_mm == 0);
  CHECK(r.x == p->start());
  CHECK(r.accepted == 0);
  CHECK(r.after.linf_mm == 0);
  CHECK(r.termination.rfind("converged", 0) == 0);
  for (double h : r.step) CHECK(h == s.min_step);
}

TEST_CASE("coordinate search: bad starts and settings", "[coordinate]") {
  TempDir tmp;
  std::vector<double> xt;
  // rinit may range over 1000 mm here: the start at 1500 mm is inside the file's bounds but far
  // from any orbit the machine's probes see.
  auto p = truth_problem(tmp, {"rinit"}, {0}, xt, "[{\"name\": \"rinit\", \"lower\": 1500, \"upper\": 2500}]");
  CoordinateSettings s;
  s.threads = 1;
  std::string msg;
  CHECK(test::error_code([&] { coordinate_search(*p, {1400}, s); }, &msg) == 64);
  CHECK(msg.find("rinit") != std::string::npos);
  CHECK(test::error_code([&] { coordinate_search(*p, {1500}, s); }, &msg) == 65);
  CHECK(msg.find(p->file()) != std::string::npos);
  s.min_step = 0.1;  // larger than initial_step
  CHECK(test::error_code([&] { coordinate_search(*p, p->start(), s); }, &msg) == 64);
  CHECK(msg.find("min_step") != std::string::npos);
}

TEST_CASE("coordinate search: steps that lose the beam are refused, smaller ones go on", "[coordinate]") {
  // rinit over 1000 mm, the truth 1.7 mm from the start (0.17 of the machine's own 10 mm
  // range): the first steps (5 % of the problem's range, 50 mm) lose the beam or its turns and
  // must be refused; smaller ones then move toward the truth.
  TempDir tmp;
  std::vector<double> xt;
  const std::string wide = "[{\"name\": \"rinit\", \"lower\": 1500, \"upper\": 2500}]";
  auto p = truth_problem(tmp, {"rinit"}, {0.17}, xt, wide);
  CoordinateSettings s;
  s.threads = 2;
  s.max_evaluations = 30;
  const CoordinateResult r = coordinate_search(*p, p->start(), s);
  CHECK(r.refused_failed >= 2);
  CHECK(r.accepted > 0);
  CHECK(r.after.ok);
  CHECK(r.after.violation == 0);
  CHECK(r.after.matched == p->measured().points.size());
  CHECK(r.after.linf_mm < 0.5 * r.before.linf_mm);
  for (const CoordinateStep& st : r.trace) CHECK(std::fabs(st.value - p->start()[0]) < 50);
}

TEST_CASE("coordinate search: a design that loses a turn is not kept, however well it fits the rest",
          "[coordinate]") {
  // T: ring8 with vchange raised by 3.75 % of its range ends a turn earlier than C (raised by
  // 1.25 %). The measurement is T's own turns plus C's last turn. From C, the first +step trial
  // (2.5 % of the range) is T: every turn it has fits exactly (all four norms 0), but it misses
  // the last measured turn. The rule on the matched turns alone would take it; the search must
  // refuse it as a failed design.
  TempDir tmp;
  const std::string name = "vchange";
  Machine mt = load_machine(ring8("machine.json")), mc = mt;
  const DesignVariable& dv = mt.dvars.at(name);
  const double range = dv.upper - dv.lower, nominal = dvar_value(mt, name);
  const double xc = nominal + 0.0125 * range, xtv = xc + 0.025 * range;
  set_dvar(mt, name, xtv);
  set_dvar(mc, name, xc);
  std::string csv;
  {
    std::ifstream in(turns_as_peaks(mt, tmp, "t.csv"));
    for (std::string line; std::getline(in, line);) csv += line + "\n";
    std::ifstream inc(turns_as_peaks(mc, tmp, "c.csv"));
    std::string line, last;
    while (std::getline(inc, line)) last = line;
    csv += last + "\n";
  }
  auto p = load_turn_problem(tmp.file("p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"" +
                                                    ring8("machine.json") + "\", \"peaks\": \"" +
                                                    tmp.file("peaks.csv", csv) + "\", \"bunch\": \"reference\", \"variables\": [\"vchange\"]}"));
  REQUIRE(p->upper()[0] - p->lower()[0] == range);
  const TurnPatternResult rc = p->simulate({xc}), rt = p->simulate({xtv});
  REQUIRE(rc.ok);
  REQUIRE(rt.ok);
  REQUIRE(rc.violation == 0);                // C has every measured turn ...
  REQUIRE(rt.matched.back() == 0);           // ... T misses the last one
  const CoordinateNorms nc = coordinate_norms(rc, p->measured()), nt = coordinate_norms(rt, p->measured());
  REQUIRE(nc.linf_mm > 0.1);
  REQUIRE(nt.linf_mm == 0);
  REQUIRE(coordinate_accepts(nc, nt, 0.01, 1e-6));  // on its own turns T is better

  CoordinateSettings s;
  s.threads = 2;
  s.initial_step = 0.025;
  s.max_evaluations = 9;  // four blocks: steps 2.5 %, then 1.25 % (T's side loses the turn too)
  const CoordinateResult r = coordinate_search(*p, {xc}, s);
  CHECK(r.refused_failed >= 1);
  CHECK(r.x[0] < xc + 0.0125 * range);  // never on T's side of the lost turn
  CHECK(r.after.matched == p->measured().points.size());
  CHECK(r.after.violation == 0);
  for (const CoordinateStep& st : r.trace) CHECK(st.value < xc + 0.0125 * range);
}
