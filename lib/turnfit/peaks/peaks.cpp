// Peak finding in probe profiles: derivative zero-crossings (the paper), Gaussian fits, turn splitting.
#include "turnfit/peaks/peaks.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <sstream>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

// ---------------------------------------------------------------------------------------------
// Reading profiles

namespace {

/// Value of `key=` in a '#' line's whitespace-separated tokens ("" if absent).
std::string meta_value(const std::string& line, const std::string& key) {
  std::istringstream is(line.substr(1));
  std::string tok;
  while (is >> tok)
    if (tok.size() > key.size() && tok.compare(0, key.size() + 1, key + "=") == 0) return tok.substr(key.size() + 1);
  return {};
}

}  // namespace

ProbeProfile parse_profile(const std::string& text, const std::string& name) {
  const CsvTable t = CsvTable::parse(text, name);
  t.require_columns({"position_mm", "intensity"});
  const size_t cx = t.column("position_mm"), cy = t.column("intensity");
  ProbeProfile p;
  p.name = t.name();
  for (const auto& c : t.comments()) {
    // The first value of a key wins; a provenance argv line is the command, not metadata.
    if (c.rfind("# argv:", 0) == 0) continue;
    if (std::string v = meta_value(c, "probe"); !v.empty() && p.probe.empty()) p.probe = v;
    if (std::string v = meta_value(c, "step_mm"); !v.empty() && p.step_mm == 0)
      p.step_mm = parse_double(v, name, 0, "'# step_mm=' metadata");
    if (std::string v = meta_value(c, "first_turn"); !v.empty() && p.first_turn == 0) {
      const double f = parse_double(v, name, 0, "'# first_turn=' metadata");
      if (f != std::floor(f) || f < 1 || f > 1e9)
        throw data_error(name, 0, "'# first_turn=" + v + "' metadata: not a turn number (1, 2, ...)");
      p.first_turn = static_cast<int>(f);
    }
  }
  if (t.rows() < 5)
    throw data_error(name, 0, "a profile needs at least 5 readings, found " + std::to_string(t.rows()));
  for (size_t i = 0; i < t.rows(); ++i) {
    p.position_mm.push_back(t.number(i, cx));
    p.intensity.push_back(t.number(i, cy));
    p.line.push_back(t.line(i));
    if (i > 0 && !(p.position_mm[i] > p.position_mm[i - 1]))
      throw data_error(name, t.line(i), "position_mm must increase (" + t.cell(i, cx) + " after " +
                                            t.cell(i - 1, cx) + ")");
  }
  // The smoothing and the detector work on the reading index: the readings must be evenly spaced.
  const size_t n = p.position_mm.size();
  const double step = (p.position_mm[n - 1] - p.position_mm[0]) / static_cast<double>(n - 1);
  for (size_t i = 1; i < n; ++i) {
    const double d = p.position_mm[i] - p.position_mm[i - 1];
    if (std::abs(d - step) > 0.01 * step)
      throw data_error(name, p.line[i], "readings are not evenly spaced: step " + std::to_string(d) +
                                            " mm where the mean step is " + std::to_string(step) + " mm");
  }
  return p;
}

ProbeProfile read_profile(const std::string& path) {
  InputText in = read_input(path);
  return parse_profile(in.text, in.name);
}

std::string peak_flag_string(unsigned flags) {
  static const char* const names[] = {"merged", "wide", "weak", "gap", "edge", "ambiguous", "cross"};
  std::string s;
  for (unsigned b = 0; b < 7; ++b)
    if (flags & (1u << b)) s += (s.empty() ? "" : "+") + std::string(names[b]);
  return s.empty() ? "ok" : s;
}

// ---------------------------------------------------------------------------------------------
// Detection and fitting

namespace {

/// One turn's shape: a Gaussian of amplitude a, centre mu and rms sigma, with an inward tail of
/// t sigma (t = 0: none; see tail_shape).
struct Gauss {
  double a = 0, mu = 0, sigma = 1;
  double t = 0;       ///< inward tail: the exponential's mean over sigma (0: a plain Gaussian)
  double area_ref = 0;  ///< a turn's expected area a sigma sqrt(2 pi) (0: none; see lm_fit)
  double t_ref = -1;    ///< expected tail when tails are fitted (negative: none)
  double mu_var = 0;  ///< variance of mu from the last fit (noise only)
  unsigned flags = 0;
  int turns = 1;      ///< turns this peak stands for (more than 1 only for an unsplit wide peak)
  double mu_lo = -1e300, mu_hi = 1e300;  ///< where the next fit may move mu
};

double gauss_at(const Gauss& g, double x) {
  const double u = (x - g.mu) / g.sigma;
  return g.a * std::exp(-0.5 * u * u);
}

/// exp(w^2) erfc(w) for w >= 0, without overflow: directly below 25, else the asymptotic series
/// (Abramowitz and Stegun 7.1.23; four terms, relative error below 1e-10 from 25 on).
double erfcx_pos(double w) {
  if (w < 25) return std::exp(w * w) * std::erfc(w);
  const double v = 1 / (w * w);
  return (1 - 0.5 * v * (1 - 1.5 * v * (1 - 2.5 * v))) / (w * std::sqrt(M_PI));
}

/// A turn with an inward tail: a Gaussian (centre mu, rms sigma) convolved with an exponential of
/// mean t sigma towards smaller positions (an exponentially modified Gaussian, Grushka, Anal. Chem.
/// 44 (1972) 1733, mirrored), scaled so that it tends to the Gaussian exp(-z^2/2) as t -> 0 and
/// has the same area, a sigma sqrt(2 pi). Its mean is mu - t sigma, its variance sigma^2 (1 + t^2).
/// With z = (x - mu) / sigma and w = (1/t + z) / sqrt 2:
///   E(z, t) = sqrt(pi/2) / t exp(-z^2/2) erfcx(w),
/// written with erfc for w < 0 so that nothing overflows. Sets e (E) and g (the Gaussian).
void tail_shape(double z, double t, double& e, double& g) {
  g = std::exp(-0.5 * z * z);
  const double w = (1 / t + z) * M_SQRT1_2;
  e = w >= 0 ? std::sqrt(0.5 * M_PI) / t * g * erfcx_pos(w)
             : std::sqrt(0.5 * M_PI) / t * std::exp(0.5 / (t * t) + z / t) * std::erfc(w);
}

/// One turn's shape at x: the Gaussian, or with a tail (t > 0) the shape of tail_shape.
double shape_at(const Gauss& g, double x) {
  if (g.t == 0) return gauss_at(g, x);
  double e, gz;
  tail_shape((x - g.mu) / g.sigma, g.t, e, gz);
  return g.a * e;
}

/// The mean position of a turn's shape.
double shape_mean(const Gauss& g) { return g.mu - g.t * g.sigma; }

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  const size_t h = v.size() / 2;
  std::nth_element(v.begin(), v.begin() + static_cast<long>(h), v.end());
  double m = v[h];
  if (v.size() % 2 == 0) m = 0.5 * (m + *std::max_element(v.begin(), v.begin() + static_cast<long>(h)));
  return m;
}

/// Rms noise of one reading: the median absolute second difference of white noise is
/// 0.6745 sqrt(6) sigma. Second differences cancel the baseline and most of a smooth signal,
/// and the median ignores the peaks' flanks when most readings are between turns. Runs of
/// identical readings (the empty bins of a histogram of counts) carry no noise to measure and
/// are left out, else a histogram would seem noise-free and every count a turn.
double noise_estimate(const std::vector<double>& y) {
  std::vector<double> d2;
  for (size_t k = 1; k + 1 < y.size(); ++k)
    if (!(y[k - 1] == y[k] && y[k] == y[k + 1])) d2.push_back(std::abs(y[k + 1] - 2 * y[k] + y[k - 1]));
  return median(d2) / (0.6745 * std::sqrt(6.0));
}

/// Baseline b0 + b1 (x - x0): a straight line fitted to the readings that are not signal. Starting
/// from all readings, those more than 2 noise rms above the line are dropped and the line refitted,
/// until the set settles: the line sinks to the floor between turns (a constant offset plus a
/// slow drift, as a wire amplifier has).
void fit_baseline(const std::vector<double>& x, const std::vector<double>& y, double noise, double& b0,
                  double& b1) {
  const size_t n = x.size();
  std::vector<char> keep(n, 1);
  b0 = 0;
  b1 = 0;
  for (int it = 0; it < 100; ++it) {
    double sw = 0, sx = 0, sy = 0, sxx = 0, sxy = 0;
    for (size_t k = 0; k < n; ++k)
      if (keep[k]) {
        const double u = x[k] - x[0];
        sw += 1;
        sx += u;
        sy += y[k];
        sxx += u * u;
        sxy += u * y[k];
      }
    const double det = sw * sxx - sx * sx;
    if (sw < 2 || !(det > 0)) break;
    b1 = (sw * sxy - sx * sy) / det;
    b0 = (sy - b1 * sx) / sw;
    size_t changed = 0, kept = 0;
    for (size_t k = 0; k < n; ++k) {
      const char k_new = y[k] - (b0 + b1 * (x[k] - x[0])) <= 2 * noise;
      changed += k_new != keep[k];
      keep[k] = k_new;
      kept += k_new;
    }
    if (changed == 0 || kept < 2) break;
  }
}

