// Trim coil field models (physics.md "Trim coil models"; paper Sec. II.C and IV.C).
#include "turnfit/trimcoil/trimcoil.hpp"

#include <algorithm>
#include <cmath>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/physics/hermite.hpp"

namespace turnfit {
namespace {

void poly(const std::vector<double>& c, double x, double& p, double& dp, double& d2p) {
  p = dp = d2p = 0;
  for (size_t i = c.size(); i-- > 0;) {  // Horner with derivatives
    d2p = d2p * x + 2 * dp;
    dp = dp * x + p;
    p = p * x + c[i];
  }
}
/// Coefficients of p(c + y) in y, accumulated in long double.
std::vector<double> shifted(const std::vector<double>& a, double c) {
  const std::vector<long double> b = taylor_shift(std::vector<long double>(a.begin(), a.end()), c);
  return std::vector<double>(b.begin(), b.end());
}
}  // namespace

std::vector<long double> taylor_shift(std::vector<long double> b, long double c) {
  const size_t n = b.size();
  // Repeated synthetic division by (x - c): after pass k, b[k] is the k-th Taylor coefficient.
  for (size_t k = 0; k < n; ++k)
    for (size_t i = n - 1; i > k; --i) b[i - 1] += c * b[i];
  return b;
}

void rational(const std::vector<double>& num, const std::vector<double>& den, double x, double& q,
              double& dq, double& d2q) {
  double f, df, d2f;
  poly(num, x, f, df, d2f);
  if (den.empty()) {
    q = f;
    dq = df;
    d2q = d2f;
    return;
  }
  double g, dg, d2g;
  poly(den, x, g, dg, d2g);
  q = f / g;
  dq = (df - q * dg) / g;
  d2q = (d2f - 2 * dq * dg - q * d2g) / g;
}

CoilTable read_coil_table(const std::string& path) {
  CsvTable t = CsvTable::read(path);
  t.require_columns({"r_mm", "b_shape"});
  const size_t cr = t.column("r_mm"), cs = t.column("b_shape");
  CoilTable out;
  for (size_t i = 0; i < t.rows(); ++i) {
    out.r_mm.push_back(t.number(i, cr));
    out.shape.push_back(t.number(i, cs));
    if (i > 0 && !(out.r_mm[i] > out.r_mm[i - 1])) throw data_error(t.name(), t.line(i), "r_mm must increase strictly");
  }
  if (out.r_mm.size() < 2) throw data_error(t.name(), 0, "a trim coil table needs at least 2 rows");
  return out;
}

TrimCoilField::TrimCoilField(const TrimCoil& coil, int symmetry) : coil_(coil), symmetry_(symmetry) {
  const std::string where = "trim coil '" + coil.name + "'";
  if (coil.type == "psi-bfield") kind_ = 0;
  else if (coil.type == "psi-phase") kind_ = 1;
  else if (coil.type == "psi-bfield-mirrored") kind_ = 2;
  else if (coil.type == "table") kind_ = 3;
  else throw Error(ExitCode::data, where + ": unknown type '" + coil.type + "'");
  if (!(coil.rmax_mm > coil.rmin_mm)) throw Error(ExitCode::data, where + ": rmax_mm must exceed rmin_mm");
  if ((kind_ == 0 || kind_ == 1) && coil.coefnum.empty())
    throw Error(ExitCode::data, where + ": coefnum is empty");
  if (kind_ == 2 && !(coil.slope_per_mm > 0)) throw Error(ExitCode::data, where + ": slope_per_mm must be positive");
  if (kind_ == 3 && coil.table.empty() && !coil.table_r_mm.empty()) {  // in memory
    if (coil.table_r_mm.size() != coil.table_shape.size() || coil.table_r_mm.size() < 2)
      throw Error(ExitCode::software, where + ": in-memory table sizes differ or hold fewer than 2 rows");
    for (size_t i = 0; i < coil.table_r_mm.size(); ++i) {
      tr_.push_back(coil.table_r_mm[i] * 1e-3);
      ts_.push_back(coil.table_shape[i]);
      if (i > 0 && !(tr_[i] > tr_[i - 1])) throw Error(ExitCode::software, where + ": table radii must increase");
    }
  } else if (kind_ == 3) {
    const CoilTable t = read_coil_table(coil.table);
    for (double r : t.r_mm) tr_.push_back(r * 1e-3);
    ts_ = t.shape;
  }
  if (kind_ == 3) {
    // Monotone-preserving (Fritsch-Carlson) slopes: no overshoot between measured points.
    const size_t n = tr_.size();
    std::vector<double> d(n - 1);
    for (size_t i = 0; i + 1 < n; ++i) d[i] = (ts_[i + 1] - ts_[i]) / (tr_[i + 1] - tr_[i]);
    tm_.assign(n, 0);
    tm_[0] = d[0];
    tm_[n - 1] = d[n - 2];
    for (size_t i = 1; i + 1 < n; ++i) tm_[i] = d[i - 1] * d[i] <= 0 ? 0 : 2 / (1 / d[i - 1] + 1 / d[i]);
    if (coil.table.empty() && coil.table_slope.size() == n)  // exact slopes given (e.g. a B-spline)
      for (size_t i = 0; i < n; ++i) tm_[i] = coil.table_slope[i] * 1e3;
  }
  if (kind_ == 0 || kind_ == 1) {
    centre_m_ = 0.5 * (coil.rmin_mm + coil.rmax_mm) * 1e-3;
    num_c_ = shifted(coil.coefnum, centre_m_ - coil.coef_origin_mm * 1e-3);
    den_c_ = shifted(coil.coefdenom, centre_m_ - coil.coef_origin_mm * 1e-3);
  }
  everywhere_ = coil.sectors.empty() && coil.phimin_deg == 0 && coil.phimax_deg >= 360;
  for (int s : coil.sectors)
    if (s < 1 || s > symmetry)
      throw Error(ExitCode::data, where + ": sector " + std::to_string(s) + " outside 1.." + std::to_string(symmetry));
  // The window in_azimuth tests: PHIMIN/PHIMAX (wrapped to [0, 2 pi)) when it is less than a
  // full circle, and a flag per sector when there is a sector list.
  const auto wrap = [](double a) { return a - 2 * kPi * std::floor(a / (2 * kPi)); };
  window_ = !(coil.phimin_deg == 0 && coil.phimax_deg >= 360) && coil.phimax_deg - coil.phimin_deg < 360;
  phi_a_ = wrap(coil.phimin_deg * kPi / 180);
  phi_b_ = wrap(coil.phimax_deg * kPi / 180);
  in_sector_.clear();
  if (!coil.sectors.empty()) {
    in_sector_.assign(static_cast<size_t>(symmetry), 0);
    for (int s : coil.sectors) in_sector_[static_cast<size_t>(s - 1)] = 1;
  }
}

void TrimCoilField::shape(double r_m, double& s, double& ds) const {
  for (const auto& g : lut_) {
    const double x = (r_m - g.r0) * g.inv_h;
    if (!(x >= 0 && x <= static_cast<double>(g.s.size() - 1))) continue;
    const size_t i = std::min(static_cast<size_t>(x), g.s.size() - 2);
    s = hermite_inv(g.s[i], g.s[i + 1], g.ds[i], g.ds[i + 1], g.h, g.inv_h, x - static_cast<double>(i), ds);
    return;
  }
  shape_exact(r_m, s, ds);
}

size_t TrimCoilField::tabulate(double r_lo, double r_hi, double rel_tol) {
  lut_.clear();
  if (kind_ == 3 || !(r_hi > r_lo)) return 0;
  // Pieces where the shape is smooth: the coil's support, split where the formula changes.
  const double rmin = coil_.rmin_mm * 1e-3, rmax = coil_.rmax_mm * 1e-3;
  std::vector<double> cuts;
  if (kind_ == 2) {
    cuts = {r_lo, 0.5 * (rmin + rmax), r_hi};  // mirrored: kink at the middle, no edges
  } else {
    cuts = {std::max(r_lo, rmin), std::min(r_hi, rmax)};
  }
  std::vector<Segment> segs;
  size_t nodes = 0;
  for (size_t k = 0; k + 1 < cuts.size(); ++k) {
    const double a = std::max(r_lo, cuts[k]), b = std::min(r_hi, cuts[k + 1]);
    if (!(b > a)) continue;
    // Inside the piece (the end nodes take the one-sided values of this piece).
    const double eps = 1e-12 * (b - a);
    auto exact = [&](double r, double& v, double& d) { shape_exact(std::min(std::max(r, a + eps), b - eps), v, d); };
    Segment g{};
    for (size_t n = 65; n <= (1u << 21); n = 2 * n - 1) {
      g.r0 = a;
      g.h = (b - a) / static_cast<double>(n - 1);
      g.inv_h = 1 / g.h;
      g.s.resize(n);
      g.ds.resize(n);
      double smax = 0, dmax = 0;
      for (size_t i = 0; i < n; ++i) {
        exact(a + static_cast<double>(i) * g.h, g.s[i], g.ds[i]);
        smax = std::max(smax, std::fabs(g.s[i]));
        dmax = std::max(dmax, std::fabs(g.ds[i]));
      }
      double es = 0, ed = 0;
      // The Hermite value error peaks mid-interval, the slope error at t = 1/2 - 1/(2 sqrt 3)
      // and its mirror (the error terms go as t^2 (1-t)^2 and its derivative).
      for (size_t i = 0; i + 1 < n; ++i) {
        for (double t : {0.5, 0.21132486540518713, 0.78867513459481287}) {
          double v, d, dv;
          exact(a + (static_cast<double>(i) + t) * g.h, v, d);
          const double hv = hermite(g.s[i], g.s[i + 1], g.ds[i], g.ds[i + 1], g.h, t, dv);
          es = std::max(es, std::fabs(hv - v));
          ed = std::max(ed, std::fabs(dv - d));
        }
      }
      if (es <= rel_tol * smax && ed <= rel_tol * std::max(dmax, 1e-300) * 10) {
        nodes += n;
        segs.push_back(std::move(g));
        break;
      }
      if (n > (1u << 20)) return 0;  // too rough to tabulate: keep the formula everywhere
    }
  }
  lut_ = std::move(segs);
  return nodes;
}

void TrimCoilField::shape_exact(double r_m, double& s, double& ds) const {
  s = ds = 0;
  const double rmin = coil_.rmin_mm * 1e-3, rmax = coil_.rmax_mm * 1e-3;
  if (kind_ == 2) {
    // OPAL's PSI-BFIELD-MIRRORED (TC15): x measured from the nearer end, in units of 1/slope,
    // 2.78 normalizes the peak; applied at every radius (physics.md).
    const double r_mm = r_m * 1e3, mid = 0.5 * (coil_.rmin_mm + coil_.rmax_mm);
    const double sl = coil_.slope_per_mm;
    const double x = r_mm < mid ? (r_mm - coil_.rmin_mm) * sl : (coil_.rmax_mm - r_mm) * sl;
    const double dx_dr = (r_mm < mid ? sl : -sl) * 1e3;  // per metre
    // 10^a as exp(a ln 10): the same function, without pow's general-exponent path (the
    // tracker evaluates this four times per step).
    constexpr double ln10 = 2.30258509299404568402;
    const double p1 = std::exp(0.03 * ln10 * (x - 4)), p2 = std::exp(-0.2 * ln10 * (x - 8));
    const double i1 = 1 / (1 + p1), i2 = 1 / (1 + p2);
    s = (-3 + 3 * i1 + 5 * i2) / 2.78;
    const double dp1 = p1 * ln10 * 0.03, dp2 = p2 * ln10 * -0.2;
    ds = (-3 * dp1 * i1 * i1 - 5 * dp2 * i2 * i2) / 2.78 * dx_dr;
    return;
  }
  if (r_m < rmin || r_m > rmax) return;
  if (kind_ == 3) {
    if (r_m < tr_.front() || r_m > tr_.back()) return;
    size_t i = static_cast<size_t>(std::upper_bound(tr_.begin(), tr_.end(), r_m) - tr_.begin());
    i = std::min(std::max<size_t>(i, 1), tr_.size() - 1) - 1;
    const double h = tr_[i + 1] - tr_[i];
    s = hermite(ts_[i], ts_[i + 1], tm_[i], tm_[i + 1], h, (r_m - tr_[i]) / h, ds);
    return;
  }
  double q, dq, d2q;
  rational(num_c_, den_c_, r_m - centre_m_, q, dq, d2q);
  if (kind_ == 0) {
    s = q;
    ds = dq;
  } else {  // psi-phase: the field follows -d(phase)/dr (paper Eq. 5)
    s = -dq;
    ds = -d2q;
  }
}

bool same_shape(const TrimCoil& a, const TrimCoil& b) {
  return a.name == b.name && a.type == b.type && a.rmin_mm == b.rmin_mm && a.rmax_mm == b.rmax_mm &&
         a.coefnum == b.coefnum && a.coefdenom == b.coefdenom && a.slope_per_mm == b.slope_per_mm &&
         a.table == b.table && a.sectors == b.sectors && a.phimin_deg == b.phimin_deg && a.phimax_deg == b.phimax_deg &&
         a.coef_origin_mm == b.coef_origin_mm && a.table_r_mm == b.table_r_mm && a.table_shape == b.table_shape &&
         a.table_slope == b.table_slope;
}

TrimCoil bfield_from_phase(const TrimCoil& phase) {
  if (phase.type != "psi-phase")
    throw Error(ExitCode::usage, "trim coil '" + phase.name + "': bfield_from_phase needs a psi-phase coil");
  // OPAL's PSI-PHASE field is -bmax (f/g)' = bmax (f g' - f' g) / g^2 (quotient rule), a rational
  // again (paper Sec. IV.C); products in long double, in the coil's own origin (no re-expansion).
  auto der = [](const std::vector<long double>& p) {
    std::vector<long double> d(p.size() > 1 ? p.size() - 1 : 1, 0.0L);
    for (size_t k = 1; k < p.size(); ++k) d[k - 1] = static_cast<long double>(k) * p[k];
    return d;
  };
  auto mul = [](const std::vector<long double>& p, const std::vector<long double>& q) {
    std::vector<long double> r(p.size() + q.size() - 1, 0.0L);
    for (size_t i = 0; i < p.size(); ++i)
      for (size_t j = 0; j < q.size(); ++j) r[i + j] += p[i] * q[j];
    return r;
  };
  const std::vector<long double> f(phase.coefnum.begin(), phase.coefnum.end());
  std::vector<long double> g(phase.coefdenom.begin(), phase.coefdenom.end());
  if (g.empty()) g = {1.0L};
  std::vector<long double> num = mul(f, der(g)), minus = mul(der(f), g);
  if (minus.size() > num.size()) num.resize(minus.size(), 0.0L);
  for (size_t k = 0; k < minus.size(); ++k) num[k] -= minus[k];
  const std::vector<long double> den = mul(g, g);
  TrimCoil b = phase;
  b.type = "psi-bfield";
  b.coefnum.assign(num.begin(), num.end());
  b.coefdenom.assign(den.begin(), den.end());
  return b;
}

void TrimCoilField::add(double r_m, double th, double main_b, double main_db_dr, double main_db_dth,
                        double threshold_T, double& b, double& db_dr, double& db_dth,
                        double sector_offset) const {
  if (coil_.bmax_T == 0) return;
  // The radial shape first: outside its support (most coils at any radius) it is a table
  // lookup that ends the work, cheaper than the azimuth and sector test.
  double s, ds;
  shape(r_m, s, ds);
  if ((s == 0 && ds == 0) || !in_azimuth(th, sector_offset)) return;
  add_faded(coil_.bmax_T * s, coil_.bmax_T * ds, main_b, main_db_dr, main_db_dth, threshold_T, b, db_dr, db_dth);
}

TrimCoilSum::TrimCoilSum(const std::vector<TrimCoilField>& coils, double r_lo, double r_hi, std::vector<char>& taken) {
  taken.assign(coils.size(), 0);
  std::vector<size_t> use;
  for (size_t i = 0; i < coils.size(); ++i) {
    const TrimCoilField& c = coils[i];
    if (c.everywhere_ && c.coil_.bmax_T != 0 && c.kind_ != 3 && !c.lut_.empty()) use.push_back(i);
  }
  if (use.size() < 2) return;
  build(coils, use, r_lo, r_hi);
  if (empty()) return;
  for (size_t i : use) taken[i] = 1;
}

TrimCoilSum::TrimCoilSum(const std::vector<TrimCoilField>& coils, const std::vector<size_t>& use, double r_lo,
                         double r_hi) {
  for (size_t i : use)
    if (coils[i].kind_ == 3 || coils[i].lut_.empty()) return;  // only tabulated rational shapes
  build(coils, use, r_lo, r_hi);
}

void TrimCoilSum::build(const std::vector<TrimCoilField>& coils, const std::vector<size_t>& use, double r_lo,
                        double r_hi) {
  if (use.empty() || !(r_hi > r_lo)) return;
  // Breaks: every table segment's ends (support edges, mirrored kinks), within [r_lo, r_hi].
  std::vector<double> cuts = {r_lo, r_hi};
  for (size_t i : use)
    for (const auto& g : coils[i].lut_) {
      const double e = g.r0 + static_cast<double>(g.s.size() - 1) * g.h;
      for (double r : {g.r0, e})
        if (r > r_lo && r < r_hi) cuts.push_back(r);
    }
  std::sort(cuts.begin(), cuts.end());
  cuts.erase(std::unique(cuts.begin(), cuts.end(), [](double a, double b) { return b - a <= 1e-12; }), cuts.end());
  for (size_t k = 0; k + 1 < cuts.size(); ++k) {
    const double a = cuts[k], b = cuts[k + 1];
    // The coils whose tables reach into this piece (the others are 0 here: outside their
    // support), and the finest spacing their tables use on it.
    double h = b - a;
    std::vector<size_t> here;
    for (size_t i : use)
      for (const auto& g : coils[i].lut_) {
        const double e = g.r0 + static_cast<double>(g.s.size() - 1) * g.h;
        if (g.r0 < b && e > a) {
          h = std::min(h, g.h);
          if (here.empty() || here.back() != i) here.push_back(i);
        }
      }
    if (here.empty()) continue;
    Piece p;
    const size_t n = static_cast<size_t>(std::ceil((b - a) / h - 1e-9)) + 1;
    p.r0 = a;
    p.r1 = b;
    p.h = (b - a) / static_cast<double>(std::max<size_t>(n - 1, 1));
    p.inv_h = 1 / p.h;
    std::vector<double> sv(std::max<size_t>(n, 2), 0.0), dv(sv.size(), 0.0);
    // One-sided values of this piece at its ends (a coil's edge may be one of them).
    const double eps = 1e-12 * (b - a);
    for (size_t j = 0; j < sv.size(); ++j) {
      const double r = std::min(std::max(a + static_cast<double>(j) * p.h, a + eps), b - eps);
      for (size_t i : here) {
        double v, d;
        coils[i].shape_exact(r, v, d);
        sv[j] += coils[i].coil_.bmax_T * v;
        dv[j] += coils[i].coil_.bmax_T * d;
      }
    }
    // The Hermite cubic through the nodes' values and slopes, interval by interval.
    p.poly.resize(4 * (sv.size() - 1));
    for (size_t j = 0; j + 1 < sv.size(); ++j) {
      const double y0 = sv[j], y1 = sv[j + 1], m0 = p.h * dv[j], m1 = p.h * dv[j + 1];
      p.poly[4 * j] = y0;
      p.poly[4 * j + 1] = m0;
      p.poly[4 * j + 2] = 3 * (y1 - y0) - 2 * m0 - m1;
      p.poly[4 * j + 3] = 2 * (y0 - y1) + m0 + m1;
    }
    pieces_.push_back(std::move(p));
  }
  if (pieces_.empty()) return;
  ncoils_ = use.size();
  // Buckets of the finest piece's width (at most 4096) point at the first piece a radius can be in.
  lo_ = pieces_.front().r0;
  const double span = pieces_.back().r1 - lo_;
  const size_t nb = std::min<size_t>(4096, static_cast<size_t>(pieces_.size()) * 8 + 1);
  inv_bucket_ = static_cast<double>(nb) / span;
  bucket_.assign(nb + 1, 0);
  size_t q = 0;
  for (size_t b = 0; b <= nb; ++b) {
    const double r = lo_ + static_cast<double>(b) / inv_bucket_;
    while (q + 1 < pieces_.size() && pieces_[q].r1 <= r) ++q;
    bucket_[b] = static_cast<unsigned>(q);
  }
}

size_t TrimCoilSum::nodes() const {
  size_t n = 0;
  for (const auto& p : pieces_) n += p.intervals() + 1;
  return n;
}

void TrimCoilSum::value(double r, double& b, double& db) const {
  Hint unused;
  lookup(r, unused, b, db);
}

void TrimCoilSum::lookup(double r, Hint& hint, double& b, double& db) const {
  b = db = 0;
  hint.piece = ~0u;
  if (pieces_.empty()) return;
  const double x = (r - lo_) * inv_bucket_;
  if (!(x >= 0 && x < static_cast<double>(bucket_.size()))) return;
  size_t q = bucket_[static_cast<size_t>(x)];
  while (q < pieces_.size() && pieces_[q].r1 < r) ++q;
  if (q == pieces_.size() || r < pieces_[q].r0) return;  // past the end, or a gap no coil covers
  hint.piece = static_cast<unsigned>(q);
  node_value(pieces_[q], r, b, db);
}

void TrimCoilSum::add(double r_m, double main_b, double main_db_dr, double main_db_dth, double threshold_T, double& b,
                      double& db_dr, double& db_dth) const {
  Hint none;  // no place known: value()'s search
  add_near(r_m, none, main_b, main_db_dr, main_db_dth, threshold_T, b, db_dr, db_dth);
}

}  // namespace turnfit
