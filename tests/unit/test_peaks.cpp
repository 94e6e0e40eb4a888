// turnfit-peakfind: turns found in synthetic sums of Gaussians with known truth (separations 25 to
// 4 mm, merged pairs, noise, baseline), grid independence, flags, numbering, profile reading,
// and the peaks of turnfit-synth profiles against the bunch centroids.
#include <catch2/catch.hpp>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <random>
#include <sstream>

#include "../support.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/metrics/metrics.hpp"
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

/// Standard errors that white noise of rms `noise` leaves in a least-squares fit of the whole
/// profile x (the model make_profile draws from: a Gaussian of height a_i, centre c_i and rms
/// width w per turn, plus the straight baseline): sqrt of the diagonal of noise^2 (J^T J)^-1,
/// J the model's Jacobian at the truth. The area a w sqrt(2 pi) by the propagation of errors.
/// Overlap shows as correlation between neighbours and widens the errors of the close turns.
struct FitErrors {
  std::vector<double> height, centre, width, area;
};

FitErrors fit_errors(const std::vector<double>& x, const std::vector<double>& centres, double w, double noise,
                     const std::vector<double>& areas = {}) {
  const long n = static_cast<long>(centres.size()), p = 3 * n + 2;
  Eigen::MatrixXd J(static_cast<long>(x.size()), p);
  for (long k = 0; k < J.rows(); ++k) {
    J(k, 3 * n) = 1;
    J(k, 3 * n + 1) = x[static_cast<size_t>(k)] - x[0];
    for (long i = 0; i < n; ++i) {
      const double a = areas.empty() ? 1.0 : areas[static_cast<size_t>(i)];
      const double u = (x[static_cast<size_t>(k)] - centres[static_cast<size_t>(i)]) / w, g = std::exp(-0.5 * u * u);
      J(k, 3 * i) = g;                     // d/d height
      J(k, 3 * i + 1) = a * g * u / w;      // d/d centre
      J(k, 3 * i + 2) = a * g * u * u / w;  // d/d width
    }
  }
  const Eigen::MatrixXd cov = noise * noise * (J.transpose() * J).inverse();
  FitErrors e;
  const double s2pi = std::sqrt(2 * M_PI);
  for (long i = 0; i < n; ++i) {
    const double a = areas.empty() ? 1.0 : areas[static_cast<size_t>(i)];
    const long h = 3 * i, c = h + 1, v = h + 2;
    e.height.push_back(std::sqrt(cov(h, h)));
    e.centre.push_back(std::sqrt(cov(c, c)));
    e.width.push_back(std::sqrt(cov(v, v)));
    // area = a w sqrt(2 pi): gradient (w, a) sqrt(2 pi).
    e.area.push_back(s2pi * std::sqrt(w * w * cov(h, h) + a * a * cov(v, v) + 2 * a * w * cov(h, v)));
  }
  return e;
}

/// Standard errors for a family of checks: two-sided 1.4e-5 per value, 1% over 720 values.
constexpr double kFitK = 4.35;

int count_flag(const PeakResult& r, unsigned flag) {
  return static_cast<int>(std::count_if(r.peaks.begin(), r.peaks.end(), [&](const Peak& p) { return (p.flags & flag) != 0; }));
}

/// turnfit-peakfind on a synthetic profile given as the tool reads it (header, then the samples):
/// its CSV into out, its warnings into err.
void peakfind_capturing(const Synthetic& p, const std::string& header, const std::string& file, std::ostringstream& out,
                        std::ostringstream& err) {
  std::string text = header;
  for (size_t k = 0; k < p.x.size(); ++k) text += std::to_string(p.x[k]) + "," + std::to_string(p.y[k]) + "\n";
  PeakfindOptions o;
  o.common.no_provenance = true;
  std::streambuf* old = std::cerr.rdbuf(err.rdbuf());
  peakfind(parse_profile(text, file), o, out);
  std::cerr.rdbuf(old);
}

}  // namespace

