// Bicubic spline interpolation of polar field maps (tensor-product spline as Hermite patches).
#include "turnfit/field/field_map.hpp"

#include <Eigen/Dense>
#include <cmath>
#include <mutex>

#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {
constexpr double kPi = 3.14159265358979323846;

/// Node slopes of the not-a-knot cubic spline through equally spaced samples; the
/// columns of y are independent data sets (h = 1; divide by the real spacing).
Eigen::MatrixXd notaknot_slopes(const Eigen::MatrixXd& y) {
  const int n = static_cast<int>(y.rows());
  Eigen::MatrixXd slopes(n, y.cols());
  if (n == 2) {  // a straight line
    for (int c = 0; c < y.cols(); ++c) slopes.col(c).setConstant(y(1, c) - y(0, c));
    return slopes;
  }
  if (n == 3) {  // not-a-knot with 3 points: the interpolating parabola
    for (int c = 0; c < y.cols(); ++c) {
      slopes(0, c) = (-3 * y(0, c) + 4 * y(1, c) - y(2, c)) / 2;
      slopes(1, c) = (y(2, c) - y(0, c)) / 2;
      slopes(2, c) = (y(0, c) - 4 * y(1, c) + 3 * y(2, c)) / 2;
    }
    return slopes;
  }
  // Interior rows: C2 continuity, m[i-1] + 4 m[i] + m[i+1] = 3 (y[i+1] - y[i-1]).
  // End rows: continuous third derivative at the second and second-to-last nodes,
  // which for Hermite cubics gives m0 - m2 = 4 y1 - 2 y0 - 2 y2 (and its mirror).
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n, n);
  Eigen::MatrixXd b(n, y.cols());
  A(0, 0) = 1;
  A(0, 2) = -1;
  b.row(0) = 4 * y.row(1) - 2 * y.row(0) - 2 * y.row(2);
  for (int i = 1; i < n - 1; ++i) {
    A(i, i - 1) = 1;
    A(i, i) = 4;
    A(i, i + 1) = 1;
    b.row(i) = 3 * (y.row(i + 1) - y.row(i - 1));
  }
  A(n - 1, n - 3) = 1;
  A(n - 1, n - 1) = -1;
  b.row(n - 1) = 4 * y.row(n - 2) - 2 * y.row(n - 3) - 2 * y.row(n - 1);
  return A.partialPivLu().solve(b);
}

/// Node slopes of the periodic cubic spline (h = 1) through y (rows: nodes).
Eigen::MatrixXd periodic_slopes(const Eigen::MatrixXd& y) {
  const int n = static_cast<int>(y.rows());
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n, n);
  Eigen::MatrixXd b(n, y.cols());
  if (n < 3) return Eigen::MatrixXd::Zero(n, y.cols());  // constant in theta
  for (int i = 0; i < n; ++i) {
    A(i, (i + n - 1) % n) += 1;
    A(i, i) += 4;
    A(i, (i + 1) % n) += 1;
    b.row(i) = 3 * (y.row((i + 1) % n) - y.row((i + n - 1) % n));
  }
  return A.partialPivLu().solve(b);
}
}  // namespace

double PolarGrid::dtheta_rad() const { return 2 * kPi / (static_cast<double>(symmetry) * ntheta); }
double PolarGrid::theta_min_rad() const { return theta_min_deg * kPi / 180.0; }

void check_grid_size(long nr, long ntheta, const std::string& file, long line) {
  if (nr > limits::kGridPoints || ntheta > limits::kGridPoints || nr * ntheta > limits::kGridPoints)
    throw data_error(file, line, "a grid of " + std::to_string(nr) + " x " + std::to_string(ntheta) +
                                     " points is larger than the " + std::to_string(limits::kGridPoints) +
                                     " points a map may hold (the limit)");
}

