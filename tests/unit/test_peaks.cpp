// turnfit-peakfind: turns found in synthetic sums of Gaussians with known truth (separations 25 to
// 4 mm, merged pairs, noise, baseline), grid independence, flags, numbering, profile reading,
// and the peaks of turnfit-synth profiles against the bunch centroids.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>

#include "../support.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/peaks/peaks.hpp"
#include "turnfit/peaks/peaks_app.hpp"
#include "turnfit/synth/synth.hpp"

using namespace turnfit;
using turnfit::test::error_code;

namespace {

/// A profile sampled at x0 + k step: turns of rms sigma_mm at centres, each of the same area
/// (a CW beam: every turn carries the whole current) unless areas are given, plus a baseline
/// b0 + b1 (x - x0) and Gaussian noise of rms noise (fixed seed).
struct Synthetic {
  std::vector<double> x, y;
};

Synthetic make_profile(const std::vector<double>& centres, double sigma_mm, double x0, double x1, double step,
                       double noise, unsigned seed = 1, const std::vector<double>& areas = {},
                       double b0 = 0.02, double b1 = 1e-4) {
  Synthetic p;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0, 1);
  for (double x = x0; x <= x1 + 1e-9; x += step) {
    double v = b0 + b1 * (x - x0);
    for (size_t i = 0; i < centres.size(); ++i) {
      const double u = (x - centres[i]) / sigma_mm, a = areas.empty() ? 1.0 : areas[i];
      v += a * std::exp(-0.5 * u * u);
    }
    p.x.push_back(x);
    p.y.push_back(v + noise * nd(rng));
  }
  return p;
}

/// Turn centres whose separation falls linearly from s0 to s1 over n turns.
std::vector<double> falling_separations(double start, double s0, double s1, int n) {
  std::vector<double> c{start};
  for (int i = 1; i < n; ++i) c.push_back(c.back() + s0 + (s1 - s0) * (i - 1) / (n - 2));
  return c;
}

/// Largest |found - true| when found and true are matched in order (same count required).
double max_error(const PeakResult& r, const std::vector<double>& truth) {
  REQUIRE(r.peaks.size() == truth.size());
  double m = 0;
  for (size_t i = 0; i < truth.size(); ++i) m = std::max(m, std::abs(r.peaks[i].r_mm - truth[i]));
  return m;
}

double rms_error(const PeakResult& r, const std::vector<double>& truth) {
  double s = 0;
  for (size_t i = 0; i < truth.size(); ++i) s += std::pow(r.peaks[i].r_mm - truth[i], 2);
  return std::sqrt(s / static_cast<double>(truth.size()));
}

int count_flag(const PeakResult& r, unsigned flag) {
  return static_cast<int>(std::count_if(r.peaks.begin(), r.peaks.end(), [&](const Peak& p) { return (p.flags & flag) != 0; }));
}

}  // namespace

TEST_CASE("peaks: separations from 25 mm down to 4 mm, sigma 1.5 mm, noise and baseline", "[peaks]") {
  // 60 turns, separation 25 -> 4 mm: the last turns overlap (4 mm = 2.7 sigma), as at RRL.
  const auto truth = falling_separations(2100, 25, 4, 60);
  for (unsigned seed : {1u, 2u, 3u}) {
    const auto p = make_profile(truth, 1.5, 2080, truth.back() + 20, 0.5, 0.005, seed);
    for (bool centroid : {false, true}) {
      PeakSettings s;
      s.centroid = centroid;
      const PeakResult r = find_peaks(p.x, p.y, s, 9);
      INFO("seed " << seed << " centroid " << centroid);
      REQUIRE(r.peaks.size() == truth.size());  // every turn, nothing spurious
      CHECK(max_error(r, truth) < 0.1);  // turnfit-peakfind(1) ACCURACY: largest error below 0.1 mm
      CHECK(rms_error(r, truth) < 0.03);
      CHECK(r.peaks.front().turn == 9);
      CHECK(r.peaks.back().turn == 68);
      CHECK(count_flag(r, kPeakMerged | kPeakWide | kPeakGap | kPeakWeak) == 0);
      // Heights, widths and areas of the fitted turns.
      for (const auto& pk : r.peaks) {
        CHECK(pk.height == Approx(1.0).epsilon(0).margin(0.05));
        CHECK(pk.width_mm == Approx(1.5).epsilon(0).margin(0.08));
        CHECK(pk.area == Approx(1.5 * std::sqrt(2 * M_PI)).epsilon(0.05));
      }
    }
  }
}