TEST_CASE("peaks: separations from 25 mm down to 4 mm, sigma 1.5 mm, noise and baseline", "[peaks]") {
  // 60 turns, separation 25 -> 4 mm: the last turns overlap (4 mm = 2.7 sigma), as at RRL.
  // Tolerances of the fitted heights and (--position fit) centres: k standard errors of a
  // least-squares fit of the whole profile with noise 0.005 (fit_errors; an isolated turn: height
  // 0.0038, centre 0.0046 mm; the 4 mm pairs up to 0.015 mm). k = kFitK (4.35): two-sided 1.4e-5
  // per value, 1% over the 720 values checked here and in the widths/areas case below (3 seeds,
  // 60 turns, 4 quantities). Was heights +-0.05 and an rms of the centres below 0.03 mm (no source).
  // Measured: heights at most 4.1, centres 3.7 standard errors.
  const auto truth = falling_separations(2100, 25, 4, 60);
  const double k = kFitK;
  for (unsigned seed : {1u, 2u, 3u}) {
    const auto p = make_profile(truth, 1.5, 2080, truth.back() + 20, 0.5, 0.005, seed);
    const FitErrors fe = fit_errors(p.x, truth, 1.5, 0.005);
    for (bool centroid : {false, true}) {
      PeakSettings s;
      s.centroid = centroid;
      const PeakResult r = find_peaks(p.x, p.y, s, 9);
      INFO("seed " << seed << " centroid " << centroid);
      REQUIRE(r.peaks.size() == truth.size());  // every turn, nothing spurious
      CHECK(max_error(r, truth) < 0.1);  // turnfit-peakfind(1) ACCURACY: largest error below 0.1 mm
      CHECK(r.peaks.front().turn == 9);
      CHECK(r.peaks.back().turn == 68);
      CHECK(count_flag(r, kPeakMerged | kPeakWide | kPeakGap | kPeakWeak) == 0);
      // Heights of the fitted turns, and with --position fit the centres.
      for (size_t i = 0; i < truth.size(); ++i) {
        const Peak& pk = r.peaks[i];
        INFO("turn " << i << " at " << truth[i]);
        CHECK(pk.height == Approx(1.0).epsilon(0).margin(k * fe.height[i]));
        if (!centroid) CHECK(pk.r_mm == Approx(truth[i]).epsilon(0).margin(k * fe.centre[i]));
      }
    }
  }
}

TEST_CASE("peaks: widths and areas of the falling-separation profile, with their known shortfall (regression)",
          "[peaks][regression]") {
  // The profiles of the case above. The noise alone (fit_errors, k = kFitK) allows an isolated
  // turn 0.0046 mm of width and 0.38% of area, but peakfind's widths and areas come out low by
  // more: their means over 20 turns fall short by 0.003-0.004 mm and 0.4% where turns are 25-18 mm
  // apart, and by 0.007-0.011 mm and 0.8-1.1% where they are 11-4 mm apart (3 seeds; up to 5.5
  // standard errors for one turn), a bias, not noise (the baseline, see turnfit-peakfind(1)
  // ALGORITHM 1, is the likely cause; reported under issue 14). No page documents widths or
  // areas; the split of merged turns compares areas with a ratio rounded to an integer, which a
  // 1% shortfall does not move. Guards: the shortfall must not grow. Bound: k standard errors
  // plus the largest measured group mean (0.011 mm, 1.1%). Was +-0.08 mm and 5% for every turn.
  const auto truth = falling_separations(2100, 25, 4, 60);
  const double k = kFitK, area = 1.5 * std::sqrt(2 * M_PI);
  for (unsigned seed : {1u, 2u, 3u}) {
    const auto p = make_profile(truth, 1.5, 2080, truth.back() + 20, 0.5, 0.005, seed);
    const FitErrors fe = fit_errors(p.x, truth, 1.5, 0.005);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 9);
    REQUIRE(r.peaks.size() == truth.size());
    double dw = 0, da = 0;
    for (size_t i = 0; i < truth.size(); ++i) {
      const Peak& pk = r.peaks[i];
      INFO("seed " << seed << " turn " << i << " at " << truth[i]);
      CHECK(pk.width_mm == Approx(1.5).epsilon(0).margin(0.011 + k * fe.width[i]));
      CHECK(pk.area == Approx(area).epsilon(0).margin(0.011 * area + k * fe.area[i]));
      dw += (pk.width_mm - 1.5) / 60;
      da += (pk.area / area - 1) / 60;
    }
    // Over all 60 turns the mean shortfall (measured 0.006-0.008 mm, 0.7-0.8%) stays within the
    // allowance plus k standard errors of a mean (the isolated turn's over sqrt(60)).
    CAPTURE(dw, da);
    CHECK(std::fabs(dw) < 0.011 + k * 0.0046 / std::sqrt(60.0));
    CHECK(std::fabs(da) < 0.011 + k * 0.0038 / std::sqrt(60.0));
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
    // Every centre within k = kFitK standard errors of a least-squares fit of the whole profile
    // (fit_errors; merged turns 0.049 mm rms, so 0.21 mm; the resolved turns 0.005 mm, 0.02 mm):
    // two-sided 1.4e-5 per value, below 1% over these 144. Was an rms below 0.1 mm (no source;
    // the page states no rms). Measured: at most 3.05 standard errors, the merged turns' rms
    // 0.036-0.057 mm, at the noise's 0.049.
    const FitErrors fe = fit_errors(p.x, truth, 1.5, 0.005);
    for (size_t i = 0; i < truth.size(); ++i) {
      INFO("turn " << i << " at " << truth[i]);
      CHECK(r.peaks[i].r_mm == Approx(truth[i]).epsilon(0).margin(kFitK * fe.centre[i]));
    }
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

namespace {
/// A profile of skewed turns, as energy spread makes them: each turn a core (90% of its area, rms
/// sigma_mm, 0.05 sigma outward) and an inner tail (10%, rms 1.3 sigma, 0.45 sigma inward), so that
/// the turn's mean, the truth, is its centre; read every 0.5 mm, white noise of rms `noise`.
Synthetic make_skewed_profile(const std::vector<double>& centres, double sigma_mm, double x0, double x1, double noise,
                              unsigned seed) {
  Synthetic p;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0, 1);
  auto g = [](double x, double c, double s, double area) { const double u = (x - c) / s; return area / s * std::exp(-0.5 * u * u); };
  for (double x = x0; x <= x1 + 1e-9; x += 0.5) {
    double v = 0.02;
    for (double c : centres)
      v += sigma_mm * (g(x, c + 0.05 * sigma_mm, sigma_mm, 0.9) + g(x, c - 0.45 * sigma_mm, 1.3 * sigma_mm, 0.1));
    p.x.push_back(x);
    p.y.push_back(v + noise * nd(rng));
  }
  return p;
}
}  // namespace