PolarFieldMap::PolarFieldMap(const PolarGrid& grid, std::vector<double> bz_T, std::string label)
    : grid_(grid), bz_(std::make_shared<const std::vector<double>>(std::move(bz_T))), label_(std::move(label)) {
  if (grid_.nr < 2 || grid_.ntheta < 1 || grid_.symmetry < 1 || !(grid_.dr_mm > 0) ||
      !(grid_.r_min_mm >= 0) || !std::isfinite(grid_.theta_min_deg))
    throw Error(ExitCode::data, "field map: invalid grid (need nr >= 2, ntheta >= 1, dr > 0, "
                                "r_min >= 0, symmetry >= 1)");
  check_grid_size(grid_.nr, grid_.ntheta);
  // Bounds a map of a real machine keeps by far, so that arithmetic on the grid stays exact
  // enough: an azimuth of 1e16 deg has no digit below 1 deg left (and stepped the tracker
  // backwards forever), a radius of 1e300 mm overflows the step.
  if (std::fabs(grid_.theta_min_deg) > 360)
    throw Error(ExitCode::data, "field map: theta_min_deg " + format_exact(grid_.theta_min_deg) +
                                    " is outside -360..360 deg");
  if (grid_.symmetry > 360)
    throw Error(ExitCode::data, "field map: symmetry " + std::to_string(grid_.symmetry) + " is above 360");
  if (!(grid_.dr_mm >= 1e-3) || !(grid_.r_min_mm + (grid_.nr - 1) * grid_.dr_mm <= 1e6))
    throw Error(ExitCode::data, "field map: the grid's radii (r_min_mm " + format_exact(grid_.r_min_mm) +
                                    ", dr_mm " + format_exact(grid_.dr_mm) +
                                    ") need dr >= 0.001 mm and the largest radius within 1000 m");
  if (bz_->size() != static_cast<size_t>(grid_.nr) * grid_.ntheta)
    throw Error(ExitCode::data, "field map: " + std::to_string(bz_->size()) + " values for a " +
                                    std::to_string(grid_.nr) + " x " + std::to_string(grid_.ntheta) +
                                    " grid");
  for (size_t k = 0; k < bz_->size(); ++k)
    if (!std::isfinite((*bz_)[k]))
      throw Error(ExitCode::data, "field map: value " + std::to_string(k) + " is not finite");
  build();
}

void PolarFieldMap::build() {
  const int nr = grid_.nr, nt = grid_.ntheta;
  r_min_ = grid_.r_min_m();
  r_max_ = grid_.r_max_m();
  theta_min_ = grid_.theta_min_rad();
  inv_dr_ = 1.0 / grid_.dr_m();
  inv_dth_ = 1.0 / grid_.dtheta_rad();
  Eigen::MatrixXd F(nr, nt);
  for (int i = 0; i < nr; ++i)
    for (int j = 0; j < nt; ++j) F(i, j) = value(i, j);
  // Slopes in grid units (per cell), so the patches live on the unit square.
  Eigen::MatrixXd Fu = notaknot_slopes(F);                          // d/du, columns = azimuths
  Eigen::MatrixXd Fv = periodic_slopes(F.transpose()).transpose();   // d/dv
  Eigen::MatrixXd Fuv = periodic_slopes(Fu.transpose()).transpose(); // d2/dudv

  // Hermite basis: p(t) = [1 t t^2 t^3] H [p0 p1 p0' p1']^T.
  Eigen::Matrix4d H;
  H << 1, 0, 0, 0, 0, 0, 1, 0, -3, 3, -2, -1, 2, -2, 1, 1;
  auto coef = std::make_shared<std::vector<std::array<double, 16>>>(static_cast<size_t>(nr - 1) * nt);
  for (int i = 0; i < nr - 1; ++i) {
    for (int j = 0; j < nt; ++j) {
      const int j1 = (j + 1) % nt;
      Eigen::Matrix4d G;
      G << F(i, j), F(i, j1), Fv(i, j), Fv(i, j1),          //
          F(i + 1, j), F(i + 1, j1), Fv(i + 1, j), Fv(i + 1, j1),  //
          Fu(i, j), Fu(i, j1), Fuv(i, j), Fuv(i, j1),        //
          Fu(i + 1, j), Fu(i + 1, j1), Fuv(i + 1, j), Fuv(i + 1, j1);
      Eigen::Matrix4d A = H * G * H.transpose();
      auto& c = (*coef)[static_cast<size_t>(i) * nt + j];
      for (int k = 0; k < 4; ++k)
        for (int l = 0; l < 4; ++l) c[k * 4 + l] = A(k, l);
    }
  }
  patch_ = coef->data();
  coef_ = std::move(coef);
  row_cache_ = std::make_shared<RowCache>();
}