/// Gaussian smoothing with rms `sigma_bins` (kernel to 4 sigma, renormalized at the ends so the
/// level of the profile is kept there).
std::vector<double> gaussian_smooth(const std::vector<double>& y, double sigma_bins) {
  const long n = static_cast<long>(y.size());
  const long h = std::max(1L, static_cast<long>(std::ceil(4 * sigma_bins)));
  std::vector<double> w(static_cast<size_t>(2 * h + 1));
  for (long j = -h; j <= h; ++j) w[static_cast<size_t>(j + h)] = std::exp(-0.5 * j * j / (sigma_bins * sigma_bins));
  std::vector<double> out(y.size());
  for (long k = 0; k < n; ++k) {
    double s = 0, sw = 0;
    for (long j = std::max(-h, -k); j <= std::min(h, n - 1 - k); ++j) {
      s += w[static_cast<size_t>(j + h)] * y[static_cast<size_t>(k + j)];
      sw += w[static_cast<size_t>(j + h)];
    }
    out[static_cast<size_t>(k)] = s / sw;
  }
  return out;
}

/// Levenberg-Marquardt fit of a sum of turn shapes to r[k] at x[k] (Press et al., Numerical
/// Recipes 15.5; parameters a, mu, ln sigma so that sigma stays positive, and with `fit_tail` each
/// turn's tail t, kept in [tmin, tmax]; otherwise every t stays as it is, 0 for a Gaussian).
/// Centres are kept in [lo, hi] and each in its own [mu_lo, mu_hi]; widths in [smin, smax].
/// Returns the residual sum of squares; sets each mu_var from the inverse normal matrix times
/// noise^2.
double lm_fit(const double* x, const double* r, long n, std::vector<Gauss>& g, double lo, double hi, double smin,
              double smax, double noise, bool fit_tail = false, double tmin = 0, double tmax = 0, double area_eps = 0, double t_eps = 0) {
  const long m = static_cast<long>(g.size()), q = fit_tail ? 4 : 3, np = q * m;
  if (m == 0 || n < np) return 0;
  // Expected areas as observations: (area_ref - area) / (area_eps area_ref), in noise units.
  std::vector<long> prior;
  if (area_eps > 0)
    for (long i = 0; i < m; ++i)
      if (g[static_cast<size_t>(i)].area_ref > 0) prior.push_back(i);
  std::vector<long> tprior;
  if (fit_tail && t_eps > 0)
    for (long i = 0; i < m; ++i)
      if (g[static_cast<size_t>(i)].t_ref >= 0) tprior.push_back(i);
  const long nr = n + static_cast<long>(prior.size() + tprior.size());
  using Eigen::MatrixXd;
  using Eigen::VectorXd;
  auto pack = [&](const std::vector<Gauss>& gs) {
    VectorXd p(np);
    for (long i = 0; i < m; ++i) {
      const Gauss& gi = gs[static_cast<size_t>(i)];
      p(q * i) = gi.a;
      p(q * i + 1) = gi.mu;
      p(q * i + 2) = std::log(gi.sigma);
      if (fit_tail) p(q * i + 3) = gi.t;
    }
    return p;
  };
  auto model_rss = [&](const VectorXd& p, MatrixXd* jac, VectorXd* res) {
    double rss = 0;
    for (long k = 0; k < n; ++k) {
      double f = 0;
      for (long i = 0; i < m; ++i) {
        const double a = p(q * i), mu = p(q * i + 1), s = std::exp(p(q * i + 2));
        const double t = fit_tail ? p(q * i + 3) : g[static_cast<size_t>(i)].t;
        const double u = (x[k] - mu) / s;
        if (t == 0) {
          const double e = std::exp(-0.5 * u * u);
          f += a * e;
          if (jac) {
            (*jac)(k, q * i) = e;
            (*jac)(k, q * i + 1) = a * e * u / s;
            (*jac)(k, q * i + 2) = a * e * u * u;
          }
          continue;
        }
        // tail_shape's E and its derivatives: dE/dz = (E - G) / t,
        // dE/dt = (G - E) / t^3 - E (t + z) / t^2.
        double e, ga;
        tail_shape(u, t, e, ga);
        f += a * e;
        if (jac) {
          const double dz = (e - ga) / t;
          (*jac)(k, q * i) = e;
          (*jac)(k, q * i + 1) = -a * dz / s;
          (*jac)(k, q * i + 2) = -a * dz * u;
          if (fit_tail) (*jac)(k, q * i + 3) = a * ((ga - e) / (t * t * t) - e * (t + u) / (t * t));
        }
      }
      const double d = r[k] - f;
      if (res) (*res)(k) = d;
      rss += d * d;
    }
    for (size_t c = 0; c < prior.size(); ++c) {
      const long i = prior[c], k = n + static_cast<long>(c);
      const double ar = g[static_cast<size_t>(i)].area_ref, wt = noise / (area_eps * ar);
      const double s2 = std::exp(p(q * i + 2)) * std::sqrt(2 * M_PI), area = p(q * i) * s2;
      const double d = wt * (ar - area);
      if (jac) {
        (*jac).row(k).setZero();
        (*jac)(k, q * i) = wt * s2;
        (*jac)(k, q * i + 2) = wt * area;
      }
      if (res) (*res)(k) = d;
      rss += d * d;
    }
    for (size_t c = 0; c < tprior.size(); ++c) {
      const long i = tprior[c], k = n + static_cast<long>(prior.size() + c);
      const double wt = noise / t_eps, d = wt * (g[static_cast<size_t>(i)].t_ref - p(q * i + 3));
      if (jac) {
        (*jac).row(k).setZero();
        (*jac)(k, q * i + 3) = wt;
      }
      if (res) (*res)(k) = d;
      rss += d * d;
    }
    return rss;
  };
  auto clamp = [&](VectorXd& p) {
    for (long i = 0; i < m; ++i) {
      const Gauss& gi = g[static_cast<size_t>(i)];
      p(q * i + 1) = std::clamp(p(q * i + 1), std::max(lo, gi.mu_lo), std::min(hi, gi.mu_hi));
      p(q * i + 2) = std::clamp(p(q * i + 2), std::log(smin), std::log(smax));
      if (fit_tail) p(q * i + 3) = std::clamp(p(q * i + 3), tmin, tmax);
    }
  };
  VectorXd p = pack(g);
  clamp(p);
  MatrixXd J(nr, np);
  VectorXd res(nr);
  double rss = model_rss(p, &J, &res);
  double lambda = 1e-3;
  for (int it = 0; it < 200; ++it) {
    const MatrixXd A = J.transpose() * J;
    const VectorXd b = J.transpose() * res;
    bool improved = false;
    while (lambda < 1e12) {
      MatrixXd Al = A;
      for (long j = 0; j < np; ++j) Al(j, j) += lambda * std::max(A(j, j), 1e-300);
      VectorXd trial = p + Al.ldlt().solve(b);
      clamp(trial);
      const double rt = model_rss(trial, nullptr, nullptr);
      if (std::isfinite(rt) && rt < rss) {
        const double gain = rss - rt;
        p = trial;
        rss = model_rss(p, &J, &res);
        lambda = std::max(lambda / 3, 1e-12);
        improved = gain > 1e-13 * rss + 1e-300;
        break;
      }
      lambda *= 4;
    }
    if (!improved) break;
  }
  const MatrixXd A = J.transpose() * J;
  Eigen::LDLT<MatrixXd> ldlt(A);
  MatrixXd cov = ldlt.solve(MatrixXd::Identity(np, np));
  for (long i = 0; i < m; ++i) {
    Gauss& gi = g[static_cast<size_t>(i)];
    gi.a = p(q * i);
    gi.mu = p(q * i + 1);
    gi.sigma = std::exp(p(q * i + 2));
    if (fit_tail) gi.t = p(q * i + 3);
    const double v = cov(q * i + 1, q * i + 1) * noise * noise;
    gi.mu_var = std::isfinite(v) && v > 0 ? v : 0;
  }
  return rss;
}

/// The profile and everything derived from it that the fitting steps share.
struct Work {
  const std::vector<double>& x;
  const std::vector<double>& y;
  std::vector<double> bg;  ///< baseline at each reading
  double step = 0, noise = 0, scale = 0, smin = 0, smax = 0;
  long n = 0;
  bool fit_tail = false;       ///< fit each turn's tail too (else every tail stays as it is)
  double tmin = 0, tmax = 0;   ///< ... within these bounds
  double area_eps = 0;         ///< relative uncertainty of the turns' expected areas (0: not used)
  double t_eps = 0;             ///< uncertainty of the turns' expected tails, when fitted (0: not used)

  /// Whether x is within a turn's reach (8 widths, and 16 tail lengths more inward): beyond, its
  /// shape is below 1e-7 of its height.
  static bool within(const Gauss& g, double x) {
    return x > g.mu - (8 + 16 * g.t) * g.sigma && x < g.mu + 8 * g.sigma;
  }

  long index_at(double pos) const {
    return std::clamp(static_cast<long>(std::floor((pos - x[0]) / step + 0.5)), 0L, n - 1);
  }

