// Midplane field maps Bz(r, theta) on a polar grid with N-fold symmetry, and their
// C1 bicubic-spline interpolation (tunes need continuous dBz/dr and dBz/dtheta).
#pragma once

#include <array>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace turnfit {

/// Bz and its first derivatives at one midplane point.
struct FieldSample {
  double bz_T = 0;          ///< Bz [T]
  double dbz_dr_T_m = 0;    ///< dBz/dr [T/m]
  double dbz_dth_T = 0;     ///< dBz/dtheta [T/rad]
};

/// The grid of a polar map covering one sector (periodic in theta with period
/// 2 pi / symmetry): radii r_min + i dr, azimuths theta_min + j dtheta,
/// with ntheta * dtheta * symmetry = 2 pi.
struct PolarGrid {
  // Kept in the file units (mm, deg) so that maps written and read back are identical.
  double r_min_mm = 0;
  double dr_mm = 0;
  int nr = 0;
  double theta_min_deg = 0;
  int ntheta = 0;
  int symmetry = 1;
  /// Azimuthal step [rad].
  double dtheta_rad() const;
  /// Smallest radius [m].
  double r_min_m() const { return r_min_mm * 1e-3; }
  /// Radial step [m].
  double dr_m() const { return dr_mm * 1e-3; }
  /// First azimuth [rad].
  double theta_min_rad() const;
  /// Largest radius of the grid [m].
  double r_max_m() const { return (r_min_mm + (nr - 1) * dr_mm) * 1e-3; }
};

/// Refuses (EX_DATAERR "file:line: ...", naming the limit) a grid of more than
/// limits::kGridPoints points, before a reader allocates for it.
void check_grid_size(long nr, long ntheta, const std::string& file = "field map", long line = 0);

/// The spline along radius at fixed sub-cell azimuths: for each radial cell i, azimuthal cell j
/// and offset slot s (an azimuth theta_min + (j + v_s) dtheta), the patch's polynomials in v
/// evaluated at v_s, so that Bz(u) = sum_k row_k u^k and dBz/dv(u) = sum_k drow_k u^k (u the
/// radial position in the cell). A grid-aligned Runge-Kutta step samples the field at the same
/// few sub-cell azimuths in every cell it crosses: with this table a sample costs one Horner
/// scheme in u per output instead of four in v and one in u. The rows are the same
/// expressions sample() evaluates, in the same order, so both give the same numbers for the
/// same (i, j, v). Built by PolarFieldMap::row_table.
struct FieldRowTable {
  struct Rows {
    double row[4], drow[4];
  };
  std::vector<double> v;  ///< offsets v_s in [0, 1)
  int nslot = 0, ntheta = 0;
  std::vector<Rows> rows;  ///< (i * ntheta + j) * nslot + s
  const Rows& at(int i, int j, int s) const {
    return rows[(static_cast<size_t>(i) * ntheta + j) * nslot + s];
  }
};

/// A midplane field map with bicubic-spline interpolation.
///
/// The interpolant is the tensor-product cubic spline (not-a-knot in r, periodic in
/// theta), stored as one bicubic patch per cell, so Bz and both first derivatives are
/// continuous everywhere inside the map. Outside [r_min, r_max] there is no field:
/// sample() returns false and trackers report a loss.
class PolarFieldMap {
 public:
  PolarFieldMap() = default;
  /// Builds the interpolant from grid values bz_T[i * ntheta + j] (radius-major).
  /// Throws EX_DATAERR if the grid is inconsistent or a value is not finite.
  PolarFieldMap(const PolarGrid& grid, std::vector<double> bz_T, std::string label = {});

  /// Interpolated field at (r, theta); false (out untouched) outside the radial range.
  bool sample(double r_m, double theta_rad, FieldSample& out) const;
  /// Bz only (NaN outside the map), for tables and plots.
  double bz(double r_m, double theta_rad) const;
  /// Whether r lies inside the map's radial range.
  bool contains(double r_m) const { return r_m >= r_min_ && r_m <= r_max_; }