TEST_CASE("peaks: merged pairs (no dip between them) are split by the fit and flagged", "[peaks]") {
  // 16 resolved turns (separation 12 -> 7 mm), then an off-centre beam: separations alternate
  // 7.5 and 2.8 mm, so 10 pairs of turns are closer than 2 sigma and each shows as one wide peak
  // of twice a turn's area.
  std::vector<double> truth = falling_separations(1880, 12, 7, 16);
  for (int i = 1; i < 21; ++i) truth.push_back(truth.back() + (i % 2 ? 7.5 : 2.8));
  for (unsigned seed : {1u, 2u, 3u, 4u}) {
    const auto p = make_profile(truth, 1.5, 1865, truth.back() + 15, 0.5, 0.005, seed);
    PeakSettings s;
    const PeakResult r = find_peaks(p.x, p.y, s, 1);
    INFO("seed " << seed);
    REQUIRE(r.peaks.size() == truth.size());
    CHECK(r.splits == 10);
    CHECK(count_flag(r, kPeakMerged) == 20);
    CHECK(count_flag(r, kPeakWide | kPeakWeak | kPeakGap) == 0);
    for (size_t i = 0; i < 16; ++i) CHECK(r.peaks[i].flags == 0);
    CHECK(max_error(r, truth) < 0.25);  // turnfit-peakfind(1) ACCURACY: merged pairs, below 0.25 mm
    CHECK(rms_error(r, truth) < 0.1);
    CHECK(r.peaks.back().turn == 36);
  }
  SECTION("--no-split: one wide peak per pair, numbered as two turns") {
    const auto p = make_profile(truth, 1.5, 1865, truth.back() + 15, 0.5, 0.005, 1);
    PeakSettings s;
    s.split = false;
    const PeakResult r = find_peaks(p.x, p.y, s, 1);
    CHECK(r.peaks.size() == 26);
    CHECK(count_flag(r, kPeakMerged) == 0);
    CHECK(count_flag(r, kPeakWide) == 10);
    // The numbering still counts every turn: the last peak holds turns 35 and 36 and carries
    // the first of its numbers.
    CHECK(r.peaks.back().turn == 35);
    CHECK(r.peaks.back().flags == kPeakWide);
    CHECK(r.peaks[16].turn == 17);
    CHECK(r.peaks[17].turn == 19);
  }
}

TEST_CASE("peaks: a pair too close to separate stays one peak, flagged wide, counted as two turns", "[peaks]") {
  // Turns every 12 mm; turns 5 and 6 only 0.3 mm apart (0.2 sigma): their sum is a Gaussian.
  std::vector<double> truth;
  for (int i = 0; i < 12; ++i) truth.push_back(2000 + 12.0 * i);
  truth.insert(truth.begin() + 5, truth[4] + 0.3);
  for (size_t i = 6; i < truth.size(); ++i) truth[i] += 0.3;
  const auto p = make_profile(truth, 1.5, 1985, truth.back() + 15, 0.5, 0.003, 5);
  const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
  // Either split (both at the pair) or one wide peak; in both cases the later turns keep their numbers.
  const auto& last = r.peaks.back();
  CHECK(last.turn == 13);
  CHECK(last.r_mm == Approx(truth.back()).epsilon(0).margin(0.05));
  const bool split = count_flag(r, kPeakMerged) == 2, wide = count_flag(r, kPeakWide) == 1;
  CHECK((split || wide));
  CHECK(count_flag(r, kPeakGap) == 0);
}

TEST_CASE("peaks: positions do not depend on the reading grid", "[peaks]") {
  // The same turns read on a grid shifted by half a step (noise free: the shift alone).
  const auto truth = falling_separations(2100, 20, 4.5, 40);
  for (double step : {0.5, 0.05}) {
    const double hi = step < 0.1 ? 2100 + 60 : truth.back() + 15;  // a short stretch at the fine step
    std::vector<double> sub;
    for (double c : truth)
      if (c < hi - 10) sub.push_back(c);
    const auto a = make_profile(sub, 1.5, 2085, hi, step, 0, 1);
    const auto b = make_profile(sub, 1.5, 2085 + 0.5 * step, hi, step, 0, 1);
    for (bool centroid : {false, true}) {
      PeakSettings s;
      s.centroid = centroid;
      const PeakResult ra = find_peaks(a.x, a.y, s, 1), rb = find_peaks(b.x, b.y, s, 1);
      INFO("step " << step << " centroid " << centroid);
      REQUIRE(ra.peaks.size() == sub.size());
      REQUIRE(rb.peaks.size() == sub.size());
      double moved = 0;
      for (size_t i = 0; i < sub.size(); ++i) moved = std::max(moved, std::abs(ra.peaks[i].r_mm - rb.peaks[i].r_mm));
      CHECK(moved < 0.02);
      CHECK(max_error(ra, sub) < 0.02);
    }
  }
}