  /// Fits the peaks `block` (indices into g) to the readings in their reach, with every other
  /// peak and the baseline held fixed, over [lo, hi] (default: 4 widths around the block, and 4
  /// tail lengths more inward).
  /// Returns the residual sum of squares in that window.
  double fit_block(std::vector<Gauss>& g, const std::vector<size_t>& block, double lo = 1e300,
                   double hi = -1e300) const {
    if (lo > hi)
      for (size_t i : block) {
        lo = std::min(lo, g[i].mu - (4 + 4 * g[i].t) * g[i].sigma);
        hi = std::max(hi, g[i].mu + 4 * g[i].sigma);
      }
    const long k0 = index_at(lo), k1 = index_at(hi);
    std::vector<double> xs, rs;
    for (long k = k0; k <= k1; ++k) {
      double f = y[static_cast<size_t>(k)] - bg[static_cast<size_t>(k)];
      for (size_t j = 0; j < g.size(); ++j)
        if (std::find(block.begin(), block.end(), j) == block.end() && within(g[j], x[static_cast<size_t>(k)]))
          f -= shape_at(g[j], x[static_cast<size_t>(k)]);
      xs.push_back(x[static_cast<size_t>(k)]);
      rs.push_back(f);
    }
    // Each centre may move at most 0.45 of the way to its neighbours: two turns cannot swap or
    // meet in one fit, so a fit cannot trade one turn for another.
    std::vector<Gauss> sub;
    for (size_t i : block) {
      sub.push_back(g[i]);
      if (i > 0) sub.back().mu_lo = g[i].mu - 0.45 * (g[i].mu - g[i - 1].mu);
      if (i + 1 < g.size()) sub.back().mu_hi = g[i].mu + 0.45 * (g[i + 1].mu - g[i].mu);
    }
    const double rss = lm_fit(xs.data(), rs.data(), static_cast<long>(xs.size()), sub, x[static_cast<size_t>(k0)],
                              x[static_cast<size_t>(k1)], smin, smax, noise, fit_tail, tmin, tmax, area_eps, t_eps);
    for (size_t b = 0; b < block.size(); ++b) {
      const unsigned f = g[block[b]].flags;
      const int t = g[block[b]].turns;
      g[block[b]] = sub[b];
      g[block[b]].flags = f;
      g[block[b]].turns = t;
    }
    return rss;
  }

  /// Whether peaks i and j overlap enough to be fitted together.
  static bool overlap(const Gauss& a, const Gauss& b) { return std::abs(a.mu - b.mu) < 4 * (a.sigma + b.sigma); }

  /// Sweeps over all peaks, each fitted with its overlapping neighbours, until the centres settle
  /// (block coordinate descent: cost grows with the number of turns, not its cube).
  void refine(std::vector<Gauss>& g, bool sort = true, int sweeps = 8) const {
    for (int sweep = 0; sweep < sweeps; ++sweep) {
      double moved = 0;
      for (size_t i = 0; i < g.size(); ++i) {
        std::vector<size_t> block;
        if (i > 0 && overlap(g[i - 1], g[i])) block.push_back(i - 1);
        block.push_back(i);
        if (i + 1 < g.size() && overlap(g[i + 1], g[i])) block.push_back(i + 1);
        const double before = g[i].mu;
        fit_block(g, block);
        moved = std::max(moved, std::abs(g[i].mu - before));
      }
      if (sort) std::sort(g.begin(), g.end(), [](const Gauss& a, const Gauss& b) { return a.mu < b.mu; });
      if (moved < 1e-5 * step) break;
    }
  }

  /// Removes what the fit reduced to nothing: amplitude below half the height threshold, or two
  /// centres within half a width (the fit merged two candidates into one turn). Returns how many.
  int prune(std::vector<Gauss>& g, double min_amp) const {
    int dropped = 0;
    for (size_t i = 0; i < g.size();) {
      bool drop = g[i].a < min_amp;
      if (!drop && i + 1 < g.size() && g[i + 1].mu - g[i].mu < 0.5 * std::min(g[i].sigma, g[i + 1].sigma)) {
        if (g[i + 1].a < g[i].a) {
          g.erase(g.begin() + static_cast<long>(i) + 1);
          ++dropped;
          continue;
        }
        drop = true;
      }
      if (drop) {
        g.erase(g.begin() + static_cast<long>(i));
        ++dropped;
      } else {
        ++i;
      }
    }
    return dropped;
  }
};

/// Median of v[j] over up to `reach` neighbours on each side of i (i itself left out).
double neighbour_median(const std::vector<double>& v, size_t i, size_t reach) {
  std::vector<double> s;
  for (size_t j = i >= reach ? i - reach : 0; j < std::min(v.size(), i + reach + 1); ++j)
    if (j != i) s.push_back(v[j]);
  return s.size() >= 2 ? median(s) : 0;
}

/// Turn separations from peak q's centre to peak q+1's: a peak standing for k turns has its
/// centre in the middle of them.
double turn_steps(const std::vector<Gauss>& g, size_t q) { return 0.5 * (g[q].turns + g[q + 1].turns); }

/// Expected turn separation around the interval (j, j+1): the mean separation over up to 6
/// intervals on each side, that interval left out. A mean, not a median: an off-centre beam
/// makes separations alternate (betatron oscillation), and the mean over several turns is the
/// radius gain per turn. 0 if fewer than 2 intervals.
double mean_separation(const std::vector<Gauss>& g, size_t j) {
  if (g.size() < 3) return 0;
  const size_t lo = j >= 6 ? j - 6 : 0, hi = std::min(g.size() - 1, j + 7);
  double span = g[hi].mu - g[lo].mu, intervals = 0;
  for (size_t q = lo; q < hi; ++q) intervals += turn_steps(g, q);
  if (j + 1 <= hi && j >= lo) {
    span -= g[j + 1].mu - g[j].mu;
    intervals -= turn_steps(g, j);
  }
  return intervals >= 2 ? span / intervals : 0;
}

/// Expected separation at peak i: the mean over its neighbourhood without the intervals that
/// involve i (0 if too few).
double expected_separation(const std::vector<Gauss>& g, size_t i) {
  if (g.size() < 4) return 0;
  const size_t lo = i >= 6 ? i - 6 : 0, hi = std::min(g.size() - 1, i + 6);
  double span = g[hi].mu - g[lo].mu, intervals = 0;
  for (size_t q = lo; q < hi; ++q) intervals += turn_steps(g, q);
  if (i > lo) {
    span -= g[i].mu - g[i - 1].mu;
    intervals -= turn_steps(g, i - 1);
  }
  if (i < hi) {
    span -= g[i + 1].mu - g[i].mu;
    intervals -= turn_steps(g, i);
  }
  return intervals >= 2 ? span / intervals : 0;
}

// ---------------------------------------------------------------------------------------------
// The turns' shapes for their positions

/// A turn's area may differ from its neighbours' median by this fraction (1 sigma): in a CW beam
/// every turn carries the same particles (on turnfit-synth profiles the fitted areas of separated
/// turns scatter by 1-3 %, the shape's doing; the tuning preferred 0.5 % to 1 and 2 %).
constexpr double kAreaEps = 0.005;
/// ... unless it is clear of its neighbours (kClearWidths) and this fraction off: a weak or cut
/// turn keeps its own area. A crowded turn never does: its fitted area is what goes wrong.
constexpr double kAreaOwn = 0.25;
/// A clear turn (its tail fitted alone): both neighbours at least this many widths away.
constexpr double kClearWidths = 5;
/// Tails: start, bounds (fractions of sigma), the clear turns whose median a turn's tail is
/// expected to be, and how far (1 sigma) a turn's own tail may stray from that.
constexpr double kTailStart = 0.3, kTailMin = 0.02, kTailMax = 1.5;
constexpr size_t kTailNearest = 13;
constexpr double kTailEps = 0.1;