TEST_CASE("peaks: r_err_mm: merged turns carry a larger uncertainty, and it covers their real error", "[peaks]") {
  // 12 resolved turns (12 -> 7 mm apart), then separations alternating 7.5 and 2.8 mm (an
  // off-centre beam: 8 pairs closer than 2 sigma, split by the fit and flagged merged).
  std::vector<double> truth = falling_separations(1880, 12, 7, 12);
  for (int i = 1; i < 17; ++i) truth.push_back(truth.back() + (i % 2 ? 7.5 : 2.8));
  SECTION("Gaussian turns: the statistical part alone covers an isolated turn") {
    const auto p = make_profile(truth, 1.5, 1865, truth.back() + 15, 0.5, 0.005, 7);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
    REQUIRE(r.peaks.size() == truth.size());
    REQUIRE(count_flag(r, kPeakMerged) == 16);
    double iso_max = 0, merged_min = 1e300;
    for (size_t i = 0; i < truth.size(); ++i) {
      const Peak& pk = r.peaks[i];
      INFO("turn " << i << " at " << truth[i] << ": r " << pk.r_mm << ", r_err " << pk.r_err_mm << " (stat "
                   << pk.r_err_stat_mm << ", sys " << pk.r_err_sys_mm << ")");
      CHECK(pk.r_err_mm == Approx(std::hypot(pk.r_err_stat_mm, pk.r_err_sys_mm)));
      CHECK(std::abs(pk.r_mm - truth[i]) <= 3 * pk.r_err_mm);
      if (pk.flags & kPeakMerged)
        merged_min = std::min(merged_min, pk.r_err_mm);
      else if (i < 11)
        iso_max = std::max(iso_max, pk.r_err_mm);
      // An isolated turn's centroid: noise 0.005 over +-3 widths of a 1.5 mm turn read every 0.5 mm
      // is sigma_n sqrt(sum (x - c)^2) / sum(y) = 0.005 sqrt(18 1.5^3 / 0.5) / (1.5 sqrt(2 pi) / 0.5)
      // = 0.0073 mm; the model adds 0.003 widths in quadrature, and 1.2 (1.5/d)^3 widths for a
      // neighbour d away (0.0035 mm at 12 mm). 20%: that, and the noise is estimated from the
      // profile (measured 5-6 % below).
      if (i < 3) {
        double v = 0.0073 * 0.0073 + 0.0045 * 0.0045;
        for (size_t j : {i - 1, i + 1})
          if (j < truth.size()) v += std::pow(1.2 * std::pow(1.5 / std::abs(truth[j] - truth[i]), 3) * 1.5, 2);
        CHECK(pk.r_err_mm == Approx(std::sqrt(v)).epsilon(0.2));
      }
    }
    // A merged turn's split adds 0.07 widths (0.105 mm here), 5 times the largest isolated turn's
    // r_err_mm (that of the turn 7 mm from the first pair).
    CHECK(merged_min > 4 * iso_max);
  }
  SECTION("skewed turns: the merged turns' errors are real, and r_err_mm covers them") {
    for (unsigned seed : {1u, 2u, 3u}) {
      const auto p = make_skewed_profile(truth, 1.2, 1865, truth.back() + 15, 0.005, seed);
      const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
      INFO("seed " << seed);
      REQUIRE(r.peaks.size() == truth.size());
      double iso_max = 0, merged_min = 1e300, merged_err2 = 0, merged_pull2 = 0, iso_pull2 = 0;
      int merged = 0, iso = 0;
      for (size_t i = 0; i < truth.size(); ++i) {
        const Peak& pk = r.peaks[i];
        const double e = pk.r_mm - truth[i];
        INFO("turn " << i << " at " << truth[i] << ": error " << e << ", r_err " << pk.r_err_mm << " (stat "
                     << pk.r_err_stat_mm << ", sys " << pk.r_err_sys_mm << ") " << peak_flag_string(pk.flags));
        CHECK(std::abs(e) <= 4 * pk.r_err_mm);  // an honest 1-sigma: 6e-5 per turn beyond 4
        if (pk.flags & kPeakMerged) {
          merged_min = std::min(merged_min, pk.r_err_mm);
          merged_err2 += e * e;
          merged_pull2 += e * e / (pk.r_err_mm * pk.r_err_mm);
          ++merged;
        } else if (i < 11) {
          iso_max = std::max(iso_max, pk.r_err_mm);
          iso_pull2 += e * e / (pk.r_err_mm * pk.r_err_mm);
          ++iso;
        }
      }
      REQUIRE(merged >= 12);
      // The skew is what makes the merged turns' positions wrong (not the noise): their rms error
      // is twice an isolated turn's largest uncertainty (0.026-0.028 against 0.012 mm; with
      // Gaussian turn shapes it was 0.07-0.08 mm, before the tails and the expected areas of
      // turnfit-peakfind(1), "Position reported"), and r_err_mm is larger by more (0.093 mm).
      CHECK(std::sqrt(merged_err2 / merged) > 1.5 * iso_max);
      CHECK(merged_min > 5 * iso_max);
      // Neither class far outside its uncertainty. The isolated turns' pulls come out near 1 (rms
      // 1.1-1.5); the merged turns' near 0.3: here the model is 3-4 times too cautious for them, as
      // it was calibrated on turnfit-synth's merged turns, whose errors are larger (about 0.07
      // widths against 0.02 here; turnfit-peakfind(1), UNCERTAINTY). Not absurdly cautious:
      CHECK(std::sqrt(iso_pull2 / iso) < 2);
      CHECK(std::sqrt(merged_pull2 / merged) < 2);
      CHECK(std::sqrt(merged_pull2 / merged) > 0.1);
    }
  }
}