TEST_CASE("peaks: thresholds reject noise, a lone turn in noise is found once", "[peaks]") {
  SECTION("noise and baseline only") {
    const auto p = make_profile({}, 1.5, 2000, 2300, 0.5, 0.01, 9);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
    CHECK(r.peaks.empty());
  }
  SECTION("one turn, 20 noise rms high") {
    const auto p = make_profile({2150.3}, 1.5, 2000, 2300, 0.5, 0.05, 9);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
    REQUIRE(r.peaks.size() == 1);
    CHECK(r.peaks[0].r_mm == Approx(2150.3).epsilon(0).margin(0.15));
  }
  SECTION("a small bump below --min-height is not a turn; above it, a weak one") {
    const std::vector<double> c{2100, 2120, 2140, 2160, 2180};
    const auto p = make_profile(c, 1.5, 2080, 2200, 0.5, 0.001, 9, {1, 1, 0.03, 1, 1});
    PeakSettings s;
    s.min_height = 0.05;
    CHECK(find_peaks(p.x, p.y, s, 1).peaks.size() == 4);
    s.min_height = 0.01;
    const PeakResult r = find_peaks(p.x, p.y, s, 1);
    REQUIRE(r.peaks.size() == 5);
    CHECK(r.peaks[2].flags == kPeakWeak);
    CHECK(peak_flag_string(r.peaks[2].flags) == "weak");
    CHECK(peak_flag_string(r.peaks[0].flags) == "ok");
  }
  SECTION("--min-slope rejects a broad hump, --min-area a one-reading spike, that --min-height keeps") {
    // A hump 0.3 high and 15 mm wide (a baseline wiggle) and a spike in one reading beside turns.
    auto p = make_profile({2100, 2120, 2140}, 1.0, 2080, 2250, 0.5, 0.001, 9);
    for (size_t k = 0; k < p.x.size(); ++k) p.y[k] += 0.3 * std::exp(-0.5 * std::pow((p.x[k] - 2210) / 15, 2));
    p.y[static_cast<size_t>(std::lround((2170 - 2080) / 0.5))] += 0.5;
    PeakSettings s;
    CHECK(find_peaks(p.x, p.y, s, 1).peaks.size() == 5);
    s.min_slope = 0.05;  // the hump's steepest flank is 0.012 P/mm, a turn's 0.6 P/mm
    CHECK(find_peaks(p.x, p.y, s, 1).peaks.size() == 4);
    s.min_slope = 0;
    s.min_area = 0.6;  // the smoothed spike's area is about 0.25 P mm, a turn's 2.5
    const PeakResult r = find_peaks(p.x, p.y, s, 1);
    REQUIRE(r.peaks.size() == 4);
    CHECK(r.peaks[3].r_mm == Approx(2210).epsilon(0).margin(1));
  }
}

TEST_CASE("peaks: a missing turn skips a turn number (gap), edges are flagged", "[peaks]") {
  std::vector<double> c;
  for (int i = 0; i < 14; ++i) c.push_back(2000 + 10.0 * i);
  c.erase(c.begin() + 7);  // turn 8 lost
  const auto p = make_profile(c, 1.5, 1990, c.back() + 2, 0.5, 0.002, 3);
  PeakSettings s;
  const PeakResult r = find_peaks(p.x, p.y, s, 1);
  REQUIRE(r.peaks.size() == 13);
  CHECK(r.peaks[6].turn == 7);
  CHECK(r.peaks[7].turn == 9);
  CHECK(r.peaks[7].flags == kPeakGap);
  CHECK(r.skipped_turns == 1);
  CHECK(r.peaks.back().turn == 14);
  CHECK((r.peaks.back().flags & kPeakEdge) != 0);
  CHECK(r.peaks.front().flags == 0);
  s.gap_ratio = 0;
  const PeakResult r0 = find_peaks(p.x, p.y, s, 1);
  CHECK(r0.peaks[7].turn == 8);
  CHECK(r0.peaks.back().turn == 13);
}