/// The turns' shapes for their positions (turnfit-peakfind(1), "Position reported"). A turn is
/// not Gaussian: particles off the RF crest gain less energy, so it has a tail inward, and its
/// mean (the bunch's centre, what a fit of the turns models) lies inward of its top. Where turns
/// crowd, Gaussians that miss the tails misplace them outward: the next turn's tail counts for
/// this one, and of two merged turns the inner one takes area (and readings) from the outer one,
/// both moving outward (on turnfit-synth truths by up to 0.7 mm). Here every turn gets a tail
/// (tail_shape) and the expected area:
/// 1. each single turn's expected area: the median of the areas of the 12 turns of their own
///    (neither merged nor wide) nearest by index, kept within kAreaEps unless the turn is clear
///    of its neighbours and kAreaOwn off;
/// 2. the tails of clear turns, each fitted alone; a turn's expected tail is the median of the
///    kTailNearest clear turns nearest by index (no clear turn: no tails);
/// 3. all turns refitted with their expected tails, then once more with their own tails kept
///    within kTailEps of the expected ones (the tails of crowded turns alternate with the beam's
///    oscillation: the inner turn of a close pair is skewed, the outer one hardly).
/// Returns the shapes, in g's order.
std::vector<Gauss> shaped_turns(Work& w, const std::vector<Gauss>& g) {
  std::vector<Gauss> e = g;
  const size_t n = g.size();
  std::vector<double> area(n);
  for (size_t i = 0; i < n; ++i) area[i] = g[i].a * g[i].sigma * std::sqrt(2 * M_PI);
  std::vector<size_t> single;  // turns of their own: neither merged nor wide
  for (size_t j = 0; j < n; ++j)
    if (g[j].turns == 1 && !(g[j].flags & kPeakMerged)) single.push_back(j);
  for (size_t i = 0; i < n; ++i) {
    if (g[i].turns != 1) continue;
    // The up to 12 nearest (by index) turns of their own: where every turn merges with another,
    // the nearest ones that do not.
    std::vector<std::pair<size_t, double>> near;
    for (size_t j : single)
      if (j != i) near.push_back({j > i ? j - i : i - j, area[j]});
    std::sort(near.begin(), near.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    std::vector<double> v;
    for (size_t c = 0; c < std::min<size_t>(near.size(), 12); ++c) v.push_back(near[c].second);
    if (v.size() < 3) continue;
    const double ref = median(v);
    double d = 1e300;
    if (i > 0) d = std::min(d, g[i].mu - g[i - 1].mu);
    if (i + 1 < n) d = std::min(d, g[i + 1].mu - g[i].mu);
    const bool crowded = (g[i].flags & kPeakMerged) || d < kClearWidths * g[i].sigma;
    if (crowded || std::abs(area[i] / ref - 1) < kAreaOwn) e[i].area_ref = ref;
  }
  w.area_eps = kAreaEps;
  w.tmin = kTailMin;
  w.tmax = kTailMax;
  std::vector<size_t> clear;
  std::vector<double> tc;
  w.fit_tail = true;
  for (size_t i = 0; i < n; ++i) {
    double d = 1e300;
    if (i > 0) d = std::min(d, g[i].mu - g[i - 1].mu);
    if (i + 1 < n) d = std::min(d, g[i + 1].mu - g[i].mu);
    if (g[i].turns != 1 || g[i].flags != 0 || d < kClearWidths * g[i].sigma) continue;
    std::vector<Gauss> one = g;
    one[i].t = kTailStart;
    w.fit_block(one, {i});
    clear.push_back(i);
    tc.push_back(one[i].t);
  }
  w.fit_tail = false;
  if (!clear.empty()) {
    for (size_t i = 0; i < n; ++i) {
      std::vector<std::pair<size_t, double>> near;
      for (size_t c = 0; c < clear.size(); ++c) near.push_back({clear[c] > i ? clear[c] - i : i - clear[c], tc[c]});
      std::sort(near.begin(), near.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
      std::vector<double> v;
      for (size_t c = 0; c < std::min(near.size(), kTailNearest); ++c) v.push_back(near[c].second);
      e[i].t = e[i].t_ref = median(v);
    }
  }
  w.refine(e, false);
  if (!clear.empty()) {
    // One sweep: a second moved the tuning truths' bias and RMS by less than 0.001 mm, and
    // costs as much again.
    w.fit_tail = true;
    w.t_eps = kTailEps;
    w.refine(e, false, 1);
    w.fit_tail = false;
  }
  w.area_eps = 0;
  w.t_eps = 0;
  return e;
}

// ---------------------------------------------------------------------------------------------
// Turn numbering

/// Position against turn index near an interval: the beam-centring model of ../shared/docs/
/// physics.md (r_n = r_0 + <dr/dn> n + A sin(2 pi nu_r n + phi) over a short range of turns, a
/// coherent betatron oscillation about the accelerated orbit, the paper's Figs. 6-7), with a
/// quadratic trend (the radius gain per turn changes with energy) and a phase advance per turn
/// that drifts linearly (nu_r changes with energy):
///   r(t) = c0 + c1 v + c2 v^2 + c3 cos(phi) + c4 sin(phi),  u = t - tc, v = u / h,
///   phi = mu u + kappa u^2 / 2.
/// A probe sees each turn once, so only mu = 2 pi nu_r modulo 2 pi shows, folded into (0, pi].
struct TurnModel {
  double rss = 1e300, mu = 0, kappa = 0;
  double c[5] = {0, 0, 0, 0, 0};
};

/// The peaks of one window: turn index t (relative), position r (less a reference), weight w.
struct TurnWindow {
  std::vector<double> t, r, w;
  double tc = 0, h = 1;

  // The sums over the window that do not depend on (mu, kappa): the trend columns 1, v, v^2.
  double p_[3][3] = {}, bp_[3] = {}, rr_ = 0;
  std::vector<double> v_;

  /// Computes the trend sums; call after t, r, w, tc and h are set.
  void prepare() {
    v_.resize(t.size());
    for (auto& row : p_) std::fill(std::begin(row), std::end(row), 0.0);
    std::fill(std::begin(bp_), std::end(bp_), 0.0);
    rr_ = 0;
    for (size_t i = 0; i < t.size(); ++i) {
      const double v = (t[i] - tc) / h, f[3] = {1, v, v * v};
      v_[i] = v;
      for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b) p_[a][b] += w[i] * f[a] * f[b];
        bp_[a] += w[i] * r[i] * f[a];
      }
      rr_ += w[i] * r[i] * r[i];
    }
  }

  /// Linear least squares of the five coefficients, given cos and sin of the phase at each peak
  /// (normal equations, Cholesky); returns the weighted rss. The positions are relative to a peak
  /// of the window, so that sum w r^2 - c.b keeps the digits that matter.
  double solve(const double* cph, const double* sph, TurnModel& m) const {
    double a[5][5], b[5];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) a[i][j] = p_[i][j];
      b[i] = bp_[i];
    }
    double sc[3] = {0, 0, 0}, ss[3] = {0, 0, 0}, scc = 0, sss = 0, scs = 0, src = 0, srs = 0;
    for (size_t i = 0; i < t.size(); ++i) {
      const double wc = w[i] * cph[i], ws = w[i] * sph[i], v = v_[i];
      sc[0] += wc;
      sc[1] += wc * v;
      sc[2] += wc * v * v;
      ss[0] += ws;
      ss[1] += ws * v;
      ss[2] += ws * v * v;
      scc += wc * cph[i];
      sss += ws * sph[i];
      scs += wc * sph[i];
      src += wc * r[i];
      srs += ws * r[i];
    }
    for (int i = 0; i < 3; ++i) {
      a[i][3] = a[3][i] = sc[i];
      a[i][4] = a[4][i] = ss[i];
    }
    a[3][3] = scc;
    a[4][4] = sss;
    a[3][4] = a[4][3] = scs;
    b[3] = src;
    b[4] = srs;
    // A column that vanishes on the turns (sin(pi u) at whole turns) or repeats another (a slow
    // cosine against the quadratic) gets no weight instead of an arbitrary one.
    double trace = 0;
    for (int i = 0; i < 5; ++i) trace += a[i][i];
    const double ridge = 1e-10 * trace / 5 + 1e-300;
    double l[5][5] = {}, y[5], c[5];
    for (int i = 0; i < 5; ++i) {
      for (int j = 0; j <= i; ++j) {
        double sum = a[i][j] + (i == j ? ridge : 0);
        for (int k = 0; k < j; ++k) sum -= l[i][k] * l[j][k];
        l[i][j] = i == j ? std::sqrt(std::max(sum, ridge)) : sum / l[j][j];
      }
    }
    for (int i = 0; i < 5; ++i) {
      double sum = b[i];
      for (int k = 0; k < i; ++k) sum -= l[i][k] * y[k];
      y[i] = sum / l[i][i];
    }
    for (int i = 4; i >= 0; --i) {
      double sum = y[i];
      for (int k = i + 1; k < 5; ++k) sum -= l[k][i] * c[k];
      c[i] = sum / l[i][i];
    }
    double cb = 0;
    for (int i = 0; i < 5; ++i) {
      m.c[i] = std::isfinite(c[i]) ? c[i] : 0;
      cb += m.c[i] * b[i];
    }
    // At the least-squares solution c.A.c = c.b: rss = r.r - c.b.
    m.rss = std::max(0.0, rr_ - cb);
    return m.rss;
  }

  /// The least-squares coefficients for one (mu, kappa); returns the weighted rss.
  double fit(TurnModel& m) const {
    std::vector<double> cph(t.size()), sph(t.size());
    for (size_t i = 0; i < t.size(); ++i) {
      const double u = t[i] - tc, ph = m.mu * u + 0.5 * m.kappa * u * u;
      cph[i] = std::cos(ph);
      sph[i] = std::sin(ph);
    }
    return solve(cph.data(), sph.data(), m);
  }

  /// The best model: a grid over mu in (0, pi] and kappa in [-0.04, 0.04] per turn (nu_r may
  /// change by up to 0.0064 a turn; ring8's changes by 0.0036), then a pattern search from the two
  /// best grid points. Over +-12 turns the grid's half steps leave at most 0.4 rad of phase error
  /// for the search to take out.
  TurnModel best() const {
    constexpr int n_mu = 48, n_kappa = 9;
    constexpr double kappa_max = 0.04;
    const double d_mu = M_PI / n_mu, d_kappa = 2 * kappa_max / (n_kappa - 1);
    const size_t np = t.size();
    // cos and sin of mu u and of kappa u^2 / 2 on the grid, combined by the angle-sum formulas.
    std::vector<double> cm(n_mu * np), sm(n_mu * np), ck(n_kappa * np), sk(n_kappa * np), cph(np), sph(np);
    for (int i = 0; i < n_mu; ++i)
      for (size_t k = 0; k < np; ++k) {
        const double ph = (i + 1) * d_mu * (t[k] - tc);
        cm[i * np + k] = std::cos(ph);
        sm[i * np + k] = std::sin(ph);
      }
    for (int j = 0; j < n_kappa; ++j)
      for (size_t k = 0; k < np; ++k) {
        const double u = t[k] - tc, ph = 0.5 * (-kappa_max + j * d_kappa) * u * u;
        ck[j * np + k] = std::cos(ph);
        sk[j * np + k] = std::sin(ph);
      }
    TurnModel best1, best2;
    for (int i = 0; i < n_mu; ++i)
      for (int j = 0; j < n_kappa; ++j) {
        for (size_t k = 0; k < np; ++k) {
          const double c1 = cm[i * np + k], s1 = sm[i * np + k], c2 = ck[j * np + k], s2 = sk[j * np + k];
          cph[k] = c1 * c2 - s1 * s2;
          sph[k] = s1 * c2 + c1 * s2;
        }
        TurnModel m;
        m.mu = (i + 1) * d_mu;
        m.kappa = -kappa_max + j * d_kappa;
        solve(cph.data(), sph.data(), m);
        if (m.rss < best1.rss) {
          best2 = best1;
          best1 = m;
        } else if (m.rss < best2.rss) {
          best2 = m;
        }
      }
    TurnModel out = best1;
    for (TurnModel m : {best1, best2}) {
      if (!(m.rss < 1e299)) continue;
      double step_mu = 0.5 * d_mu, step_kappa = 0.5 * d_kappa;
      for (int it = 0; it < 40 && step_mu > 1e-3 * d_mu; ++it) {
        bool moved = false;
        for (int k = 0; k < 4; ++k) {
          TurnModel trial = m;
          trial.mu = std::clamp(m.mu + (k == 0 ? step_mu : k == 1 ? -step_mu : 0), 1e-3, M_PI);
          trial.kappa = std::clamp(m.kappa + (k == 2 ? step_kappa : k == 3 ? -step_kappa : 0), -kappa_max, kappa_max);
          fit(trial);
          if (trial.rss < m.rss) {
            m = trial;
            moved = true;
          }
        }
        if (!moved) {
          step_mu *= 0.5;
          step_kappa *= 0.5;
        }
      }
      if (m.rss < out.rss) out = m;
    }
    return out;
  }
};