struct PolarFieldMap::RowCache {
  std::mutex mu;
  std::vector<std::shared_ptr<const FieldRowTable>> tables;
};

std::shared_ptr<const FieldRowTable> PolarFieldMap::row_table(const std::vector<double>& v, size_t max_bytes) const {
  if (!row_cache_ || v.empty()) return nullptr;
  const size_t bytes = static_cast<size_t>(grid_.nr - 1) * grid_.ntheta * v.size() * sizeof(FieldRowTable::Rows);
  if (bytes > max_bytes) return nullptr;
  std::lock_guard<std::mutex> lock(row_cache_->mu);
  for (const auto& t : row_cache_->tables)
    if (t->v == v) return t;
  auto t = std::make_shared<FieldRowTable>();
  t->v = v;
  t->nslot = static_cast<int>(v.size());
  t->ntheta = grid_.ntheta;
  t->rows.resize(static_cast<size_t>(grid_.nr - 1) * grid_.ntheta * v.size());
  for (int i = 0; i < grid_.nr - 1; ++i)
    for (int j = 0; j < grid_.ntheta; ++j)
      for (int s = 0; s < t->nslot; ++s) {
        FieldRowTable::Rows& q = t->rows[(static_cast<size_t>(i) * grid_.ntheta + j) * t->nslot + s];
        patch_rows(patch_[static_cast<size_t>(i) * grid_.ntheta + j], v[static_cast<size_t>(s)], q.row, q.drow);
      }
  row_cache_->tables.push_back(t);
  return t;
}

bool PolarFieldMap::sample(double r_m, double theta_rad, FieldSample& out) const {
  if (!(r_m >= r_min_ && r_m <= r_max_)) return false;
  double u;
  const int i = radial_cell(r_m, u);
  double y = (theta_rad - theta_min_) * inv_dth_;
  const double nt = grid_.ntheta;
  if (y < 0 || y >= nt) y -= nt * std::floor(y / nt);  // periodic in theta (cheaper than fmod)
  int j = static_cast<int>(y);
  if (j >= grid_.ntheta) j = grid_.ntheta - 1;  // y rounded up to nt
  const double v = y - j;
  double row[4], drow[4];
  patch_rows(patch_[static_cast<size_t>(i) * grid_.ntheta + j], v, row, drow);
  from_rows(row, drow, u, out);
  return true;
}

double PolarFieldMap::bz(double r_m, double theta_rad) const {
  FieldSample s;
  return sample(r_m, theta_rad, s) ? s.bz_T : std::nan("");
}

double PolarFieldMap::average(int i) const {
  double s = 0;
  for (int j = 0; j < grid_.ntheta; ++j) s += value(i, j);
  return s / grid_.ntheta;
}

double PolarFieldMap::average_at(double r_m) const {
  double s = 0;
  for (int j = 0; j < grid_.ntheta; ++j) s += bz(r_m, theta_min_ + j * grid_.dtheta_rad());
  return s / grid_.ntheta;
}

PolarFieldMap make_field_map(const PolarGrid& grid, const std::function<double(double, double)>& f,
                             const std::string& label) {
  std::vector<double> v(static_cast<size_t>(grid.nr) * grid.ntheta);
  const double dth = grid.dtheta_rad();
  for (int i = 0; i < grid.nr; ++i)
    for (int j = 0; j < grid.ntheta; ++j)
      v[static_cast<size_t>(i) * grid.ntheta + j] =
          f(grid.r_min_m() + i * grid.dr_m(), grid.theta_min_rad() + j * dth);
  return PolarFieldMap(grid, std::move(v), label);
}

}  // namespace turnfit
