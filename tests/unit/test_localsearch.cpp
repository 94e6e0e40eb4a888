// Local search (issue 15): the Jacobian a new sigma pass keeps, and the report's trace.
#include <catch2/catch.hpp>

#include <cmath>
#include <random>

#include "../support.hpp"
#include "ring8_problem.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/optimize/localsearch.hpp"

using namespace turnfit;
using turnfit::test::TempDir;
using turnfit::test::load_turn_problem;
using turnfit::test::moved_ring8;
using turnfit::test::ring8;

TEST_CASE("local search: a new sigma pass keeps the last pass's Jacobian, reweighted, equal to one formed anew",
          "[localsearch]") {
  // ring8 with four settings moved by 5 % of their ranges, its turns with Gaussian noise as the
  // measurement (0.005 mm on RRI2, 0.03 mm on RRL), no sigma_mm: the first pass weighs by the
  // wire step / sqrt(12) (0.014 and 0.14 mm), the next by the estimates (~0.005 and ~0.03 mm), so
  // the data rows' weights change by factors ~3 and ~5, differently per probe, between passes: a
  // Jacobian kept without reweighting, or reweighted the wrong way, would be off by that much.
  TempDir tmp;
  const std::vector<std::string> names = {"phiinit", "prinit", "rinit", "vchange"};
  std::vector<double> xt;
  const Machine truth = moved_ring8(names, {0.05, 0.05, -0.05, 0.05}, xt);
  const TrackModel model = make_track_model(truth);
  std::vector<TurnRecord> turns;
  track_particle(model, injection_state(effective_injection(truth), truth.particle.mass_MeV),
                 machine_track_settings(truth), turns);
  std::mt19937_64 rng(15);
  std::normal_distribution<double> noise(0, 1);
  std::string csv = "probe,turn,r_mm,height,area,width_mm,flag\n";
  char buf[160];
  for (const auto& t : turns) {
    const std::string& probe = model.probes[static_cast<size_t>(t.probe)].name;
    std::snprintf(buf, sizeof buf, "%s,%d,%.9f,1,1,1,ok\n", probe.c_str(), t.turn,
                  t.r_mm + (probe == "RRI2" ? 0.005 : 0.03) * noise(rng));
    csv += buf;
  }
  const std::string peaks = tmp.file("peaks.csv", csv);
  auto p = load_turn_problem(tmp.file(
      "p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"" + ring8("machine.json") + "\", \"peaks\": \"" +
                    peaks + "\", \"bunch\": \"reference\", \"variables\": [\"phiinit\", \"prinit\", \"rinit\", \"vchange\"]}"));
  LocalSearchSettings s;
  s.threads = 2;
  s.minimax = false;
  s.check_kept_jacobian = true;
  const LocalSearchResult r = local_search(*p, p->start(), s);

  REQUIRE(r.sigma_passes >= 2);
  // The weights did change: every probe's sigma moved from the first pass's by more than half.
  REQUIRE(r.sigma_probes.size() == 2);
  for (size_t q = 0; q < r.sigma_probes.size(); ++q) {
    double step = 0;
    for (const auto& pr : p->machine().probes)
      if (pr.name == r.sigma_probes[q]) step = pr.step_mm;
    CHECK(std::fabs(r.sigma_mm[q] / (step / std::sqrt(12.0)) - 1) > 0.5);
  }
  // Every later pass, and every stage of pass 1's turn continuation after the first, began from
  // the kept Jacobian, and at a pass it equals one formed anew at the same design with the new
  // weights (the same designs are simulated, so only rounding differs; 1e-6 is far below the
  // factor ~7 the reweighting applies).
  CHECK(r.kept_jacobians == r.sigma_passes - 1 + (s.stages - 1));
  CHECK(r.kept_jacobian_difference < 1e-6);
  CHECK(r.after.rms_mm < 0.03);  // the fit reached the noise

  // The trace: every pass, evaluations that only grow, and it starts at the start's turns and
  // ends at the result's.
  REQUIRE(!r.trace.empty());
  CHECK(r.trace.front().pass == 1);
  CHECK(r.trace.front().iteration == 0);
  CHECK(r.trace.back().pass == r.sigma_passes);
  for (size_t k = 1; k < r.trace.size(); ++k) CHECK(r.trace[k].evaluations >= r.trace[k - 1].evaluations);
  CHECK(r.trace.back().evaluations <= r.evaluations);
  CHECK(r.trace.front().rms_mm == Approx(r.before.rms_mm).epsilon(1e-6));
  CHECK(r.trace.back().rms_mm == Approx(r.after.rms_mm).epsilon(1e-6));
  CHECK(r.trace.back().matched == r.after.matched);
}