/// Turn numbers of the peaks (turnfit-peakfind(1), "Numbering and flags"): how many turns are
/// missing before each peak, and the flags and doubts of the numbering.
struct Numbering {
  std::vector<int> missing;       ///< turns missing between peak j-1 and peak j
  std::vector<unsigned> flags;    ///< kPeakGap, kPeakAmbiguous, kPeakCross per peak
  std::vector<NumberingDoubt> doubts;
  int model_judged = 0;             ///< intervals the position model had to judge
};

/// Fewest peaks for the numbering below (fewer: the gap-ratio rule); intervals on each side
/// whose lengths make the envelope; peaks on each side that the position model sees.
constexpr size_t kNumberingMinPeaks = 12, kEnvelopeReach = 8, kModelReach = 12;
/// How far, in trend separations, an interval may lie outside the envelope of its count of turns
/// (position errors of merged turns, an oscillation that grows within the window).
constexpr double kLengthSlack = 0.2;
/// A count of missing turns is decided when every other count leaves kDecide times the residual
/// variance more (a likelihood ratio of 25: "5 sigma"); the variance is at least
/// (kModelFloor D)^2, D the trend separation.
constexpr double kDecide = 25, kModelFloor = 0.005;
/// The swing of the separation, in trend separations, from which turns may cross, measured over
/// kSwingReach intervals on each side.
constexpr double kCrossStart = 0.85;
constexpr size_t kSwingReach = 3;

/// What lengths k consecutive one-turn intervals take near an interval (k = 1, 2, 3), in trend
/// separations: the betatron oscillation's swing, measured rather than modelled.
struct Envelope {
  double lo[4] = {0, 1e300, 1e300, 1e300}, hi[4] = {0, -1e300, -1e300, -1e300};
  int count[4] = {0, 0, 0, 0};
  double half = 0;  ///< largest distance of a measured length from k, any k

  void add(int k, double len) {
    lo[k] = std::min(lo[k], len);
    hi[k] = std::max(hi[k], len);
    ++count[k];
    half = std::max(half, std::abs(len - k));
  }
  /// Whether an interval of length q may span c turns (c = 1, 1.5, 2, ...).
  bool allows(double c, double q) const {
    const int k = static_cast<int>(std::lround(c));
    if (std::abs(c - k) < 1e-9 && k >= 1 && k <= 3 && count[k] >= 2)
      return q >= lo[k] - kLengthSlack && q <= hi[k] + kLengthSlack;
    return std::abs(q - c) <= half + kLengthSlack;
  }
  /// The separation's swing: how far one-turn intervals reach from the trend.
  double swing() const { return count[1] > 0 ? std::max(hi[1] - 1, 1 - lo[1]) : 0; }
};

Numbering number_turns(const std::vector<Gauss>& g, const PeakSettings& s) {
  const size_t n = g.size();
  Numbering out;
  out.missing.assign(n, 0);
  out.flags.assign(n, 0);
  if (n < 2) return out;

  // Too few peaks to measure the oscillation: the gap-ratio rule on the mean separation.
  if (n < kNumberingMinPeaks) {
    for (size_t j = 1; j < n; ++j) {
      const double de = mean_separation(g, j - 1), gap = g[j].mu - g[j - 1].mu, steps = turn_steps(g, j - 1);
      if (s.gap_ratio > 0 && de > 0 && gap >= s.gap_ratio * de * steps) {
        out.missing[j] = std::max(1, static_cast<int>(std::lround(gap / de - steps)));
        out.flags[j] |= kPeakGap;
      }
    }
    return out;
  }

  // The trend at interval j (peaks j-1, j): the radius gain per turn over up to 13 intervals
  // centred on it, the turns counted as numbered so far. A mean over several turns, not a
  // median: the oscillation averages out of the radius gained. The interval itself stays in:
  // leaving it out biases the trend against it (a long interval's trend comes out short) by up
  // to 2 A / 12, which made a 25.7 mm interval 1.9 trends long where it is 1.6.
  auto trend = [&](size_t j) {
    const size_t lo = j >= 7 ? j - 7 : 0, hi = std::min(n - 1, j + 6);
    double turns = 0;
    for (size_t q = lo; q < hi; ++q) turns += turn_steps(g, q) + out.missing[q + 1];
    return turns >= 2 ? (g[hi].mu - g[lo].mu) / turns : 0.0;
  };
  // The tapered least-squares misfit of the peaks around interval j (peaks j-1, j) to one
  // TurnModel, the turns numbered with `counts` missing turns; wsum: the sum of the weights.
  auto model_rss = [&](size_t j, const std::vector<int>& counts, double& wsum) {
    std::vector<double> t(n, 0);
    for (size_t i = 1; i < n; ++i) t[i] = t[i - 1] + turn_steps(g, i - 1) + counts[i];
    const size_t a = j >= kModelReach ? j - kModelReach : 0, b = std::min(n, j + kModelReach);
    TurnWindow win;
    wsum = 0;
    for (size_t i = a; i < b; ++i) {
      win.t.push_back(t[i] - t[j]);
      win.r.push_back(g[i].mu - g[j].mu);
      // Weights taper with the distance from the interval (Epanechnikov), so that what the
      // model cannot follow far away counts less than the turns beside the gap; a peak of k
      // turns sits at their mean and counts a quarter.
      const double d = (static_cast<double>(i) - (static_cast<double>(j) - 0.5)) / (kModelReach + 0.5);
      win.w.push_back((1 - d * d) * (g[i].turns > 1 ? 0.25 : 1.0));
      wsum += win.w.back();
    }
    win.h = std::max(1.0, 0.5 * (win.t.back() - win.t.front()));
    win.tc = 0.5 * (win.t.front() + win.t.back());
    win.prepare();
    return win.best().rss;
  };
  std::vector<int> alt(n, -1);
  std::vector<double> swing(n, 0);
  std::vector<char> modelled(n, 0);
  for (int pass = 0; pass < 4; ++pass) {
    bool changed = false;
    std::vector<double> len(n, 0);  // interval lengths in trend separations
    for (size_t i = 1; i < n; ++i) {
      const double de = trend(i);
      len[i] = de > 0 ? (g[i].mu - g[i - 1].mu) / de : 0;
    }
    // A one-turn interval: between two single turns, no turn missing in it.
    auto single = [&](size_t i) {
      return i >= 1 && i < n && g[i - 1].turns == 1 && g[i].turns == 1 && out.missing[i] == 0 && len[i] > 0;
    };
    for (size_t j = 1; j < n; ++j) {
      const double de = trend(j);
      if (!(de > 0)) continue;
      // The envelope of the lengths of 1, 2 and 3 consecutive one-turn intervals near j.
      Envelope env;
      const size_t lo = j > kEnvelopeReach ? j - kEnvelopeReach : 1, hi = std::min(n - 1, j + kEnvelopeReach);
      for (size_t i = lo; i <= hi; ++i) {
        double sum = 0;
        for (int k = 1; k <= 3 && i + static_cast<size_t>(k) - 1 <= hi; ++k) {
          const size_t e = i + static_cast<size_t>(k) - 1;
          if (e == j || !single(e)) break;
          sum += len[e];
          env.add(k, sum);
        }
      }
      // The swing where turns may cross is a local property: the one-turn intervals within
      // kSwingReach of j (about a period of the oscillation for nu_r - 1 above 0.15). The turns
      // of a peak the fit could not split are within about its width of each other.
      {
        Envelope near;
        for (size_t i = j > kSwingReach ? j - kSwingReach : 1; i <= std::min(n - 1, j + kSwingReach); ++i) {
          if (single(i)) near.add(1, len[i]);
          if (g[i].turns > 1) near.add(1, g[i].sigma / de);
        }
        swing[j] = near.swing();
      }
      // The counts of missing turns the interval's length allows. A gap holds missing turns only
      // when the data say so: where the envelope allows no count but none, the interval is one
      // turn; else the position model decides between none and the counts the envelope allows
      // (or, if it allows none at all, the counts around the length).
      const double steps = turn_steps(g, j - 1);
      const double longest = len[j] - steps + env.half + kLengthSlack;  // most missing turns the length allows
      const int m_max = s.gap_ratio > 0 ? std::clamp(static_cast<int>(std::ceil(longest)), 0, 60) : 0;
      std::vector<int> cand{0};
      for (int m = 1; m <= m_max; ++m)
        if (env.allows(steps + m, len[j])) cand.push_back(m);
      if (cand.size() == 1 && !env.allows(steps, len[j])) {
        const int near = std::clamp(static_cast<int>(std::lround(len[j] - steps)), 0, m_max);
        for (int m = std::max(1, near - 1); m <= std::min(m_max, near + 1); ++m) cand.push_back(m);
      }
      int used = cand.front();
      alt[j] = -1;
      modelled[j] = cand.size() > 1;
      if (cand.size() > 1) {
        // Peaks on both sides on one model of position against turn (TurnModel), once per count:
        // the counts that leave about the least residual fit; the smallest of them is used.
        std::vector<double> rss;
        double wsum = 0;
        for (int m : cand) {
          std::vector<int> counts = out.missing;
          counts[j] = m;
          rss.push_back(model_rss(j, counts, wsum));
        }
        const size_t best = static_cast<size_t>(std::min_element(rss.begin(), rss.end()) - rss.begin());
        const double floor = kModelFloor * de;
        const double var = std::max(rss[best] / std::max(1.0, wsum - 7), floor * floor);
        size_t u = best;
        for (size_t c = 0; c < best; ++c)
          if (rss[c] - rss[best] < kDecide * var) {
            u = c;
            break;
          }
        used = cand[u];
        // The doubt: the best other count within the margin.
        size_t other = cand.size();
        for (size_t c = 0; c < cand.size(); ++c)
          if (c != u && rss[c] - rss[best] < kDecide * var && (other == cand.size() || rss[c] < rss[other])) other = c;
        if (other < cand.size()) alt[j] = cand[other];
      }
      if (used != out.missing[j]) {
        out.missing[j] = used;
        changed = true;
      }
    }
    if (!changed) break;
  }
  // One interval at a time, a gap can settle an interval or two off its place (the turns beside
  // it fit almost as well either way, and moving it changes two counts at once): each gap is
  // tried at the intervals around it, the other counts held, and goes where the peaks fit best
  // by the decision margin. Where another place fits within the margin, the numbers of the
  // peaks between the two places are doubtful.
  for (size_t j = 1; j < n && s.gap_ratio > 0; ++j) {
    if (out.missing[j] == 0) continue;
    const int m = out.missing[j];
    std::vector<size_t> places;
    std::vector<double> rss;
    double wsum = 0;
    for (size_t c = j > 2 ? j - 2 : 1; c <= std::min(n - 1, j + 2); ++c) {
      if (c != j && out.missing[c] != 0) continue;
      std::vector<int> counts = out.missing;
      counts[j] = 0;
      counts[c] = m;
      places.push_back(c);
      rss.push_back(model_rss(j, counts, wsum));
    }
    const size_t best = static_cast<size_t>(std::min_element(rss.begin(), rss.end()) - rss.begin());
    const size_t here = static_cast<size_t>(std::find(places.begin(), places.end(), j) - places.begin());
    const double floor = kModelFloor * trend(j);
    const double margin = kDecide * std::max(rss[best] / std::max(1.0, wsum - 7), floor * floor);
    const size_t u = rss[here] - rss[best] >= margin ? places[best] : j;
    out.missing[j] = 0;
    out.missing[u] = m;
    for (size_t c = 0; c < places.size(); ++c)
      if (places[c] != u && rss[c] - rss[best] < margin) {
        NumberingDoubt d;
        d.kind = NumberingDoubt::kGapPlace;
        d.first = std::min(places[c], u);
        d.last = std::max(places[c], u) - 1;
        d.missing = m;
        d.alternative = static_cast<int>(places[c]);
        out.doubts.push_back(d);
        for (size_t i = d.first; i <= d.last; ++i) out.flags[i] |= kPeakAmbiguous;
      }
    j = std::max(j, u);
  }
  bool touching = false;
  for (size_t j = 1; j < n; ++j) {
    out.model_judged += modelled[j];
    if (out.missing[j] > 0) out.flags[j] |= kPeakGap;
    if (alt[j] >= 0) {
      out.flags[j] |= kPeakAmbiguous;
      NumberingDoubt d;
      d.kind = NumberingDoubt::kAmbiguousGap;
      d.first = d.last = j;
      d.missing = out.missing[j];
      d.alternative = alt[j];
      out.doubts.push_back(d);
    }
    // Turns that may cross: once the oscillation brings turns within 0.15 trend separations of
    // each other, the profile cannot tell whether they went on to cross: sorted by position,
    // crossed turns look like a weaker oscillation (on ring8's crossing profiles the swing fell
    // from 1.2 to 0.15 of the trend where turns had crossed), so the doubt lasts to the end.
    touching = touching || swing[j] >= kCrossStart;
    if (touching) {
      out.flags[j - 1] |= kPeakCross;
      out.flags[j] |= kPeakCross;
    }
  }
  // Runs of crossing peaks as one doubt each.
  for (size_t i = 0; i < n; ++i) {
    if (!(out.flags[i] & kPeakCross)) continue;
    NumberingDoubt d;
    d.kind = NumberingDoubt::kCross;
    d.first = i;
    while (i + 1 < n && (out.flags[i + 1] & kPeakCross)) ++i;
    d.last = i;
    out.doubts.push_back(d);
  }
  std::stable_sort(out.doubts.begin(), out.doubts.end(),
                   [](const NumberingDoubt& x, const NumberingDoubt& y) { return x.first < y.first; });
  return out;
}