namespace {
/// A profile of turns with an inward tail, as particles off the RF crest make them: each turn a
/// Gaussian of rms sigma_mm convolved with an exponential of mean tail sigma_mm towards smaller
/// positions, the convolution written as the mean of 40 Gaussians at the exponential's quantiles
/// (so not the fitted shape's formula), centred so that each turn's mean is its centre exactly;
/// baseline 0.02, read every 0.5 mm, white noise of rms `noise`.
Synthetic make_tailed_profile(const std::vector<double>& means, double sigma_mm, double tail, double x0, double x1,
                              double noise, unsigned seed) {
  constexpr int kq = 40;
  std::vector<double> q(kq);
  double qm = 0;
  for (int j = 0; j < kq; ++j) {
    q[static_cast<size_t>(j)] = -std::log(1 - (j + 0.5) / kq);
    qm += q[static_cast<size_t>(j)] / kq;
  }
  for (auto& v : q) v -= qm;  // quantiles less their mean
  Synthetic p;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0, 1);
  for (double x = x0; x <= x1 + 1e-9; x += 0.5) {
    double v = 0.02;
    for (double c : means)
      for (double u : q) {
        const double z = (x - c + tail * sigma_mm * u) / sigma_mm;
        v += std::exp(-0.5 * z * z) / kq;
      }
    p.x.push_back(x);
    p.y.push_back(v + noise * nd(rng));
  }
  return p;
}
}  // namespace

