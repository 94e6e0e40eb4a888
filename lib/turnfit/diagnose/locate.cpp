// Noise of a residual from its own scatter, radial tunes, and where and how a residual departs
// from noise (offset, trend, oscillation at the radial tune, step, outliers, regions).
#include <algorithm>
#include <cmath>
#include <numeric>

#include "turnfit/cli/common.hpp"
#include "turnfit/diagnose/diagnose.hpp"
#include "turnfit/field/load.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/orbit/closed_orbit.hpp"

namespace turnfit {

using nlohmann::json;

namespace {

double median(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  const size_t h = v.size() / 2;
  std::nth_element(v.begin(), v.begin() + static_cast<long>(h), v.end());
  if (v.size() % 2) return v[h];
  const double hi = v[h];
  std::nth_element(v.begin(), v.begin() + static_cast<long>(h) - 1, v.end());
  return 0.5 * (hi + v[h - 1]);
}

double peak_error(const TurnPoint& pt) { return std::isnan(pt.r_err_mm) ? 0.0 : pt.r_err_mm; }

// The median of chi2 with one degree of freedom.
constexpr double kChi2Median1 = 0.454936423119573;

}  // namespace

NoiseEstimate estimate_noise(const TurnTable& measured, const std::vector<double>& e,
                             const std::vector<unsigned char>& matched, const ScanNoise& scan, double floor_mm) {
  NoiseEstimate out;
  out.scan = scan;
  out.probes = measured.probes;
  const size_t n = measured.points.size();
  out.sigma_mm.assign(n, 0);
  out.outlier.assign(n, 0);
  for (size_t p = 0; p < measured.probes.size(); ++p) {
    // Plain names, not a structured binding: lambdas below use them (C++17 forbids capturing a
    // binding; clang enforces it).
    const auto range = measured.probe_range(static_cast<int>(p));
    const size_t b = range.first, end = range.second;
    // The scatter s and the trust c in the peaks' own uncertainties: sigma_i^2 = s^2 + c^2 u_i^2.
    // For each c on a grid, s from the median condition (robust); c by the likelihood of the
    // second differences (each capped at 4 sigma, so a bad triple cannot steer it).
    double trust = 1;
    auto solve = [&](const std::vector<unsigned char>& skip, size_t& used) {
      std::vector<std::array<size_t, 3>> triples;
      for (size_t i = b + 1; i + 1 < end; ++i) {
        const auto& a = measured.points[i - 1];
        const auto& c = measured.points[i];
        const auto& d = measured.points[i + 1];
        if (c.turn - a.turn != 1 || d.turn - c.turn != 1) continue;
        if (!matched[i - 1] || !matched[i] || !matched[i + 1] || skip[i - 1] || skip[i] || skip[i + 1]) continue;
        triples.push_back({i - 1, i, i + 1});
      }
      used = triples.size();
      if (triples.size() < 3) return std::nan("");
      std::vector<double> d2(triples.size()), uu(triples.size()), dd(triples.size(), 0.0);
      bool any_u = false;
      for (size_t k = 0; k < triples.size(); ++k) {
        const auto& t = triples[k];
        d2[k] = std::pow(e[t[0]] - 2 * e[t[1]] + e[t[2]], 2);
        if (scan.active()) {
          const double r0 = measured.points[t[0]].r_mm, r1 = measured.points[t[1]].r_mm, r2 = measured.points[t[2]].r_mm;
          dd[k] = 6 * scan.covariance(r0, r0) - 4 * scan.covariance(r0, r1) - 4 * scan.covariance(r1, r2) +
                  2 * scan.covariance(r0, r2);
        }
        const double u0 = peak_error(measured.points[t[0]]), u1 = peak_error(measured.points[t[1]]),
                     u2 = peak_error(measured.points[t[2]]);
        uu[k] = u0 * u0 + 4 * u1 * u1 + u2 * u2;
        any_u = any_u || uu[k] > 0;
      }
      auto ratio_median = [&](double sc, double c) {
        std::vector<double> q(triples.size());
        for (size_t k = 0; k < q.size(); ++k) q[k] = d2[k] / std::max(6 * sc * sc + c * c * uu[k] + dd[k], 1e-300);
        return median(q);
      };
      auto scatter_for = [&](double c) {
        if (ratio_median(floor_mm, c) <= kChi2Median1) return floor_mm;
        double lo = floor_mm, hi = 1.0;
        while (ratio_median(hi, c) > kChi2Median1 && hi < 1e4) hi *= 4;
        for (int it = 0; it < 60; ++it) {
          const double mid = std::sqrt(lo * hi);
          (ratio_median(mid, c) > kChi2Median1 ? lo : hi) = mid;
        }
        return std::sqrt(lo * hi);
      };
      // The trust needs many differences: with RRI2's 14 the likelihood ran to the grid's end
      // on a blind control and the noise came out three times too small (a false alarm). Few
      // differences, or none with an uncertainty: the peaks' own at face value.
      if (!any_u || d2.size() < 40) {
        trust = 1;
        return scatter_for(1);
      }
      double best_ll = -1e300, best_s = floor_mm;
      for (int g = 0; g <= 48; ++g) {
        const double c = 0.5 * std::pow(6.0, g / 48.0);  // 0.5 .. 3
        const double sc = scatter_for(c);
        double ll = 0;
        for (size_t k = 0; k < d2.size(); ++k) {
          const double var = std::max(6 * sc * sc + c * c * uu[k] + dd[k], 1e-300);
          ll -= 0.5 * (std::min(d2[k] / var, 16.0) + std::log(var));
        }
        if (ll > best_ll) best_ll = ll, best_s = sc, trust = c;
      }
      return best_s;
    };
    std::vector<unsigned char> none(n, 0);
    size_t used = 0;
    double s = solve(none, used);
    if (std::isnan(s)) {  // too few consecutive turns: the scatter about the probe's mean
      std::vector<double> v;
      for (size_t i = b; i < end; ++i)
        if (matched[i]) v.push_back(e[i]);
      double mean = v.empty() ? 0 : std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
      double ss = 0;
      for (double x : v) ss += (x - mean) * (x - mean);
      // The scatter beyond the drive error's (which all of a few turns share in good part:
      // taking all of it off is the lower estimate, the one that raises no alarm).
      s = v.size() > 1 ? std::sqrt(std::max(0.0, ss / static_cast<double>(v.size() - 1) - scan.drive_mm * scan.drive_mm))
                       : floor_mm;
      s = std::max(s, floor_mm);
    }
    // Single outliers: beyond 5 sigma of the running median of five turns (a merged or
    // misplaced peak; no physics moves one turn alone); then the scatter again without them.
    for (int round = 0; round < 2; ++round) {
      for (size_t i = b; i < end; ++i) {
        if (!matched[i]) continue;
        std::vector<double> w;
        for (size_t k = (i >= b + 2 ? i - 2 : b); k < std::min(end, i + 3); ++k)
          if (matched[k]) w.push_back(e[k]);
        const double sig =
            std::sqrt(s * s + std::pow(trust * peak_error(measured.points[i]), 2) + scan.drive_mm * scan.drive_mm);
        out.outlier[i] = w.size() >= 4 && std::fabs(e[i] - median(w)) > 5 * sig;
      }
      const double again = solve(out.outlier, used);
      if (!std::isnan(again)) s = again;
    }
    out.scatter_mm.push_back(s);
    out.trust.push_back(trust);
    out.differences.push_back(used);
    for (size_t i = b; i < end; ++i) {
      const double u = trust * peak_error(measured.points[i]);
      out.sigma_mm[i] = std::sqrt(s * s + u * u);
    }
  }
  return out;
}

double TuneTable::at(double r) const {
  if (r_mm.empty()) return std::nan("");
  if (r <= r_mm.front()) return nu_r.front();
  if (r >= r_mm.back()) return nu_r.back();
  const size_t k = static_cast<size_t>(std::upper_bound(r_mm.begin(), r_mm.end(), r) - r_mm.begin());
  const double f = (r - r_mm[k - 1]) / (r_mm[k] - r_mm[k - 1]);
  return nu_r[k - 1] + f * (nu_r[k] - nu_r[k - 1]);
}

TuneTable radial_tunes(const Machine& m, unsigned threads) {
  TuneTable t;
  if (!m.injection) return t;
  const PolarFieldMap map = load_main_field(m);
  OrbitSettings os;
  os.mass_MeV = m.particle.mass_MeV;
  os.charge_e = m.particle.charge_e;
  // Energies from injection to where the map ends: closed orbits at 40 energies, geometric
  // spacing (the radius grows as the momentum does).
  const double e0 = m.injection->energy_MeV;
  std::vector<double> energies;
  for (int k = 0; k < 40; ++k) energies.push_back(e0 * std::pow(12.0, k / 39.0));
  const auto rows = orbit_table(map, os, energies, threads);
  for (const auto& r : rows)
    if (r.ok() && std::isfinite(r.nu_r) && (t.r_mm.empty() || r.r_avg_mm > t.r_mm.back())) {
      t.r_mm.push_back(r.r_avg_mm);
      t.nu_r.push_back(r.nu_r);
    }
  return t;
}

namespace {

/// Generalized least squares of y on the columns of A under the whitening W (one probe's
/// points: divided by sigma, or by the Cholesky factor of their covariance with scan noise);
/// returns chi2 of the residual and the fitted values (and the coefficients).
double wls(const Eigen::MatrixXd& A, const Eigen::VectorXd& y, const Whitener& W, Eigen::VectorXd* fit,
           Eigen::VectorXd* coef = nullptr) {
  Eigen::MatrixXd Aw = A;
  W.whiten_columns(Aw);
  Eigen::VectorXd yw = y;
  W.whiten(yw);
  const Eigen::VectorXd c = Aw.completeOrthogonalDecomposition().solve(yw);
  if (fit) *fit = A * c;
  if (coef) *coef = c;
  return (yw - Aw * c).squaredNorm();
}

Eigen::MatrixXd legendre(const Eigen::VectorXd& x, int degree) {
  Eigen::MatrixXd L(x.size(), degree + 1);
  for (Eigen::Index i = 0; i < x.size(); ++i) {
    double p0 = 1, p1 = x[i];
    L(i, 0) = 1;
    if (degree >= 1) L(i, 1) = p1;
    for (int d = 2; d <= degree; ++d) {
      const double p2 = ((2 * d - 1) * x[i] * p1 - (d - 1) * p0) / d;
      L(i, d) = p2;
      p0 = p1;
      p1 = p2;
    }
  }
  return L;
}

json range(double a, double b) { return json::array({a, b}); }

}  // namespace

Located locate(const TurnTable& measured, const std::vector<double>& e, const std::vector<unsigned char>& matched,
               const NoiseEstimate& noise, const TuneTable& tunes, double dof, double threshold) {
  Located out;
  const size_t N = measured.points.size();
  {
    std::vector<size_t> pts;
    for (size_t i = 0; i < N; ++i)
      if (matched[i] && !noise.outlier[i]) pts.push_back(i);
    out.points = pts.size();
    out.chi2 = Whitener(measured, pts, noise.sigma_mm, noise.scan).whitened(e).squaredNorm();
  }
  // Wilson and Hilferty's cube-root normal approximation of chi2's upper tail.
  if (dof > 0) {
    const double v = dof, zc = (std::cbrt(out.chi2 / v) - (1 - 2 / (9 * v))) / std::sqrt(2 / (9 * v));
    out.chi2_p_value = 0.5 * std::erfc(zc / std::sqrt(2.0));
  }
  const double logN = std::log(std::max<double>(2, static_cast<double>(out.points)));
  auto significant = [&](double dchi2, int k) { return dchi2 > k * logN + threshold; };
  if (out.chi2_p_value < 1e-3) out.significant = true;
  out.findings.push_back({{"kind", "overall"},
                          {"chi2", out.chi2},
                          {"points", out.points},
                          {"dof", dof},
                          {"chi2_per_dof", dof > 0 ? out.chi2 / dof : std::nan("")},
                          {"p_value", out.chi2_p_value},
                          {"significant", out.chi2_p_value < 1e-3}});

  for (size_t p = 0; p < measured.probes.size(); ++p) {
    const std::string& probe = measured.probes[p];
    auto [b, end] = measured.probe_range(static_cast<int>(p));
    std::vector<size_t> idx;
    for (size_t i = b; i < end; ++i) {
      if (!matched[i]) continue;
      if (noise.outlier[i]) {
        const auto& pt = measured.points[i];
        out.findings.push_back({{"kind", "outlier"},
                                {"probe", probe},
                                {"turns", range(pt.turn, pt.turn)},
                                {"r_mm", range(pt.r_mm, pt.r_mm)},
                                {"residual_mm", e[i]},
                                {"sigma_mm", noise.sigma_mm[i]},
                                {"significant", false},
                                {"text", "turn " + std::to_string(pt.turn) + " alone, " +
                                             cli::fmt(e[i] / noise.sigma_mm[i], 3) +
                                             " sigma from its neighbours: a peak, not physics (left out)"}});
        continue;
      }
      idx.push_back(i);
    }
    const auto n = static_cast<Eigen::Index>(idx.size());
    if (n < 3) continue;
    Eigen::VectorXd y(n), w(n), x(n), r(n);
    const double t0 = measured.points[idx.front()].turn, t1 = measured.points[idx.back()].turn;
    std::vector<double> rr, ss;
    for (Eigen::Index k = 0; k < n; ++k) {
      const auto& pt = measured.points[idx[static_cast<size_t>(k)]];
      y[k] = e[idx[static_cast<size_t>(k)]];
      w[k] = 1 / noise.sigma_mm[idx[static_cast<size_t>(k)]];
      x[k] = t1 > t0 ? 2 * (pt.turn - t0) / (t1 - t0) - 1 : 0;
      r[k] = pt.r_mm;
      rr.push_back(pt.r_mm);
      ss.push_back(noise.sigma_mm[idx[static_cast<size_t>(k)]]);
    }
    const Whitener W(measured, idx, noise.sigma_mm, noise.scan);
    // The points' covariance, for the regions' window sums (scan noise only).
    const Eigen::MatrixXd C = noise.scan.active() ? scan_covariance(rr, ss, noise.scan) : Eigen::MatrixXd();
    const double chi2_0 = W.whitened(e).squaredNorm();
    // One turn's noise: its sigma, with the drive error beside it.
    const double sigma_typ = std::hypot(1 / median(std::vector<double>(w.data(), w.data() + n)), noise.scan.drive_mm);
    auto turn_of = [&](Eigen::Index k) { return measured.points[idx[static_cast<size_t>(k)]].turn; };
    out.findings.push_back({{"kind", "probe"},
                            {"probe", probe},
                            {"turns", range(turn_of(0), turn_of(n - 1))},
                            {"r_mm", range(r.minCoeff(), r.maxCoeff())},
                            {"chi2", chi2_0},
                            {"points", n},
                            {"rms_mm", std::sqrt(y.squaredNorm() / static_cast<double>(n))},
                            {"noise_mm", sigma_typ}});

    // Offset.
    {
      Eigen::MatrixXd A = Eigen::MatrixXd::Ones(n, 1);
      Eigen::VectorXd fit;
      const double g = chi2_0 - wls(A, y, W, &fit);
      const bool sig = significant(g, 1);
      out.significant = out.significant || sig;
      out.findings.push_back({{"kind", "offset"},
                              {"probe", probe},
                              {"offset_mm", fit[0]},
                              {"delta_chi2", g},
                              {"significant", sig},
                              {"text", probe + " as a whole " + cli::fmt(fit[0], 3) + " mm"}});
    }
    // Smooth trend: Legendre degree by BIC.
    int best_d = -1;
    double best_bic = chi2_0, best_chi2 = chi2_0;
    Eigen::VectorXd trend = Eigen::VectorXd::Zero(n);
    for (int d = 0; d <= std::min<int>(8, static_cast<int>(n / 4)); ++d) {
      Eigen::VectorXd fit;
      const double c2 = wls(legendre(x, d), y, W, &fit);
      const double bic = c2 + (d + 1) * logN;
      if (bic < best_bic) best_bic = bic, best_d = d, best_chi2 = c2, trend = fit;
    }
    if (best_d >= 0) {
      const double g = chi2_0 - best_chi2;
      const bool sig = significant(g, best_d + 1);
      out.significant = out.significant || sig;
      // Its extent: where the trend is larger than the noise of one turn.
      Eigen::Index a = -1, z = -1, at = 0;
      for (Eigen::Index k = 0; k < n; ++k) {
        if (std::fabs(trend[k]) > std::fabs(trend[at])) at = k;
        if (std::fabs(trend[k]) > sigma_typ) {
          if (a < 0) a = k;
          z = k;
        }
      }
      json f = {{"kind", "trend"},   {"probe", probe},  {"degree", best_d},       {"delta_chi2", g},
                {"significant", sig}, {"peak_mm", trend[at]}, {"peak_turn", turn_of(at)}};
      if (a >= 0) {
        f["turns"] = range(turn_of(a), turn_of(z));
        f["r_mm"] = range(r[a], r[z]);
      }
      f["text"] = "a smooth trend (degree " + std::to_string(best_d) + ") up to " + cli::fmt(trend[at], 3) +
                  " mm at turn " + std::to_string(turn_of(at)) +
                  (a >= 0 ? ", above the noise over turns " + std::to_string(turn_of(a)) + "-" + std::to_string(turn_of(z))
                          : std::string());
      out.findings.push_back(f);
    }
    const Eigen::MatrixXd T = legendre(x, std::max(best_d, 0));
    Eigen::VectorXd trend_fit;
    const double chi2_t = wls(T, y, W, &trend_fit);

    // A coherent oscillation at the radial tune: betatron phase advanced by 2 pi nu_r a turn.
    if (!tunes.r_mm.empty() && n >= 8) {
      Eigen::VectorXd psi(n);
      psi[0] = 0;
      for (Eigen::Index k = 1; k < n; ++k)
        psi[k] = psi[k - 1] + 2 * M_PI * tunes.at(0.5 * (r[k] + r[k - 1])) * (turn_of(k) - turn_of(k - 1));
      Eigen::MatrixXd A(n, T.cols() + 4);
      A << T, psi.array().cos().matrix(), psi.array().sin().matrix(), psi.array().cos().matrix().cwiseProduct(x),
          psi.array().sin().matrix().cwiseProduct(x);
      Eigen::VectorXd fit;
      const double c2 = wls(A, y, W, &fit);
      const Eigen::VectorXd osc = fit - trend_fit;
      const double g = chi2_t - c2;
      const bool sig = significant(g, 4);
      out.significant = out.significant || sig;
      const double nu_mid = tunes.at(r[n / 2]);
      const double q = nu_mid - std::floor(nu_mid);
      out.findings.push_back({{"kind", "oscillation"},
                              {"probe", probe},
                              {"nu_r", nu_mid},
                              {"cycles_per_turn", std::min(q, 1 - q)},
                              {"delta_chi2", g},
                              {"significant", sig},
                              {"amplitude_mm", std::sqrt(2.0) * std::sqrt(osc.squaredNorm() / static_cast<double>(n))},
                              {"text", "an oscillation at the radial tune (nu_r " + cli::fmt(nu_mid, 4) + ", " +
                                           cli::fmt(std::min(q, 1 - q), 3) + " cycles a turn), amplitude " +
                                           cli::fmt(std::sqrt(2.0) * std::sqrt(osc.squaredNorm() / static_cast<double>(n)), 3) +
                                           " mm"}});
    }
    // A step over a quadratic background.
    if (n >= 10) {
      const Eigen::MatrixXd Q = legendre(x, 2);
      const double c2q = wls(Q, y, W, nullptr);
      double best = 0, size = 0;
      Eigen::Index at = -1;
      for (Eigen::Index k = 3; k + 3 <= n; ++k) {
        Eigen::MatrixXd A(n, 4);
        A << Q, (Eigen::VectorXd::LinSpaced(n, 0, static_cast<double>(n - 1)).array() >= static_cast<double>(k))
                    .cast<double>()
                    .matrix();
        Eigen::VectorXd c;
        const double g = c2q - wls(A, y, W, nullptr, &c);
        if (g > best) best = g, at = k, size = c[3];
      }
      if (at > 0) {
        // The step's place is a free parameter too: look-elsewhere as one more (k = 2).
        const bool sig = significant(best, 2) && best > 2 * std::log(static_cast<double>(n));
        out.significant = out.significant || sig;
        out.findings.push_back({{"kind", "step"},
                                {"probe", probe},
                                {"turns", range(turn_of(at - 1), turn_of(at))},
                                {"r_mm", range(r[at - 1], r[at])},
                                {"step_mm", size},
                                {"delta_chi2", best},
                                {"significant", sig},
                                {"text", "a step of " + cli::fmt(size, 3) + " mm between turns " +
                                             std::to_string(turn_of(at - 1)) + " and " + std::to_string(turn_of(at))}});
      }
    }
    // Regions: runs where the running mean over 5 turns lies beyond 3 sigma of its noise.
    {
      Eigen::Index k = 0;
      while (k < n) {
        // The window's mean in units of its own noise (with the drive error: the mean of y over
        // the window against the square root of the sum of its covariance).
        auto zbar = [&](Eigen::Index c) {
          const Eigen::Index a0 = std::max<Eigen::Index>(0, c - 2), a1 = std::min<Eigen::Index>(n - 1, c + 2);
          double s = 0;
          if (noise.scan.active()) {
            for (Eigen::Index j = a0; j <= a1; ++j) s += y[j];
            return s / std::sqrt(C.block(a0, a0, a1 - a0 + 1, a1 - a0 + 1).sum());
          }
          int m = 0;
          for (Eigen::Index j = a0; j <= a1; ++j) s += y[j] * w[j], ++m;
          return s / std::sqrt(static_cast<double>(m));
        };
        if (std::fabs(zbar(k)) <= 3) {
          ++k;
          continue;
        }
        const double sign = zbar(k) > 0 ? 1 : -1;
        Eigen::Index a = k;
        while (k < n && zbar(k) * sign > 3) ++k;
        const Eigen::Index z = k - 1;
        if (z - a + 1 < 3) continue;
        double c2 = 0, mean = 0, sw = 0;
        for (Eigen::Index j = a; j <= z; ++j) c2 += y[j] * w[j] * y[j] * w[j], mean += y[j] * w[j] * w[j], sw += w[j] * w[j];
        if (noise.scan.active()) {
          const Eigen::Index m = z - a + 1;
          const Eigen::VectorXd ys = y.segment(a, m);
          c2 = ys.dot(C.block(a, a, m, m).llt().solve(ys));
        }
        out.findings.push_back({{"kind", "region"},
                                {"probe", probe},
                                {"turns", range(turn_of(a), turn_of(z))},
                                {"r_mm", range(r[a], r[z])},
                                {"mean_mm", mean / sw},
                                {"chi2", c2},
                                {"points", z - a + 1},
                                {"significant", c2 - static_cast<double>(z - a + 1) > 3 * logN + threshold},
                                {"text", "turns " + std::to_string(turn_of(a)) + "-" + std::to_string(turn_of(z)) + " (" +
                                             cli::fmt(std::round(r[a]), 6) + "-" + cli::fmt(std::round(r[z]), 6) +
                                             " mm) " + (sign > 0 ? "the model outside the measurement" : "the model inside the measurement") + " by " +
                                             cli::fmt(std::fabs(mean / sw), 3) + " mm on average"}});
      }
    }
  }
  return out;
}

}  // namespace turnfit