// The systematic part of a position's uncertainty (turnfit-peakfind(1), UNCERTAINTY). Calibrated
// blind on turnfit-synth truths of ring8 (bench/peak_pulls.py, bench/RESULTS.md): the constants
// marked "calibrated" were tuned on master seeds 7001-7003 and checked on 8101, 8102 and 8111;
// those of the overlap and of merged turns were tuned again for the tailed shapes
// (shaped_turns) on 7001-7003 and 9301, and checked on 9402 and 9411.
constexpr double kShapeFloor = 0.003;  ///< an isolated turn: fraction of its width (calibrated: 0.0029 RRI2, 0.0031 RRL)
constexpr double kOverlap = 1.2;       ///< a neighbour at d: kOverlap (s_pair/d)^3 of the width (calibrated)
constexpr double kOverlapPower = 3;    ///< (calibrated by the pulls: 3 against 3.5, 4 and 5)
constexpr double kOverlapCap = 0.04;   ///< ... at most this fraction of the width per neighbour (calibrated)
constexpr double kMergedSplit = 0.07;  ///< a merged turn: the split itself, fraction of the width (calibrated)
constexpr double kEdge = 0.02;         ///< a turn at the end of the profile: fraction of its width (calibrated on 6 turns)
constexpr double kWeakShape = 0.2;     ///< a weak turn: fraction of its width (designed; few weak turns to calibrate on)
constexpr double kWeakLost = 1.6;      ///< ... and this many widths per fraction of its area missing (designed)

/// Systematic 1-sigma of peak i's position, in mm; area_ratio: its area over its neighbours'.
double systematic_error(const std::vector<Peak>& p, size_t i, double area_ratio) {
  const Peak& a = p[i];
  const double s = a.width_mm;
  // Real turns are not Gaussian (energy spread skews them): even an isolated turn's centroid sits
  // a little off the bunch mean.
  double v = std::pow(kShapeFloor * s, 2);
  // A neighbour's shape that the model misses leaks into this turn's window after the
  // deblending, and the split of turns that merge rests on the model: both grow as the neighbour
  // comes within a few widths. With Gaussian shapes the errors on ring8's synth data grew as
  // (s_pair/d)^3.9 from d = 5.3 to 2 s_pair and levelled off near 0.35 s; with tails and equal
  // areas (shaped_turns) they stay below 0.05 s for ok turns and 0.1 s for merged ones.
  for (size_t j : {i - 1, i + 1}) {
    if (j >= p.size()) continue;  // i - 1 wraps around for i = 0
    const double d = std::abs(p[j].r_fit_mm - a.r_fit_mm);
    const double sp = std::sqrt(0.5 * (s * s + p[j].width_mm * p[j].width_mm));
    const double t = d > 0 ? std::min(kOverlap * std::pow(sp / d, kOverlapPower), kOverlapCap) : kOverlapCap;
    v += std::pow(t * s, 2);
  }
  if (a.flags & kPeakMerged) v += std::pow(kMergedSplit * s, 2);
  // A weak turn lacks a fraction f of a turn's area (cut by an aperture, or a split that gave its
  // partner too much): the rest of a Gaussian cut on one side has its mean phi(z)/(1-f) widths off,
  // z = Phi^-1(f), about 1.6 f for f up to 0.5 (0.8 at 0.5); at most one width.
  if (a.flags & kPeakWeak) {
    const double f = std::clamp(1 - area_ratio, 0.0, 1.0);
    v += std::pow(kWeakShape * s, 2) + std::pow(std::min(1.0, kWeakLost * f) * s, 2);
  }
  // A turn near the end of the profile: on ring8's synth data the last RRL turn, within 1-2 widths
  // of the end, where the beam ends too (the particles beyond were extracted): the centroid of what
  // the probe saw is the mean of the particles that crossed it, 0.008-0.031 mm off (6 turns).
  // A turn cut by the end of the readings while the beam goes on is off the whole bunch's mean by
  // that of a truncated normal, phi(alpha)/Phi(alpha) widths for the end alpha widths away (0.29
  // at 1). Blind-suite truths have it (RRL's last turn, 729-1977 of 2000 particles seen), but the
  // peak is then the centre of what the probe saw, as truth.json's is, and a turn-pattern problem
  // predicts that part (centroid_turns): no term here (turnfit-peakfind(1), UNCERTAINTY).
  if (a.flags & kPeakEdge) v += std::pow(kEdge * s, 2);
  // A wide peak stands for k turns and sits at their middle, but carries the first one's number
  // (k turns h apart: the first is (k-1) h / 2 from the middle, and the peak's width^2 is at least
  // (k^2 - 1) h^2 / 12, so the offset is at most sqrt(3 (k-1) / (k+1)) widths).
  if ((a.flags & kPeakWide) && a.turns > 1) v += 3.0 * (a.turns - 1) / (a.turns + 1) * s * s;
  return std::sqrt(v);
}

}  // namespace