TEST_CASE("peaks: crowded turns with an inward tail sit at their means, not outward", "[peaks]") {
  // 13 turns 12 -> 7 mm apart (clear: their tails are measured), then 16 crowded turns of rms 1.2
  // mm with a tail of 0.6 rms (skewness -0.26 overall; ring8's outer turns at RRL: -0.05 to -0.5).
  // Gaussian shapes put crowded turns outward: the next turn's tail counts for this one, and of
  // two merged turns the inner one takes area from the outer one. turnfit-peakfind before the
  // tails and expected areas: mean error +0.21-0.22 mm at 2.8 widths, +0.34-0.35 mm in pairs 2.2
  // widths apart, every crowded turn outward; now +0.025-0.038 and +0.014-0.019 mm.
  std::vector<double> base = falling_separations(1880, 12, 7, 12);
  base.push_back(base.back() + 7);
  struct Case {
    const char* name;
    std::vector<double> steps;
    double bias, rms;
  };
  for (const Case& c : {Case{"2.8 widths apart", {3.36}, 0.06, 0.07}, Case{"pairs 2.2 widths apart", {2.64, 7.8}, 0.05, 0.07}}) {
    std::vector<double> truth = base;
    for (int i = 0; i < 16; ++i) truth.push_back(truth.back() + c.steps[static_cast<size_t>(i) % c.steps.size()]);
    for (unsigned seed : {1u, 2u, 3u}) {
      const auto p = make_tailed_profile(truth, 1.2, 0.6, 1865, truth.back() + 15, 0.005, seed);
      const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
      INFO(c.name << ", seed " << seed);
      REQUIRE(r.peaks.size() == truth.size());
      double sum = 0, sum2 = 0;
      for (size_t i = 13; i < truth.size(); ++i) {
        const double e = r.peaks[i].r_mm - truth[i];
        INFO("turn " << i << " at " << truth[i] << ": error " << e << " " << peak_flag_string(r.peaks[i].flags));
        CHECK(std::abs(e) < 0.15);
        sum += e;
        sum2 += e * e;
      }
      CAPTURE(sum / 16, std::sqrt(sum2 / 16));
      CHECK(std::abs(sum / 16) < c.bias);
      CHECK(std::sqrt(sum2 / 16) < c.rms);
      for (size_t i = 0; i < 12; ++i) CHECK(std::abs(r.peaks[i].r_mm - truth[i]) < 0.1);  // ACCURACY: separated turns
    }
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
      // Noise-free Gaussian turns down to 3 widths apart: the last turn, with one neighbour 4.5 mm
      // away, is off by 0.021-0.023 mm (the turns' expected areas reshape that neighbour a little;
      // before them 0.006-0.007 mm), the others by less than 0.004 mm.
      CHECK(max_error(ra, sub) < 0.03);
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
    // Standard errors at noise/height 0.05: the fitted centre (noise/height) sqrt(2 w step /
    // sqrt(pi)) = 0.046 mm; the default centroid over +-3 widths (+-4.5 mm, 19 readings)
    // noise sqrt(sum (x - x0)^2) / sum y = 0.05 x 11.9 / 7.52 = 0.079 mm. Bounds: 3.29 of them
    // (two-sided 1e-3 each): 0.15 and 0.26 mm (was 0.15 mm for the centroid, 1.9 standard errors).
    const auto p = make_profile({2150.3}, 1.5, 2000, 2300, 0.5, 0.05, 9);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
    REQUIRE(r.peaks.size() == 1);
    CHECK(r.peaks[0].r_mm == Approx(2150.3).epsilon(0).margin(3.29 * 0.079));
    PeakSettings fit;
    fit.centroid = false;
    const PeakResult rf = find_peaks(p.x, p.y, fit, 1);
    REQUIRE(rf.peaks.size() == 1);
    CHECK(rf.peaks[0].r_mm == Approx(2150.3).epsilon(0).margin(3.29 * 0.046));
    CAPTURE(r.peaks[0].r_mm, rf.peaks[0].r_mm);
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

namespace {

/// Turn centres as a probe sees a beam injected off its equilibrium orbit (issue 15): a radius
/// gain per turn falling linearly from d0 to d1 mm, plus a coherent betatron oscillation of
/// amplitude a0 -> a1 mm whose phase advances by 2 pi nu a turn, nu (the fractional tune)
/// rising linearly from nu0 to nu1.
std::vector<double> oscillating_turns(double start, double d0, double d1, double a0, double a1, double nu0, double nu1,
                                      int n) {
  std::vector<double> c;
  double r = start, phase = 0;
  for (int i = 0; i < n; ++i) {
    const double f = static_cast<double>(i) / (n - 1);
    c.push_back(r + (a0 + (a1 - a0) * f) * std::cos(phase));
    r += d0 + (d1 - d0) * f;
    phase += 2 * M_PI * (nu0 + (nu1 - nu0) * f);
  }
  return c;
}

/// Intervals that the gap rule before issue 15 took for missing turns: at least 1.8 times the
/// mean of up to 6 intervals on each side, itself left out (the default --gap-ratio).
int old_rule_gaps(const std::vector<double>& c) {
  int gaps = 0;
  const size_t n = c.size();
  for (size_t j = 0; j + 1 < n; ++j) {
    const size_t lo = j >= 6 ? j - 6 : 0, hi = std::min(n - 1, j + 7);
    const double mean = (c[hi] - c[lo] - (c[j + 1] - c[j])) / static_cast<double>(hi - lo - 1);
    gaps += c[j + 1] - c[j] >= 1.8 * mean;
  }
  return gaps;
}

/// The peaks' turn numbers against the truth's: each true turn (first_turn + its index in
/// `truth`, unless listed in `lost`) must be the one its peak's number says, matched in order.
void check_numbers(const PeakResult& r, const std::vector<double>& truth, const std::vector<int>& lost, int first_turn) {
  std::vector<std::pair<int, double>> kept;
  for (size_t i = 0; i < truth.size(); ++i)
    if (std::find(lost.begin(), lost.end(), static_cast<int>(i)) == lost.end())
      kept.emplace_back(first_turn + static_cast<int>(i), truth[i]);
  REQUIRE(r.peaks.size() == kept.size());
  for (size_t i = 0; i < kept.size(); ++i) {
    INFO("peak " << i << " at " << r.peaks[i].r_mm << " mm, true turn " << kept[i].first << " at " << kept[i].second);
    CHECK(r.peaks[i].turn == kept[i].first);
    CHECK(r.peaks[i].r_mm == Approx(kept[i].second).epsilon(0).margin(0.3));
  }
}

}  // namespace

TEST_CASE("peaks: a strongly oscillating separation skips no turn number (issue 15)", "[peaks]") {
  // 60 turns 15 -> 12 mm apart with a 5.4 mm betatron oscillation near the half-integer: the
  // separation swings between 2.7 and 25 mm, and 9 intervals are 1.8 times their neighbours'
  // mean, which the old gap rule took for missing turns (it numbered these turns up to 77).
  const auto truth = oscillating_turns(2100, 15, 12, 5.4, 5.4, 0.42, 0.5, 60);
  REQUIRE(old_rule_gaps(truth) == 9);
  for (unsigned seed : {1u, 2u}) {
    const auto p = make_profile(truth, 1.0, 2085, truth.back() + 15, 0.5, 0.005, seed);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 9);
    INFO("seed " << seed);
    check_numbers(r, truth, {}, 9);
    CHECK(r.skipped_turns == 0);
    CHECK(count_flag(r, kPeakGap | kPeakAmbiguous | kPeakCross) == 0);
    CHECK(r.doubts.empty());
  }
}

TEST_CASE("peaks: a missing turn is found where the separation oscillates", "[peaks]") {
  // The profile above with turn 29 lost, and turns 49-50 (two in a row): the numbers skip
  // exactly there, each gap flagged once, the rest numbered right.
  const auto truth = oscillating_turns(2100, 15, 12, 5.4, 5.4, 0.42, 0.5, 60);
  const std::vector<int> lost{20, 40, 41};
  std::vector<double> kept;
  for (size_t i = 0; i < truth.size(); ++i)
    if (std::find(lost.begin(), lost.end(), static_cast<int>(i)) == lost.end()) kept.push_back(truth[i]);
  for (unsigned seed : {1u, 2u}) {
    const auto p = make_profile(kept, 1.0, 2085, truth.back() + 15, 0.5, 0.005, seed);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 9);
    INFO("seed " << seed);
    check_numbers(r, truth, lost, 9);
    CHECK(r.skipped_turns == 3);
    REQUIRE(count_flag(r, kPeakGap) == 2);
    CHECK(r.peaks[20].flags == kPeakGap);
    CHECK(r.peaks[20].turn == 30);
    CHECK(r.peaks[39].flags == kPeakGap);
    CHECK(r.peaks[39].turn == 51);
    CHECK(count_flag(r, kPeakAmbiguous | kPeakCross) == 0);
  }
}