TEST_CASE("peaks: profile reading: metadata, strict numbers, file and line in errors", "[peaks]") {
  const std::string head = "# turnfit-synth 0.1.0\n# argv: turnfit-synth x --probe=NOT first_turn=77\n"
                           "# probe=RRL step_mm=0.5 current_uA=88 seed=1 first_turn=9\nposition_mm,intensity\n";
  std::string body;
  for (int k = 0; k < 10; ++k) body += std::to_string(2000 + 0.5 * k) + "," + std::to_string(k == 4 ? 1.0 : 0.0) + "\n";
  const ProbeProfile p = parse_profile(head + body, "RRL.csv");
  CHECK(p.probe == "RRL");
  CHECK(p.step_mm == 0.5);
  CHECK(p.first_turn == 9);
  CHECK(p.position_mm.size() == 10);
  CHECK(p.line[0] == 5);

  std::string msg;
  CHECK(error_code([&] { parse_profile("position_mm,intensity\n1,0\n2,0\n", "a.csv"); }, &msg) == 65);
  CHECK(msg.find("at least 5") != std::string::npos);
  CHECK(error_code([&] { parse_profile("x,intensity\n1,0\n", "a.csv"); }, &msg) == 65);
  CHECK(msg.find("position_mm") != std::string::npos);
  CHECK(error_code([&] { parse_profile("position_mm,intensity\n1,0\n2,0\n3,x\n4,0\n5,0\n", "a.csv"); }, &msg) == 65);
  CHECK(msg.find("a.csv:4") != std::string::npos);
  CHECK(error_code([&] { parse_profile("position_mm,intensity\n1,0\n2,0\n3,0\n2.5,0\n5,0\n", "a.csv"); }, &msg) == 65);
  CHECK(msg.find("a.csv:5: position_mm must increase") != std::string::npos);
  CHECK(error_code([&] { parse_profile("position_mm,intensity\n1,0\n2,0\n3,0\n4.5,0\n5,0\n", "a.csv"); }, &msg) == 65);
  CHECK(msg.find("a.csv:5: readings are not evenly spaced") != std::string::npos);
  CHECK(error_code([&] { parse_profile("# first_turn=0\nposition_mm,intensity\n1,0\n2,0\n3,0\n4,0\n5,0\n", "a.csv"); }) == 65);
}

TEST_CASE("peaks: peakfind writes the peaks table and its JSON form", "[peaks]") {
  const auto truth = falling_separations(2100, 20, 6, 12);
  const auto syn = make_profile(truth, 1.5, 2090, truth.back() + 10, 0.5, 0.002, 4);
  std::string text = "# probe=RRX step_mm=0.5 first_turn=9\nposition_mm,intensity\n";
  for (size_t k = 0; k < syn.x.size(); ++k) text += std::to_string(syn.x[k]) + "," + std::to_string(syn.y[k]) + "\n";
  const ProbeProfile prof = parse_profile(text, "p.csv");
  PeakfindOptions o;
  o.common.no_provenance = true;
  o.common.format = "csv";
  std::ostringstream os;
  const PeakResult r = peakfind(prof, o, os);
  REQUIRE(r.peaks.size() == 12);
  std::istringstream is(os.str());
  std::string line;
  std::getline(is, line);
  CHECK(line.rfind("# probe=RRX first_turn=9 peaks=12 merged=0", 0) == 0);
  std::getline(is, line);
  CHECK(line == "probe,turn,r_mm,height,area,width_mm,flag");
  std::getline(is, line);
  CHECK(line.rfind("RRX,9,", 0) == 0);
  CHECK(line.substr(line.size() - 3) == ",ok");

  o.probe = "P1";
  o.first_turn = 3;
  o.common.format = "json";
  std::ostringstream js;
  peakfind(prof, o, js);
  const auto doc = nlohmann::json::parse(js.str());
  CHECK(doc["probe"] == "P1");
  CHECK(doc["peaks"].size() == 12);
  CHECK(doc["peaks"][0]["turn"] == 3);
  CHECK(doc["peaks"][11]["turn"] == 14);
  CHECK(doc["peaks"][0]["r_mm"].get<double>() == Approx(truth[0]).epsilon(0).margin(0.1));
  CHECK(doc["peaks"][0]["r_err_mm"].get<double>() > 0);
  CHECK(doc["peaks"][0]["r_err_mm"].get<double>() < 0.05);
  CHECK(doc.find("provenance") == doc.end());

  o.probe = "a,b";
  CHECK(error_code([&] { std::ostringstream x; peakfind(prof, o, x); }) == 64);
}

TEST_CASE("peaks: turnfit-synth profiles: every turn at its bunch centroid", "[peaks]") {
  // The synth test machine (uniform isochronous field, 12 turns at the probe P0, about 22 mm
  // apart): the wire profile of a tracked bunch with the default noise and baseline.
  const Machine m = load_machine(std::string(TURNFIT_TEST_DIR) + "/cli/data/synth_iso.json");
  SynthSettings st;
  st.track.turns = 12;
  st.particles = 400;
  st.threads = 1;
  st.phases = false;
  const SynthResult res = synthesize(m, st);
  REQUIRE(res.profiles.size() == 1);
  const SynthProfile& prof = res.profiles[0];
  std::vector<double> truth;
  for (const auto& c : res.centroids)
    if (c.probe == 0) truth.push_back(c.r_mm);
  std::sort(truth.begin(), truth.end());
  for (bool centroid : {false, true}) {
    PeakSettings s;
    s.centroid = centroid;
    const PeakResult r = find_peaks(prof.position_mm, prof.intensity, s, 1);
    INFO("centroid " << centroid);
    REQUIRE(r.peaks.size() == truth.size());
    CHECK(max_error(r, truth) < (centroid ? 0.05 : 0.15));
    CHECK(count_flag(r, ~0u) == 0);
  }
}