PeakResult find_peaks(const std::vector<double>& x, const std::vector<double>& y, const PeakSettings& s,
                      int first_turn) {
  if (x.size() != y.size()) throw data_error("find_peaks", 0, "positions and intensities differ in number");
  if (x.size() < 5) throw data_error("find_peaks", 0, "a profile needs at least 5 readings");
  for (size_t k = 1; k < x.size(); ++k)
    if (!(x[k] > x[k - 1])) throw data_error("find_peaks", 0, "positions must increase");
  PeakResult out;
  Work w{x, y, {}, 0, 0, 0, 0, 0, static_cast<long>(x.size())};
  const long n = w.n;
  w.step = (x.back() - x.front()) / static_cast<double>(n - 1);
  out.step_mm = w.step;
  w.noise = noise_estimate(y);
  double ymax = 0;
  for (double v : y) ymax = std::max(ymax, std::abs(v));
  // A noise-free profile still needs a scale for the fit's significance tests.
  w.noise = std::max(w.noise, 1e-9 * ymax + 1e-300);
  out.noise = w.noise;
  fit_baseline(x, y, w.noise, out.baseline_at0, out.baseline_slope);
  w.bg.resize(x.size());
  for (size_t k = 0; k < x.size(); ++k) w.bg[k] = out.baseline_at0 + out.baseline_slope * (x[k] - x[0]);

  // 1. The paper's detector: downward zero-crossings of the smoothed first derivative.
  const double smooth_mm = s.smooth_mm > 0 ? s.smooth_mm : std::max(0.5, w.step);
  out.smooth_mm = smooth_mm;
  const std::vector<double> ys = gaussian_smooth(y, smooth_mm / w.step);
  std::vector<double> d(x.size());
  for (long k = 0; k < n; ++k) {
    const long a = std::max(0L, k - 1), b = std::min(n - 1, k + 1);
    d[static_cast<size_t>(k)] = (ys[static_cast<size_t>(b)] - ys[static_cast<size_t>(a)]) / ((b - a) * w.step);
  }
  std::vector<long> tops;
  for (long k = 0; k + 1 < n; ++k)
    if (d[static_cast<size_t>(k)] > 0 && d[static_cast<size_t>(k + 1)] <= 0)
      tops.push_back(ys[static_cast<size_t>(k + 1)] > ys[static_cast<size_t>(k)] ? k + 1 : k);
  // A turn cut by an end of the readings (a probe's outer end, where the last turn may lie
  // across it) has no downward crossing: the smoothing, renormalized over the readings that
  // exist, leans toward the end, so the smoothed profile still rises into the last reading even
  // where the readings have turned (blind run AB's control: RRL's turn 182, 1294 of 2000
  // particles seen, peaked one reading before the end and went unfound; its area, fitted into
  // turn 181, moved that turn 0.16 mm outward at an uncertainty of 0.007 mm). The end itself
  // is then a candidate; the thresholds below and the fit decide, and the fit flags it edge.
  // (Only the outer end: turns are numbered from the first peak found, which --first-turn
  // names, so a new candidate at the inner end would renumber every turn.)
  if (d[static_cast<size_t>(n - 1)] > 0) tops.push_back(n - 1);  // (n >= 5: checked above)
  out.candidates = static_cast<int>(tops.size());
  auto above = [&](long k) { return ys[static_cast<size_t>(k)] - w.bg[static_cast<size_t>(k)]; };
  for (long k : tops) out.scale = std::max(out.scale, above(k));
  w.scale = out.scale;
  if (!(out.scale > 0)) {
    out.rejected = out.candidates;
    return out;
  }
  // Noise of the smoothed profile: white noise averaged over 2 sqrt(pi) sigma / step readings.
  const double noise_s = w.noise / std::sqrt(std::max(1.0, 2 * std::sqrt(M_PI) * smooth_mm / w.step));
  auto valley = [&](long a, long b) {  // lowest smoothed reading in [a, b]
    long v = a;
    for (long k = a; k <= b; ++k)
      if (ys[static_cast<size_t>(k)] < ys[static_cast<size_t>(v)]) v = k;
    return v;
  };
  // Thresholds, applied until nothing changes: a rejected candidate's bump joins its neighbour's
  // region, which changes that neighbour's area and slope.
  // Relative thresholds alone would find "turns" in a profile of pure noise: a top must also
  // stand 5 noise rms (of the smoothed profile) above the baseline.
  std::vector<long> acc;
  for (long k : tops)
    if (above(k) >= s.min_height * out.scale && above(k) >= 5 * noise_s) acc.push_back(k);
  for (bool changed = true; changed;) {
    changed = false;
    // Prominence: a dip between two tops smaller than 3 noise rms (plus 0.5% of the height, for
    // the shot noise on the tops) is noise on one turn, not two turns; the lower top goes.
    for (size_t i = 0; i + 1 < acc.size(); ++i) {
      const long v = valley(acc[i], acc[i + 1]);
      const double lower = std::min(ys[static_cast<size_t>(acc[i])], ys[static_cast<size_t>(acc[i + 1])]);
      if (lower - ys[static_cast<size_t>(v)] < 3 * noise_s + 0.005 * (lower - w.bg[static_cast<size_t>(v)])) {
        acc.erase(acc.begin() + static_cast<long>(ys[static_cast<size_t>(acc[i])] < ys[static_cast<size_t>(acc[i + 1])] ? i : i + 1));
        changed = true;
        break;
      }
    }
    if (changed) continue;
    for (size_t i = 0; i < acc.size(); ++i) {
      const long l = valley(i > 0 ? acc[i - 1] : 0, acc[i]);
      const long r = valley(acc[i], i + 1 < acc.size() ? acc[i + 1] : n - 1);
      double area = 0, slope = 0;
      for (long k = l; k <= r; ++k) {
        area += std::max(0.0, above(k)) * w.step;
        slope = std::max(slope, k <= acc[i] ? d[static_cast<size_t>(k)] : -d[static_cast<size_t>(k)]);
      }
      if (area < s.min_area * out.scale || slope < s.min_slope * out.scale) {
        acc.erase(acc.begin() + static_cast<long>(i));
        changed = true;
        break;
      }
    }
  }
  out.rejected = out.candidates - static_cast<int>(acc.size());

  // 2. Starting shapes: height and half width at half maximum on the smoothed profile, on the side
  // that reaches half height before the next turn (the smoothing taken out again).
  std::vector<Gauss> g;
  for (size_t i = 0; i < acc.size(); ++i) {
    const long t = acc[i];
    const double h = above(t);
    const long l = valley(i > 0 ? acc[i - 1] : 0, t), r = valley(t, i + 1 < acc.size() ? acc[i + 1] : n - 1);
    double hw = 1e300;
    for (long k = t; k > l; --k)
      if (above(k - 1) < 0.5 * h) {
        hw = std::min(hw, x[static_cast<size_t>(t)] - x[static_cast<size_t>(k)] + w.step * (above(k) - 0.5 * h) / (above(k) - above(k - 1)));
        break;
      }
    for (long k = t; k < r; ++k)
      if (above(k + 1) < 0.5 * h) {
        hw = std::min(hw, x[static_cast<size_t>(k)] - x[static_cast<size_t>(t)] + w.step * (above(k) - 0.5 * h) / (above(k) - above(k + 1)));
        break;
      }
    if (hw > 1e299) hw = 0.25 * (x[static_cast<size_t>(r)] - x[static_cast<size_t>(l)]);
    const double sg = std::sqrt(std::max(std::pow(hw / std::sqrt(2 * std::log(2.0)), 2) - smooth_mm * smooth_mm, w.step * w.step));
    Gauss gi;
    gi.a = h;
    gi.mu = x[static_cast<size_t>(t)];
    gi.sigma = sg;
    g.push_back(gi);
  }
  // Turns of one profile have similar widths: a fitted width may range from 0.3 to 3 times the
  // typical starting width, so that a turn cannot spread over its neighbours' readings.
  {
    std::vector<double> sg;
    for (const auto& gi : g) sg.push_back(gi.sigma);
    const double typical = median(sg);
    w.smin = std::max(0.25 * w.step, 0.3 * typical);
    w.smax = std::max(w.smin, 3 * typical);
    for (auto& gi : g) gi.sigma = std::clamp(gi.sigma, w.smin, w.smax);
  }

  // 3. Fit all turns; drop what the fit reduces to nothing.
  const double min_amp = 0.5 * s.min_height * out.scale;
  w.refine(g);
  while (int dropped = w.prune(g, min_amp)) {
    out.dropped += dropped;
    w.refine(g);
  }

  // 4. Turns that merge. In a CW beam every turn carries the same current, so every turn's peak
  // has the same area; a peak with about k times its neighbours' area holds k turns closer than
  // the beam is wide. Try k turns of the neighbours' width in its place; keep them if they fit
  // the same readings better by far more than the noise, keep their order, stay of similar size
  // and no farther apart than 1.5 expected separations. Otherwise the peak stays one, flagged wide.
  for (int round = 0; s.split_area > 0 && round < 3; ++round) {
    bool any = false;
    for (size_t i = 0; i < g.size(); ++i) {
      if (g[i].flags & (kPeakMerged | kPeakWide)) continue;
      std::vector<double> area(g.size()), sig(g.size());
      for (size_t j = 0; j < g.size(); ++j) {
        area[j] = g[j].a * g[j].sigma;
        sig[j] = g[j].sigma;
      }
      // One turn's area: the neighbours', unless most of them hold two turns too (then the
      // whole profile's median, where most turns are resolved, knows better).
      const double ae = std::min(neighbour_median(area, i, 6), median(area));
      if (!(ae > 0)) continue;
      // A neighbour that lacks area may have lost it to this peak: two close turns fitted as a
      // small and a large Gaussian (the large one wide enough to cover the other's flank) hold
      // two turns between them, not one plus k. What the neighbour lacks of a turn's area (from
      // under three quarters of it) does not count for this peak.
      // The neighbour's position then rests on a bad split: it is flagged weak (its uncertainty
      // grows with the area it lacks).
      double own = area[i];
      std::vector<size_t> lenders;
      for (size_t j : {i - 1, i + 1})
        if (j < g.size() && !(g[j].flags & (kPeakMerged | kPeakWide)) && area[j] < 0.75 * ae) {
          own -= ae - area[j];
          lenders.push_back(j);
        }
      if (own < s.split_area * ae) {
        if (area[i] >= s.split_area * ae)
          for (size_t j : lenders) g[j].flags |= kPeakWeak;
        continue;
      }
      const int k = std::clamp(static_cast<int>(std::lround(own / ae)), 2, 4);
      if (!s.split) {
        g[i].flags |= kPeakWide;
        g[i].turns = k;
        continue;
      }
      const double se = std::min({neighbour_median(sig, i, 6), median(sig), g[i].sigma});
      const double de = expected_separation(g, i);
      std::vector<size_t> block;
      if (i > 0 && Work::overlap(g[i - 1], g[i])) block.push_back(i - 1);
      block.push_back(i);
      if (i + 1 < g.size() && Work::overlap(g[i + 1], g[i])) block.push_back(i + 1);
      double lo = 1e300, hi = -1e300;
      for (size_t j : block) {
        lo = std::min(lo, g[j].mu - 4 * g[j].sigma);
        hi = std::max(hi, g[j].mu + 4 * g[j].sigma);
      }
      std::vector<Gauss> one = g;
      const double rss1 = w.fit_block(one, block, lo, hi);
      // k turns with the wide peak's area and second moment (k evenly spaced, h apart).
      const double h = std::sqrt(std::max(12 * (g[i].sigma * g[i].sigma - se * se) / (k * k - 1), 0.25 * se * se));
      std::vector<Gauss> many(g.begin(), g.begin() + static_cast<long>(i));
      for (int c = 0; c < k; ++c) {
        Gauss t = g[i];
        t.mu += (c - 0.5 * (k - 1)) * h;
        t.sigma = se;
        t.a = g[i].a * g[i].sigma / (k * se);
        t.flags = kPeakMerged;
        many.push_back(t);
      }
      many.insert(many.end(), g.begin() + static_cast<long>(i) + 1, g.end());
      std::vector<size_t> block2;
      if (block.front() + 1 == i) block2.push_back(i - 1);
      for (int c = 0; c < k; ++c) block2.push_back(i + static_cast<size_t>(c));
      if (block.back() == i + 1) block2.push_back(i + static_cast<size_t>(k));
      const double rss2 = w.fit_block(many, block2, lo, hi);
      bool ok = rss1 - rss2 > 25 * w.noise * w.noise;
      double amin = 1e300, amax = 0;
      for (int c = 0; c < k; ++c) {
        const Gauss& t = many[i + static_cast<size_t>(c)];
        amin = std::min(amin, t.a);
        amax = std::max(amax, t.a);
        ok = ok && t.sigma >= 0.5 * se && t.sigma <= 2 * se;
        if (c > 0) {
          const double sep = t.mu - many[i + static_cast<size_t>(c) - 1].mu;
          ok = ok && sep > 0.25 * se && (!(de > 0) || sep <= 1.5 * de);
        }
      }
      ok = ok && amin > 0 && amin >= 0.25 * amax;
      // The neighbours keep their place: the new turns must not take their readings.
      if (i > 0) ok = ok && many[i - 1].mu < many[i].mu && std::abs(many[i - 1].mu - g[i - 1].mu) < 0.5 * se;
      if (i + 1 < g.size())
        ok = ok && many[i + static_cast<size_t>(k)].mu > many[i + static_cast<size_t>(k) - 1].mu &&
             std::abs(many[i + static_cast<size_t>(k)].mu - g[i + 1].mu) < 0.5 * se;
      if (ok) {
        g = std::move(many);
        ++out.splits;
        any = true;
        i += static_cast<size_t>(k) - 1;
      } else {
        g[i].flags |= kPeakWide;
        g[i].turns = k;
      }
    }
    if (!any) break;
    w.refine(g);
  }

  // 4b. The turns' shapes for their positions: tails and equal areas (shaped_turns). The
  // Gaussians g keep numbering the turns.
  const std::vector<Gauss> e = shaped_turns(w, g);

  // 5. Flags and turn numbers.
  std::vector<double> area(g.size());
  for (size_t i = 0; i < g.size(); ++i) area[i] = g[i].a * g[i].sigma / g[i].turns;
  const double median_area = median(area);
  const Numbering numbering = number_turns(g, s);
  out.model_judged = numbering.model_judged;
  out.doubts = numbering.doubts;
  // The noise for the positions' statistical errors: the detector's estimate (second differences
  // of the readings) also counts the turns' own curvature where turns cover most of the profile
  // (RRL's outer turns: 7x the noise between turns); the same estimate on the fit's residuals
  // does not.
  {
    std::vector<double> res(x.size());
    for (size_t k = 0; k < x.size(); ++k) res[k] = y[k] - w.bg[k];
    for (const auto& gi : g)
      for (long k = w.index_at(gi.mu - 8 * gi.sigma); k <= w.index_at(gi.mu + 8 * gi.sigma); ++k)
        res[static_cast<size_t>(k)] -= gauss_at(gi, x[static_cast<size_t>(k)]);
    out.residual_noise = g.empty() ? w.noise : std::max(noise_estimate(res), 1e-9 * ymax + 1e-300);
  }
  int turn = first_turn;
  std::vector<double> area_ratio(g.size(), 1.0);  // a turn's area over its neighbours' (for the uncertainty)
  for (size_t i = 0; i < g.size(); ++i) {
    Gauss& gi = g[i];
    const double na = std::min(neighbour_median(area, i, 6), median_area);
    if (na > 0) area_ratio[i] = area[i] / na;
    if (gi.a < 2 * s.min_height * out.scale || (na > 0 && area[i] < 0.5 * na)) gi.flags |= kPeakWeak;
    if (gi.mu - 3 * gi.sigma < x.front() || gi.mu + 3 * gi.sigma > x.back()) gi.flags |= kPeakEdge;
    gi.flags |= numbering.flags[i];
    // A peak of k unresolved turns stands for k turn numbers; a gap skips the missing turns'.
    if (i > 0) turn += g[i - 1].turns + numbering.missing[i];
    out.skipped_turns += numbering.missing[i];
    Peak pk;
    pk.turn = turn;
    pk.r_mm = gi.mu;
    pk.r_fit_mm = gi.mu;
    pk.r_err_stat_mm = std::sqrt(gi.mu_var) * out.residual_noise / w.noise;  // mu_var is in units of w.noise^2
    pk.turns = gi.turns;
    pk.height = gi.a;
    pk.width_mm = gi.sigma;
    pk.area = gi.a * gi.sigma * std::sqrt(2 * M_PI);
    pk.flags = gi.flags;
    if (s.centroid) {
      // Deblended centroid: the readings minus the baseline and every other turn's fitted shape
      // (with its tail), weighted over the shape's mean +- 3 rms (sigma sqrt(1 + t^2)) with
      // fractional end readings, so the window slides smoothly across the reading grid.
      const Gauss& ei = e[i];
      const double m = shape_mean(ei), sd = ei.sigma * std::sqrt(1 + ei.t * ei.t);
      const double lo = m - 3 * sd, hi = m + 3 * sd;
      double sw = 0, sx = 0;
      for (long k = w.index_at(lo); k <= w.index_at(hi); ++k) {
        const double xk = x[static_cast<size_t>(k)];
        const double frac = std::clamp(std::min(xk + 0.5 * w.step, hi) - std::max(xk - 0.5 * w.step, lo), 0.0, w.step) / w.step;
        double v = y[static_cast<size_t>(k)] - w.bg[static_cast<size_t>(k)];
        for (size_t j = 0; j < e.size(); ++j)
          if (j != i && Work::within(e[j], xk)) v -= shape_at(e[j], xk);
        sw += frac * v;
        sx += frac * v * xk;
      }
      if (sw > 0) {
        pk.r_mm = sx / sw;
        // The centroid's noise: sum frac^2 (x - c)^2 noise^2 / sw^2 (white noise on each reading).
        double sq = 0;
        for (long k = w.index_at(lo); k <= w.index_at(hi); ++k) {
          const double xk = x[static_cast<size_t>(k)];
          const double frac = std::clamp(std::min(xk + 0.5 * w.step, hi) - std::max(xk - 0.5 * w.step, lo), 0.0, w.step) / w.step;
          sq += frac * frac * (xk - pk.r_mm) * (xk - pk.r_mm);
        }
        pk.r_err_stat_mm = std::sqrt(sq) * out.residual_noise / sw;
      }
    }
    out.peaks.push_back(pk);
  }
  for (size_t i = 0; i < out.peaks.size(); ++i) {
    Peak& pk = out.peaks[i];
    pk.r_err_sys_mm = systematic_error(out.peaks, i, area_ratio[i]);
    pk.r_err_mm = std::hypot(pk.r_err_stat_mm, pk.r_err_sys_mm);
  }
  return out;
}

}  // namespace turnfit