TEST_CASE("peaks: turns that cross are flagged and not silently numbered", "[peaks]") {
  // The oscillation grows from 2 to 7 mm on 12 -> 10 mm separations: from turn 56 (index 47)
  // on, pairs of turns cross, and a profile shows them in the order of position. Every peak
  // whose number the crossing makes wrong carries 'cross', and so do the turns from where they
  // first come within 0.15 trend separations; a warning names probe, turns and radii.
  const auto truth = oscillating_turns(2100, 12, 10, 2, 7, 0.45, 0.5, 60);
  std::vector<size_t> order(truth.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return truth[a] < truth[b]; });
  size_t first_swap = truth.size();
  for (size_t k = 0; k < order.size(); ++k)
    if (order[k] != k) first_swap = std::min(first_swap, k);
  REQUIRE(first_swap == 47);
  std::vector<double> sorted = truth;
  std::sort(sorted.begin(), sorted.end());
  const auto p = make_profile(sorted, 1.0, 2085, sorted.back() + 15, 0.5, 0.005, 1);
  const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 9);
  REQUIRE(r.peaks.size() >= 55);  // crossing turns that coincide are one peak (wide) or split (merged)
  // Every peak that is not where its number's true turn is (0.5 mm) is flagged cross.
  for (const Peak& pk : r.peaks) {
    const int i = pk.turn - 9;
    const bool right =
        i >= 0 && i < static_cast<int>(truth.size()) && std::abs(truth[static_cast<size_t>(i)] - pk.r_mm) < 0.5;
    INFO("turn " << pk.turn << " at " << pk.r_mm << " flags " << peak_flag_string(pk.flags));
    if (!right) CHECK((pk.flags & kPeakCross) != 0);
  }
  // The doubt starts at or before the first crossing and lasts to the end of the profile.
  REQUIRE(!r.doubts.empty());
  const auto cross = std::find_if(r.doubts.begin(), r.doubts.end(),
                                  [](const NumberingDoubt& d) { return d.kind == NumberingDoubt::kCross; });
  REQUIRE(cross != r.doubts.end());
  CHECK(r.peaks[cross->first].r_mm <= sorted[first_swap] + 0.5);
  CHECK(cross->last == r.peaks.size() - 1);
  // Before the turns touch, no gap; where they may cross, lengths do not count turns and a gap
  // (the last one: 20 mm after its sorted neighbour) is as doubtful as every other number.
  for (const Peak& pk : r.peaks)
    if (pk.flags & kPeakGap) CHECK((pk.flags & kPeakCross) != 0);
  // The warning names the probe, the turns and their radius.
  std::ostringstream os, err;
  peakfind_capturing(p, "# probe=RRX first_turn=9\nposition_mm,intensity\n", "x.csv", os, err);
  char expect[200];
  std::snprintf(expect, sizeof expect, "RRX (x.csv): turns %d-%d (r = %.2f to %.2f mm) may cross",
                r.peaks[cross->first].turn, r.peaks[cross->last].turn, r.peaks[cross->first].r_mm,
                r.peaks[cross->last].r_mm);
  CAPTURE(err.str());
  CHECK(err.str().find(expect) != std::string::npos);
  CHECK(os.str().find(",cross\n") != std::string::npos);
}

