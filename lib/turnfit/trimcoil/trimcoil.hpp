// Trim coil fields: the rational PSI models, OPAL's mirrored TC15 shape, and tables,
// restricted by radius, azimuth window, sector list and the main-field threshold.
#pragma once

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {

/// Adds a coil field c(r) (dc/dr) to b and its derivatives. Below the threshold the coil
/// fades linearly with the main field (OPAL's smooth transition).
inline void add_faded(double c, double dc_dr, double main_b, double main_db_dr, double main_db_dth, double threshold_T,
               double& b, double& db_dr, double& db_dth) {
  double w = 1, dw_dr = 0, dw_dth = 0;
  const double amain = std::fabs(main_b);
  if (threshold_T > 0 && amain < threshold_T) {
    w = amain / threshold_T;
    const double sg = main_b >= 0 ? 1.0 : -1.0;
    dw_dr = sg * main_db_dr / threshold_T;
    dw_dth = sg * main_db_dth / threshold_T;
  }
  b += c * w;
  db_dr += dc_dr * w + c * dw_dr;
  db_dth += c * dw_dth;
}

/// A trim coil's table (type table): radii [mm], strictly increasing, and shape values.
struct CoilTable {
  std::vector<double> r_mm;
  std::vector<double> shape;
};

/// Reads a trim coil table file (CSV r_mm,b_shape; EX_NOINPUT / EX_DATAERR naming the file and
/// line: radii not strictly increasing, fewer than 2 rows).
CoilTable read_coil_table(const std::string& path);

/// A trim coil's contribution to the bending field b (turnfit's convention: b > 0 bends the
/// particle; a positive bmax_T strengthens the field for every type).
///
/// Relation to OPAL (physics.md): OPAL adds PSI-BFIELD and PSI-PHASE fields to the sign-flipped
/// Bz, so OPAL's BMAX = -bmax_T for those two types, and BMAX = +bmax_T for PSI-BFIELD-MIRRORED.
class TrimCoilField {
 public:
  /// Builds the coil (reads its table for type "table"); `symmetry` places the sectors.
  /// EX_DATAERR / EX_NOINPUT for an unusable description or table file.
  TrimCoilField(const TrimCoil& coil, int symmetry);

  /// Adds the coil to b and its derivatives at (r, theta), given the main field there
  /// (for the threshold fall-off). Units: m, rad, T.
  /// `sector_offset_rad`: azimuth of sector 1's centre line at this radius (a spiral turns it),
  /// so a sector list follows the magnets; the PHIMIN/PHIMAX window stays in machine azimuth.
  void add(double r_m, double theta_rad, double main_b_T, double main_db_dr, double main_db_dth,
           double threshold_T, double& b, double& db_dr, double& db_dth, double sector_offset_rad = 0) const;

  /// The radial shape s(r) and ds/dr [1/m] (b = bmax * s before windows); 0 outside.
  /// From the lookup table when one was built, else from the formula.
  void shape(double r_m, double& s, double& ds_dr) const;

  /// The shape from its formula (what tabulate() approximates).
  void shape_exact(double r_m, double& s, double& ds_dr) const;

  /// Replaces the formula on [r_lo, r_hi] by a cubic Hermite table through exact values and
  /// slopes, split at the shape's kinks and edges, refined until every interval midpoint is
  /// within `rel_tol` of the shape's peak (and the slope within 10 rel_tol of the peak slope:
  /// Hermite slopes are one order less accurate). A tracker evaluates
  /// the coil several times per step; the mirrored shape costs two exponentials. Returns the
  /// number of nodes (0: not tabulated, e.g. tables, which are already tables).
  size_t tabulate(double r_lo_m, double r_hi_m, double rel_tol = 1e-7);

  /// Whether the coil's window (PHIMIN/PHIMAX, sector list) holds azimuth theta, sector 1's
  /// centre line being at `sector_offset_rad` at this radius.
  bool in_azimuth(double theta_rad, double sector_offset_rad) const;
  /// Whether two coils have the same window (sums of such coils need one test).
  bool same_window(const TrimCoilField& o) const {
    return coil_.phimin_deg == o.coil_.phimin_deg && coil_.phimax_deg == o.coil_.phimax_deg &&
           coil_.sectors == o.coil_.sectors && symmetry_ == o.symmetry_;
  }

  /// The coil's name.
  const std::string& name() const { return coil_.name; }
  /// Whether it acts at every azimuth (no sector list, a full-circle window).
  bool everywhere() const { return everywhere_; }
  /// Sets the coil's strength; the shape and its table stay (they do not depend on it).
  void set_bmax(double bmax_T) { coil_.bmax_T = bmax_T; }
  /// The description it was built from.
  const TrimCoil& coil() const { return coil_; }

 private:
  friend class TrimCoilSum;
  TrimCoil coil_;
  int symmetry_;
  int kind_;  // 0 bfield, 1 phase, 2 mirrored, 3 table
  bool everywhere_ = false;  // full circle, all sectors: skip the azimuth test
  bool window_ = false;          // a PHIMIN/PHIMAX window of less than a full circle
  double phi_a_ = 0, phi_b_ = 0;  // its ends, wrapped to [0, 2 pi) [rad]
  std::vector<char> in_sector_;   // per sector (index k - 1): in the sector list; empty: no list
  std::vector<double> tr_, ts_, tm_;  // table radii [m], shape values, Hermite slopes
  // Rational coefficients re-expanded about the support's centre r_c: f(r) = sum c_k (r - r_c)^k.
  // Coefficients in r itself cancel heavily at r ~ 4 m (terms of (r/w)^5 ~ 1e9 for a value of 1),
  // which makes their evaluation noisy at 1e-7 of the peak and its slope jagged; the shift is
  // done once in extended precision, so the function evaluated is smooth.
  double centre_m_ = 0;
  std::vector<double> num_c_, den_c_;
  struct Segment {  // equally spaced lookup nodes on [r0, r0 + (n - 1) h]
    double r0, h, inv_h;
    std::vector<double> s, ds;
  };
  std::vector<Segment> lut_;  // sorted, disjoint; outside them the formula applies
};

/// The coils that act at every azimuth, summed into one radial table: b += w sum_i bmax_i s_i(r)
/// (w the threshold fall-off, the same for every coil). One lookup then replaces up to one per
/// coil and field sample; with 18 coils the coils took 57 % of a ring8 track.
///
/// The table is cubic Hermite through the exact sum's values and slopes, piecewise between
/// every coil's support edges (and mirrored kinks), on each piece equally spaced at the
/// finest spacing that any coil present there needed for its own table (tabulate()). The nodes
/// therefore do not depend on the coil strengths, and the table is linear in every bmax: an
/// optimizer's finite differences in bmax see a smooth function. The error is at most each
/// coil's own table error (1e-7 of its peak), summed.
class TrimCoilSum {
 public:
  /// Sums every coil of `coils` that acts at every azimuth, has a nonzero bmax and a lookup
  /// table (tabulate(); tables of type "table" and untabulated coils stay single), over
  /// [r_lo, r_hi] [m]. taken[i] is set for each coil summed. Empty when fewer than two qualify.
  TrimCoilSum(const std::vector<TrimCoilField>& coils, double r_lo_m, double r_hi_m, std::vector<char>& taken);
  /// Sums the coils `use` (indices into `coils`) whatever their windows, which the caller tests
  /// (they must share one); empty unless every one has a lookup table and a rational shape.
  TrimCoilSum(const std::vector<TrimCoilField>& coils, const std::vector<size_t>& use, double r_lo_m, double r_hi_m);
  TrimCoilSum() = default;

  bool empty() const { return pieces_.empty(); }
  /// Number of coils summed, and of table nodes.
  size_t coils() const { return ncoils_; }
  size_t nodes() const;

  /// The summed shape sum_i bmax_i s_i(r) [T] and its r derivative [T/m]; 0 outside.
  void value(double r_m, double& b, double& db_dr) const;

  /// Adds the summed coils to b and its derivatives at radius r, given the main field there
  /// (threshold fall-off as TrimCoilField::add).
  void add(double r_m, double main_b_T, double main_db_dr, double main_db_dth, double threshold_T, double& b,
           double& db_dr, double& db_dth) const;

  /// The piece the last lookup of a caller that samples nearby radii landed in: the fast
  /// steppers keep one per particle and table. (Pieces are long, nodes short: a particle's
  /// radius changes node at nearly every sample, piece about once a turn.)
  struct Hint {
    unsigned piece = ~0u;
  };
  /// value() in the hint's piece when r is still in it (no search on the way from the radius
  /// to the rows), else by value()'s search, which sets the hint. The same numbers as value()
  /// (the same piece, node and offset).
  void value_near(double r_m, Hint& hint, double& b, double& db_dr) const {
    if (hint.piece < pieces_.size()) {
      const Piece& p = pieces_[hint.piece];
      // value() takes the first piece whose end is not below r.
      if (r_m >= p.r0 && r_m <= p.r1 && (hint.piece == 0 || pieces_[hint.piece - 1].r1 < r_m)) {
        node_value(p, r_m, b, db_dr);
        return;
      }
    }
    lookup(r_m, hint, b, db_dr);
  }
  /// add() through value_near().
  void add_near(double r_m, Hint& hint, double main_b_T, double main_db_dr, double main_db_dth, double threshold_T,
                double& b, double& db_dr, double& db_dth) const;

 private:
  struct Piece {  // equally spaced nodes on [r0, r0 + (n - 1) h]
    double r0, r1, h, inv_h;
    /// The Hermite cubic through the summed values and slopes at the nodes, each interval in
    /// powers of its offset u in [0, 1]: c0 + c1 u + c2 u^2 + c3 u^3, four numbers per
    /// interval (fewer operations per lookup than the Hermite basis).
    std::vector<double> poly;
    size_t intervals() const { return poly.size() / 4; }
  };
  void build(const std::vector<TrimCoilField>& coils, const std::vector<size_t>& use, double r_lo_m, double r_hi_m);
  /// value()'s search; the hint gets the piece found (or none).
  void lookup(double r_m, Hint& hint, double& b, double& db_dr) const;
  /// The table at r in piece p.
  static void node_value(const Piece& p, double r_m, double& b, double& db_dr) {
    const double t = (r_m - p.r0) * p.inv_h;
    const size_t i = std::min(static_cast<size_t>(t), p.intervals() - 1);
    const double u = t - static_cast<double>(i), u2 = u * u;
    const double* c = &p.poly[4 * i];
    b = (c[0] + c[1] * u) + u2 * (c[2] + c[3] * u);
    db_dr = ((c[1] + 2 * c[2] * u) + 3 * c[3] * u2) * p.inv_h;
  }
  std::vector<Piece> pieces_;
  size_t ncoils_ = 0;
  double lo_ = 0, inv_bucket_ = 0;
  std::vector<unsigned> bucket_;  // first piece that can hold a radius in each bucket
};

/// Whether two coil descriptions give the same shape and windows (everything but bmax_T).
bool same_shape(const TrimCoil& a, const TrimCoil& b);

/// Coefficients of p(c + y) in y from those of p (a Taylor shift by repeated synthetic division).
std::vector<long double> taylor_shift(std::vector<long double> coefficients, long double c);

/// The PSI-BFIELD description of a PSI-PHASE coil: the same field, B = bmax (f g' - f' g) / g^2
/// (numerator degree n + m - 1, denominator 2m), in the coil's coefficient origin.
TrimCoil bfield_from_phase(const TrimCoil& phase);

/// Value, first and second derivative of the rational function f(x)/g(x) with polynomial
/// coefficients num (a_0 + a_1 x + ...) and den (b_0 + ...; empty: g = 1).
void rational(const std::vector<double>& num, const std::vector<double>& den, double x, double& q,
              double& dq, double& d2q);

// (Inline: the fast steppers call these at every field sample.)
inline bool TrimCoilField::in_azimuth(double th, double sector_offset) const {
  if (everywhere_) return true;
  // (Stored inverses instead of divisions: a tracker tests this at every field sample of a
  // coil on some sectors.)
  const double two_pi = 2 * kPi, inv_two_pi = 1 / two_pi;
  if (window_) {
    // (Azimuths within a turn, as the fast steppers pass them, need no floor.)
    const double t = th >= 0 && th < two_pi ? th : th - two_pi * std::floor(th * inv_two_pi);
    const bool inside = phi_a_ <= phi_b_ ? (t >= phi_a_ && t <= phi_b_) : (t >= phi_a_ || t <= phi_b_);
    if (!inside) return false;
  }
  if (in_sector_.empty()) return true;
  // Sector k is centred on azimuth (k - 1) 360/N deg from sector 1's centre line (theta = 0
  // without a spiral): x counts sector pitches from sector 1's start edge, modulo N.
  const double n = symmetry_;
  double x = (th - sector_offset) * (n * inv_two_pi) + 0.5;
  if (!(x >= 0 && x < n)) x -= n * std::floor(x * (1 / n));
  int k = static_cast<int>(x);
  if (k >= symmetry_) k -= symmetry_;
  return in_sector_[static_cast<size_t>(k)] != 0;
}

inline void TrimCoilSum::add_near(double r_m, Hint& hint, double main_b, double main_db_dr, double main_db_dth,
                           double threshold_T, double& b, double& db_dr, double& db_dth) const {
  double s, ds;
  value_near(r_m, hint, s, ds);
  if (s == 0 && ds == 0) return;
  add_faded(s, ds, main_b, main_db_dr, main_db_dth, threshold_T, b, db_dr, db_dth);
}

}  // namespace turnfit