  /// The row table for sub-cell offsets `v` (each in [0, 1)), built on first use and shared by
  /// every copy of this map (thread-safe); nullptr when it would exceed `max_bytes`.
  std::shared_ptr<const FieldRowTable> row_table(const std::vector<double>& v, size_t max_bytes = size_t(256) << 20) const;
  /// The field at radius r in azimuthal cell j at slot s of `t` (a table of this map): the
  /// numbers sample() gives at theta_min + (j + v_s) dtheta. False (out untouched) outside the
  /// radial range.
  bool sample_row(const FieldRowTable& t, double r_m, int j, int s, FieldSample& out) const {
    if (!(r_m >= r_min_ && r_m <= r_max_)) return false;
    double u;
    const FieldRowTable::Rows& q = t.at(radial_cell(r_m, u), j, s);
    from_rows(q.row, q.drow, u, out);
    return true;
  }
  /// sample_row with the radial cell of the previous sample as a guess (`cell`, -1: none; set
  /// to this sample's): while the radius stays in that cell, the row's address is known before
  /// the radius is, and a single particle's dependency chain loses the index computation and
  /// the load. The same numbers to rounding (u from the cell's edge instead of from r_min).
  bool sample_row_near(const FieldRowTable& t, double r_m, int j, int s, int& cell, FieldSample& out) const {
    if (cell >= 0) {
      const FieldRowTable::Rows& q = t.at(cell, j, s);
      const double u = (r_m - (r_min_ + cell * grid_.dr_m())) * inv_dr_;
      if (u >= 0 && u < 1) {
        // Estrin's scheme: two levels of products where Horner's has three.
        const double u2 = u * u;
        out.bz_T = (q.row[0] + q.row[1] * u) + u2 * (q.row[2] + q.row[3] * u);
        out.dbz_dr_T_m = ((q.row[1] + 2 * q.row[2] * u) + 3 * q.row[3] * u2) * inv_dr_;
        out.dbz_dth_T = ((q.drow[0] + q.drow[1] * u) + u2 * (q.drow[2] + q.drow[3] * u)) * inv_dth_;
        return true;
      }
    }
    if (!(r_m >= r_min_ && r_m <= r_max_)) return false;
    double u;
    cell = radial_cell(r_m, u);
    const FieldRowTable::Rows& q = t.at(cell, j, s);
    from_rows(q.row, q.drow, u, out);
    return true;
  }
  /// sample_row_near for the n lanes of a group at one stage: lane l's radius r_m[l] and cell
  /// guess cell[l]; its field goes to bz[l], br[l], bt[l] (zeros off the map, where good[l] is
  /// cleared; good is never set). The numbers are sample_row_near's bit for bit: with `vector`
  /// and AVX-512 the lanes still in their cells go eight at a time (field/row_lanes.cpp), the
  /// others one by one through sample_row_near; without `vector`, every lane so (the same
  /// function compiled in the same file, which tests compare the kernel with).
  void sample_rows_near(const FieldRowTable& t, int n, const double* r_m, int j, int s, int* cell, double* bz,
                        double* br, double* bt, unsigned char* good, bool vector = true) const;

  /// The grid.
  const PolarGrid& grid() const { return grid_; }
  /// Grid values [T], radius-major.
  const std::vector<double>& values() const { return *bz_; }
  /// Grid value at radius index i, azimuth index j [T].
  double value(int i, int j) const { return (*bz_)[static_cast<size_t>(i) * grid_.ntheta + j]; }
  /// Free-text label (file label or generator description).
  const std::string& label() const { return label_; }
  /// Azimuthal average of the grid values at radius index i [T].
  double average(int i) const;
  /// Azimuthal average of Bz at radius r (by the interpolant at the grid azimuths) [T].
  double average_at(double r_m) const;

 private:
  void build();
  // sample()'s parts, shared with the row tables so that both give the same numbers.
  /// The radial cell of r (inside the map) and the position u in it.
  int radial_cell(double r_m, double& u) const {
    const double x = (r_m - r_min_) * inv_dr_;
    int i = static_cast<int>(x);
    if (i >= grid_.nr - 1) i = grid_.nr - 2;
    u = x - i;
    return i;
  }
  /// A patch's polynomial in v for each power of u (Horner), with the v-derivative alongside.
  static void patch_rows(const std::array<double, 16>& a, double v, double row[4], double drow[4]) {
    for (int k = 0; k < 4; ++k) {
      const double* c = &a[k * 4];
      row[k] = ((c[3] * v + c[2]) * v + c[1]) * v + c[0];
      drow[k] = (3 * c[3] * v + 2 * c[2]) * v + c[1];
    }
  }
  /// The field at u from the rows (Horner in u).
  void from_rows(const double row[4], const double drow[4], double u, FieldSample& out) const {
    out.bz_T = ((row[3] * u + row[2]) * u + row[1]) * u + row[0];
    out.dbz_dr_T_m = ((3 * row[3] * u + 2 * row[2]) * u + row[1]) * inv_dr_;
    out.dbz_dth_T = (((drow[3] * u + drow[2]) * u + drow[1]) * u + drow[0]) * inv_dth_;
  }
  // The values and patches never change after construction and are shared between copies: an
  // optimizer builds a model (holding a copy of the map) per design, and copying ring8's 2.7 MB
  // of patches cost each design a memcpy and 700 page faults.
  PolarGrid grid_;
  std::shared_ptr<const std::vector<double>> bz_;
  std::string label_;
  double r_min_ = 0, r_max_ = 0, theta_min_ = 0;
  double inv_dr_ = 0, inv_dth_ = 0;
  std::shared_ptr<const std::vector<std::array<double, 16>>> coef_;  ///< per cell: a[k*4+l] u^k v^l
  const std::array<double, 16>* patch_ = nullptr;                    ///< coef_'s data (shared, so valid in copies)
  struct RowCache;                       // row tables built so far (field_map.cpp)
  std::shared_ptr<RowCache> row_cache_;  // shared by copies, like the patches
};

/// Samples f(r_m, theta_rad) [T] on a grid: the analytic-field generator used by tests
/// and by machine builders.
PolarFieldMap make_field_map(const PolarGrid& grid,
                             const std::function<double(double, double)>& f,
                             const std::string& label);

}  // namespace turnfit