TEST_CASE("local search: the weak prior holds undetermined variables at its centre, the start's or the one given",
          "[localsearch]") {
  // ring8's own turns at RRI2 alone, with rinit moved by 3 % of its range: the turns fix rinit,
  // and rrlshift (RRL's offset, a probe without turns here) is not determined at all. Its
  // only residual is the weak prior's, so it ends at the prior's centre: the start when none
  // is given (two starts, two answers), the given centre from either start (one answer).
  TempDir tmp;
  std::vector<double> xt;
  const Machine truth = moved_ring8({"rinit"}, {0.03}, xt);
  const std::string peaks = turnfit::test::turns_as_peaks(truth, tmp, "rri2.csv", "RRI2");
  auto p = load_turn_problem(tmp.file(
      "p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"" + ring8("machine.json") + "\", \"peaks\": \"" +
                    peaks + "\", \"bunch\": \"reference\", \"sigma_mm\": 0.01, \"objectives\": [\"RRI2:l2\"], \"variables\": [\"rinit\", \"rrlshift\"]}"));
  REQUIRE(p->measured().probes.size() == 1);
  const auto& vs = p->variables();
  const double range1 = vs[1].upper - vs[1].lower;
  LocalSearchSettings s;
  s.threads = 2;
  s.minimax = false;
  std::vector<double> a = p->start(), b = p->start();
  a[1] += 0.2 * range1;
  b[1] -= 0.1 * range1;
  const LocalSearchResult ra = local_search(*p, a, s), rb = local_search(*p, b, s);
  // Without a centre: rinit found from both starts, rrlshift left where each began.
  CHECK(ra.x[0] == Approx(xt[0]).margin(1e-4 * (vs[0].upper - vs[0].lower)));
  CHECK(rb.x[0] == Approx(xt[0]).margin(1e-4 * (vs[0].upper - vs[0].lower)));
  CHECK(ra.x[1] == Approx(a[1]).margin(1e-6 * range1));
  CHECK(rb.x[1] == Approx(b[1]).margin(1e-6 * range1));
  // With one centre (the machine's rrlshift plus 5 % of its range; a prefix: rinit's entry only
  // matters while its data outweigh it), both starts end at it.
  s.weak_prior_centre = {p->start()[0], p->start()[1] + 0.05 * range1};
  const LocalSearchResult ca = local_search(*p, a, s), cb = local_search(*p, b, s);
  CHECK(ca.x[0] == Approx(xt[0]).margin(1e-4 * (vs[0].upper - vs[0].lower)));
  CHECK(ca.x[1] == Approx(s.weak_prior_centre[1]).margin(1e-3 * range1));
  CHECK(cb.x[1] == Approx(s.weak_prior_centre[1]).margin(1e-3 * range1));
  CHECK(ca.x[0] == Approx(cb.x[0]).margin(1e-6 * (vs[0].upper - vs[0].lower)));
  // A centre for more variables than the problem has is the caller's bug.
  s.weak_prior_centre = {0, 0, 0};
  CHECK(turnfit::test::error_code([&] { local_search(*p, a, s); }) == 70);
}
