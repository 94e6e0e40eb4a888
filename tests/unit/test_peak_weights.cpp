// A fit weighs each measured turn by its peak's own uncertainty (issue 15): a peak that
// turnfit-peakfind marks as doubtful (a large r_err_mm, e.g. one of a merged pair) cannot pull
// the fit away from the turns it is sure of; nor can one it failed to mark, which the fit's
// outlier rule (Huber, 3 sigma) finds and names.
#include <catch2/catch.hpp>

#include <cmath>
#include <sstream>
#include <string>
#include <vector>

#include "../support.hpp"
#include "ring8_problem.hpp"
#include "turnfit/optimize/localsearch.hpp"

using namespace turnfit;
using turnfit::test::TempDir;
using turnfit::test::load_turn_problem;
using turnfit::test::ring8;

namespace {

/// ring8 with rinit and vchange moved, its turns as a peaks file with an r_err_mm column:
/// `err` on every peak but RRL turns 150-152, which are moved by 0.4 mm and carry `bad_err`.
/// Small reproducible jitter (+-err) on every other peak keeps chi2 finite.
std::string peaks_with_errors(const TempDir& tmp, double err, double bad_err, std::vector<double>& xt) {
  Machine m = load_machine(ring8("machine.json"));
  xt = {dvar_value(m, "rinit") + 0.6, dvar_value(m, "vchange") + 0.004};
  set_dvars(m, {"rinit", "vchange"}, xt);
  const TrackModel model = make_track_model(m);
  std::vector<TurnRecord> turns;
  track_particle(model, injection_state(effective_injection(m), m.particle.mass_MeV), machine_track_settings(m),
                 turns);
  std::ostringstream csv;
  csv.precision(17);
  csv << "probe,turn,r_mm,height,area,width_mm,r_err_mm,flag\n";
  int k = 0;
  for (const auto& t : turns) {
    const std::string& probe = model.probes[static_cast<size_t>(t.probe)].name;
    const bool bad = probe == "RRL" && t.turn >= 150 && t.turn <= 152;
    const double jitter = err * std::sin(12.9898 * ++k);  // deterministic, |jitter| <= err
    csv << probe << ',' << t.turn << ',' << t.r_mm + (bad ? 0.4 : jitter) << ",1,1,1," << (bad ? bad_err : err) << ','
        << (bad ? "merged" : "ok") << "\n";
  }
  return tmp.file("peaks.csv", csv.str());
}

}  // namespace

TEST_CASE("local search: peaks weighted by their own uncertainty, doubtful ones cannot pull the fit",
          "[localsearch][turn-problem]") {
  TempDir tmp;
  std::vector<double> xt;
  LocalSearchSettings s;
  s.threads = 2;
  s.minimax = false;
  auto fit = [&](double bad_err) {
    const std::string peaks = peaks_with_errors(tmp, 0.002, bad_err, xt);
    auto p = load_turn_problem(tmp.file("p.json", "{\"format\": \"turnfit-problem/1\", \"machine\": \"" +
                                                      ring8("machine.json") + "\", \"peaks\": \"" + peaks +
                                                      "\", \"bunch\": \"reference\", \"variables\": [\"rinit\", "
                                                      "\"vchange\"]}"));
    return local_search(*p, p->start(), s);
  };
  // The three bad peaks marked as such (0.4 mm): the fit comes back to the truth within its
  // sigma, and the scatter it estimates beyond the peaks' own errors is small.
  const LocalSearchResult good = fit(0.4);
  CHECK(good.peak_uncertainties == good.after.matched);
  for (size_t j = 0; j < 2; ++j) {
    INFO(good.variables[j].name << " " << good.variables[j].value << " +- " << good.variables[j].sigma << ", truth "
                                << xt[j]);
    CHECK(std::fabs(good.variables[j].value - xt[j]) < 3 * good.variables[j].sigma);
  }
  CHECK(good.sigma_mm[1] < 0.002);  // RRL: no scatter beyond r_err_mm (measured 0: the jitter is within it)
  CHECK(good.chi2_dof < 2);

  CHECK(good.outliers.empty());  // within their own uncertainty: nothing to down-weight

  // The same peaks claiming to be as good as the rest, without the outlier rule (--huber 0):
  // the fit leans toward them, its RRL scatter grows to absorb them, and rinit lands further
  // from the truth.
  s.huber_k = 0;
  const LocalSearchResult blind = fit(0.002);
  CHECK(blind.sigma_mm[1] > 0.03);  // three 0.4 mm errors among 174 turns: 0.052 mm rms
  CHECK(std::fabs(blind.variables[0].value - xt[0]) > std::fabs(good.variables[0].value - xt[0]));
  CHECK(blind.outliers.empty());

  // With it (the default, 3 sigma), the fit finds them itself: exactly those three turns are
  // named and down-weighted, and rinit comes back within 3 sigma.
  s.huber_k = 3;
  const LocalSearchResult robust = fit(0.002);
  REQUIRE(robust.outliers.size() == 3);
  for (size_t k = 0; k < 3; ++k) CHECK(robust.outliers[k].residual_mm == Approx(-0.4).margin(0.02));
  CHECK(robust.sigma_mm[1] < 0.002);
  CHECK(std::fabs(robust.variables[0].value - xt[0]) < 3 * robust.variables[0].sigma);
}