TEST_CASE("peaks: a gap between one and two separations is numbered as one turn and flagged ambiguous", "[peaks]") {
  // Turns every 10 mm without oscillation, but one interval 15 mm long: neither one turn nor
  // two. The numbering goes on without a skip (a missing turn needs evidence), the peak after
  // the gap is flagged and a warning says by how much later numbers may be off.
  std::vector<double> c;
  for (int i = 0; i < 30; ++i) c.push_back(2000 + 10.0 * i + (i >= 15 ? 5 : 0));
  const auto p = make_profile(c, 1.2, 1985, c.back() + 15, 0.5, 0.003, 2);
  const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 1);
  REQUIRE(r.peaks.size() == 30);
  CHECK(r.peaks.back().turn == 30);
  CHECK(r.skipped_turns == 0);
  CHECK(r.peaks[15].flags == kPeakAmbiguous);
  CHECK(count_flag(r, kPeakAmbiguous) == 1);
  REQUIRE(r.doubts.size() == 1);
  CHECK(r.doubts[0].kind == NumberingDoubt::kAmbiguousGap);
  CHECK(r.doubts[0].first == 15);
  CHECK(r.doubts[0].missing == 0);
  CHECK(r.doubts[0].alternative == 1);
  CHECK(peak_flag_string(r.peaks[15].flags) == "ambiguous");
  std::ostringstream os, err;
  peakfind_capturing(p, "# probe=P3\nposition_mm,intensity\n", "p3.csv", os, err);
  char expect[200];
  std::snprintf(expect, sizeof expect,
                "P3 (p3.csv): turn 16 at r = %.2f mm: the gap before it fits 0 or 1 missing turns alike", r.peaks[15].r_mm);
  CAPTURE(err.str());
  CHECK(err.str().find(expect) != std::string::npos);
  CHECK(err.str().find("may be short by 1") != std::string::npos);
  CHECK(os.str().find("ambiguous=1 cross=0") != std::string::npos);
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
  CHECK(line == "probe,turn,r_mm,height,area,width_mm,r_err_mm,flag");
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

TEST_CASE("peaks: the r_err_mm column reads back into a turn table (metrics), and is NaN without it", "[peaks]") {
  const auto truth = falling_separations(2100, 20, 6, 12);
  const auto syn = make_profile(truth, 1.5, 2090, truth.back() + 10, 0.5, 0.002, 4);
  const PeakResult r = find_peaks(syn.x, syn.y, PeakSettings{}, 9);
  std::ostringstream os;
  write_peaks_csv(os, "RRX", 9, r, false);
  const TurnTable t = turn_table_from_csv(CsvTable::parse(os.str(), "peaks.csv"));
  REQUIRE(t.points.size() == r.peaks.size());
  for (size_t i = 0; i < r.peaks.size(); ++i) {
    CHECK(t.points[i].turn == r.peaks[i].turn);
    CHECK(t.points[i].r_err_mm == Approx(r.peaks[i].r_err_mm).epsilon(0).margin(5e-7));  // printed to 1e-6 mm
    CHECK(t.points[i].r_err_mm > 0);
  }
  const TurnTable old = turn_table_from_csv(
      CsvTable::parse("probe,turn,r_mm,height,area,width_mm,flag\nRRX,9,2100,1,1,1,ok\n", "old.csv"));
  REQUIRE(old.points.size() == 1);
  CHECK(std::isnan(old.points[0].r_err_mm));
}

namespace {
/// The synth test machine's P0 profile (uniform isochronous field, 12 turns about 22 mm apart,
/// default noise and baseline) and the bunch centroids there, sorted.
std::pair<SynthProfile, std::vector<double>> synth_profile() {
  const Machine m = load_machine(std::string(TURNFIT_TEST_DIR) + "/cli/data/synth_iso.json");
  SynthSettings st;
  st.track.turns = 12;
  st.particles = 400;
  st.threads = 1;
  st.phases = false;
  const SynthResult res = synthesize(m, st);
  REQUIRE(res.profiles.size() == 1);
  std::vector<double> truth;
  for (const auto& c : res.centroids)
    if (c.probe == 0) truth.push_back(c.r_mm);
  std::sort(truth.begin(), truth.end());
  return {res.profiles[0], truth};
}
}  // namespace

TEST_CASE("peaks: turnfit-synth profiles: every turn at its bunch centroid", "[peaks]") {
  const auto [prof, truth] = synth_profile();
  const PeakResult r = find_peaks(prof.position_mm, prof.intensity, PeakSettings{}, 1);
  REQUIRE(r.peaks.size() == truth.size());
  CAPTURE(max_error(r, truth));
  // The deblended centroid is the bunch's mean position (turnfit-peakfind(1), Position reported):
  // ACCURACY promises a largest error below 0.1 mm for separated turns (ring8: 0.009 and
  // 0.058 mm). Half of that here, 0.05 mm (measured 0.021 mm).
  CHECK(max_error(r, truth) < 0.05);
  CHECK(count_flag(r, ~0u) == 0);
}

TEST_CASE("peaks: turnfit-synth profiles: the fitted centre's offset from the bunch centroid (regression)",
          "[peaks][regression]") {
  // --position fit reports the fitted Gaussian's centre, not the mean of a skewed turn
  // (turnfit-peakfind(1), Position reported): on this machine it misses the bunch centroids by up
  // to 0.124 mm, above ACCURACY's 0.1 mm (stated for sums of Gaussians) and ring8's 0.042/0.049 mm
  // (reported under issue 14). Trusted as the turns' skew, not a fit error: the centroid of the
  // same profile is within 0.021 mm (case above). Guards: the offset must not grow; 0.15 mm.
  const auto [prof, truth] = synth_profile();
  PeakSettings s;
  s.centroid = false;
  const PeakResult r = find_peaks(prof.position_mm, prof.intensity, s, 1);
  REQUIRE(r.peaks.size() == truth.size());
  CAPTURE(max_error(r, truth));
  CHECK(max_error(r, truth) < 0.15);
  CHECK(count_flag(r, ~0u) == 0);
}

TEST_CASE("peaks: a turn that loses area to its neighbour's wide fit does not make the neighbour two turns",
          "[peaks]") {
  // Readings of a blind-suite truth (tests/data/peaks/crowded-end.csv): the Gaussian fit gave turn
  // 178 half a turn's area and 179 1.8 turns' in a wide shape over both. Counted as two turns,
  // 179 shifted every later number by one; the pair holds two turns, every turn keeps its
  // number (the truth's bunch centres below), and 178, whose position rests on the bad split, is
  // flagged weak with an uncertainty that covers its 0.3 mm error.
  const ProbeProfile prof = read_profile(test::test_file("peaks/crowded-end.csv"));
  const PeakResult r = find_peaks(prof.position_mm, prof.intensity, PeakSettings{}, 166);
  const std::vector<double> truth = {4250.127, 4255.979, 4263.388, 4268.260, 4273.823, 4281.124,
                                     4286.176, 4291.187, 4298.290, 4303.862, 4308.288, 4314.769,
                                     4321.114, 4325.446, 4330.726, 4337.455, 4342.661};
  REQUIRE(r.peaks.size() == truth.size());
  CHECK(count_flag(r, kPeakWide) == 0);
  CHECK(r.skipped_turns == 0);
  CHECK((r.peaks[12].flags & kPeakWeak));
  CHECK(std::fabs(r.peaks[12].r_mm - truth[12]) < r.peaks[12].r_err_mm);
  for (size_t i = 0; i < truth.size(); ++i) {
    const Peak& p = r.peaks[i];
    INFO("turn " << p.turn << " at " << p.r_mm << " mm, r_err " << p.r_err_mm << ", truth " << truth[i]);
    CHECK(p.turn == 166 + static_cast<int>(i));
    // Every turn at its own centre, not a neighbour's 4-8 mm away (a few of these crowded turns
    // are 0.15-0.23 mm off, 3-4 r_err: the tails' bias, RESULTS). The readings start inside
    // turn 166: its position is the window's, not the probe's.
    if (i > 0) CHECK(std::fabs(p.r_mm - truth[i]) < std::max(0.25, 3 * p.r_err_mm));
  }
}

TEST_CASE("peaks: a turn cut by the profile's outer end is found, flagged edge, and leaves its neighbour in place",
          "[peaks]") {
  // RRL's outer end as blind run AB's control had it: turns 5.5 mm apart and 1 mm rms, the last
  // one centred one or two readings (0.5 or 0.8 mm) inside the last reading, so the readings peak
  // just before the end. The renormalized smoothing still rises into the last reading there: without a
  // candidate at the end the turn went unfound, and the fit gave its readings to the turn before,
  // 0.16 mm outward.
  std::vector<double> c;
  for (int i = 0; i < 9; ++i) c.push_back(4300 + 5.5 * i);
  for (const double inside : {0.5, 0.8}) {
    const auto p = make_profile(c, 1.0, 4290, c.back() + inside, 0.5, 0.004, 7);
    const PeakResult r = find_peaks(p.x, p.y, PeakSettings{}, 174);
    CAPTURE(inside);
    REQUIRE(r.peaks.size() == c.size());
    CHECK(r.peaks.back().turn == 182);
    CHECK((r.peaks.back().flags & kPeakEdge) != 0);
    // The part inside the end has its mean inward of the centre (a truncated Gaussian's); the
    // neighbour sits where it is.
    CHECK(r.peaks.back().r_mm < c.back());
    CHECK(r.peaks.back().r_mm > c.back() - 1.0);
    CHECK(r.peaks[r.peaks.size() - 2].r_mm == Approx(c[c.size() - 2]).epsilon(0).margin(0.02));
    CHECK((r.peaks[r.peaks.size() - 2].flags & kPeakEdge) == 0);
  }
  // A profile that ends on the baseline, where the noise alone rises into the last reading at
  // times, gains no turn at its end.
  const auto q = make_profile(c, 1.0, 4290, c.back() + 8, 0.5, 0.004, 7);
  const PeakResult rq = find_peaks(q.x, q.y, PeakSettings{}, 174);
  CHECK(rq.peaks.size() == c.size());
  CHECK((rq.peaks.back().flags & kPeakEdge) == 0);
}
