// Open-boundary Poisson solver for space charge: CIC deposit, Hockney FFT convolution, CIC gather.
#include "turnfit/spacecharge/poisson.hpp"

#include <fftw3.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <mutex>
#include <new>
#include <sstream>
#include <vector>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit::sc {

namespace {

using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// FFTW's planner (and plan destruction) is not thread safe; executing plans is.
std::mutex& fftw_planner_mutex() {
  static std::mutex mu;
  return mu;
}

constexpr int kMinAxis = 8, kMaxAxis = 512;
constexpr long kMaxPoints = 1L << 24;  // 256^3: the doubled arrays then take about 4 GB together
// Hysteresis of the cached Green's function: rebuilt when the bunch needs a larger spacing or
// one below kShrink of the cached one, then with kHeadroom, so a slowly breathing bunch keeps it.
// On ring8's bunch over 40 turns (14400 solves at 32^3): 0.8 and 1.05 rebuilt it 1350 times,
// 0.7 and 1.1 656 times, 0.6 and 1.15 405 times, and the turns' widths moved by 2e-4 mm.
constexpr double kShrink = 0.7, kHeadroom = 1.1;
// An axis much thinner than the others is gridded as if it were this fraction of the widest
// spacing: cells of larger aspect ratios lose the integrated Green's function's digits to
// cancellation, and a sheet that thin is flat at the other axes' resolution anyway.
constexpr double kMinAspect = 0.01;

// Antiderivative of 1/r, d^3F/dxdydz = 1/r: the integrated Green's function of Qiang et al.,
// Phys. Rev. ST Accel. Beams 9, 044204 (2006). Long double: the 8-corner difference of a far
// cell cancels about (distance/h)^4 of F's digits (1e-8 of a double's at 100 cells).
long double antiderivative(long double x, long double y, long double z) {
  const long double r = std::sqrt(x * x + y * y + z * z);
  return y * z * std::log(x + r) + x * z * std::log(y + r) + x * y * std::log(z + r) -
         0.5L * x * x * std::atan(y * z / (x * r)) - 0.5L * y * y * std::atan(x * z / (y * r)) -
         0.5L * z * z * std::atan(x * y / (z * r));
}

// The 8-corner difference of F over cell (i, j, k), divided by its volume. Corners sit at
// half-integer offsets, so no coordinate is ever 0 and F has no singular term.
template <class Fn>
long double corner_difference(Fn&& f, int i, int j, int k) {
  long double s = 0;
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b)
      for (int c = 0; c < 2; ++c) {
        const long double v = f(i + a, j + b, k + c);
        s += ((a + b + c) % 2 == 1) ? v : -v;  // + at the upper corner (1,1,1): odd count of 1s
      }
  return s;
}

struct Cell {
  int i, j, k;           // lower node of the cloud-in-cell stencil
  double fx, fy, fz;     // fractions towards the upper node
};

std::string point_text(size_t i, const double* xyz, const double* q) {
  std::ostringstream s;
  s.precision(17);
  s << "point " << i << " (x, y, z, q) = (" << xyz[3 * i] << ", " << xyz[3 * i + 1] << ", " << xyz[3 * i + 2]
    << ", " << q[i] << ")";
  return s.str();
}

}  // namespace

double integrated_green(int i, int j, int k, const std::array<double, 3>& h_m) {
  const long double hx = h_m[0], hy = h_m[1], hz = h_m[2];
  auto f = [&](int ci, int cj, int ck) {
    return antiderivative((ci - 0.5L) * hx, (cj - 0.5L) * hy, (ck - 0.5L) * hz);
  };
  return static_cast<double>(corner_difference(f, std::abs(i), std::abs(j), std::abs(k)) / (hx * hy * hz));
}

GridSize parse_grid(const std::string& text) {
  auto bad = [&](const std::string& why) {
    return usage_error("grid '" + text + "': " + why);
  };
  std::vector<int> axes;
  size_t pos = 0;
  while (true) {
    size_t end = text.find('x', pos);
    const std::string part = text.substr(pos, end == std::string::npos ? std::string::npos : end - pos);
    if (part.empty() || part.size() > 6 || part.find_first_not_of("0123456789") != std::string::npos)
      throw bad("expected points per axis as N or NxNxN (e.g. 32 or 64x64x32)");
    axes.push_back(std::stoi(part));
    if (end == std::string::npos) break;
    pos = end + 1;
  }
  if (axes.size() != 1 && axes.size() != 3)
    throw bad("expected one number (every axis) or three (NxNxN), not " + std::to_string(axes.size()));
  for (int a : axes) {
    if (a < kMinAxis)
      throw bad("a grid of " + std::to_string(a) + " points per axis cannot resolve a bunch: at least 8");
    if (a > kMaxAxis) throw bad("at most 512 points per axis, not " + std::to_string(a));
  }
  if (axes.size() == 1) return GridSize{axes[0], axes[0], axes[0]};
  return GridSize{axes[0], axes[1], axes[2]};
}

struct OpenPoissonSolver::Impl {
  GridSize g;
  unsigned threads = 1;
  int n0, n1, n2;           // doubled grid
  int n2c;                  // complex points along the last axis (r2c)
  size_t real_size, complex_size;
  double* rho = nullptr;    // doubled real grid: charge [C] in the first octant, zeros elsewhere
  double* phi = nullptr;    // doubled real grid: potential [V] after the inverse transform
  fftw_complex* spec = nullptr;
  std::vector<double> green_hat;  // FFT of the mirrored Green's function, with 1/(4 pi eps0 N)
  fftw_plan forward = nullptr, backward = nullptr;

  std::array<double, 3> h{{0, 0, 0}};       // cached spacing of green_hat [m]
  std::array<double, 3> h_last{{0, 0, 0}};  // spacing of the last solve
  std::vector<double> efield;               // E [V/m] at the nx*ny*nz nodes, xyz interleaved
  std::vector<Cell> cells;
  std::vector<unsigned char> on_grid;
  size_t outside = 0;
  SolveTimes times;

  size_t at(int i, int j, int k) const { return (static_cast<size_t>(i) * n1 + j) * n2 + k; }

  void build_green();
  void deposit(size_t n, const double* q);
  void field_on_nodes();
  void gather(size_t n, double* E) const;
};

OpenPoissonSolver::OpenPoissonSolver(GridSize g, unsigned threads) : impl_(std::make_unique<Impl>()) {
  for (int a : {g.nx, g.ny, g.nz})
    if (a < kMinAxis || a > kMaxAxis)
      throw usage_error("space charge grid: " + std::to_string(a) + " points on an axis: expected 8..512");
  const long points = static_cast<long>(g.nx) * g.ny * g.nz;
  if (points > kMaxPoints)
    throw usage_error("space charge grid " + std::to_string(g.nx) + "x" + std::to_string(g.ny) + "x" +
                      std::to_string(g.nz) + ": " + std::to_string(points) +
                      " points need more memory than allowed (at most 2^24, e.g. 256x256x256)");
  Impl& m = *impl_;
  m.g = g;
  m.threads = resolve_thread_count(threads);
  m.n0 = 2 * g.nx;
  m.n1 = 2 * g.ny;
  m.n2 = 2 * g.nz;
  m.n2c = m.n2 / 2 + 1;
  m.real_size = static_cast<size_t>(m.n0) * m.n1 * m.n2;
  m.complex_size = static_cast<size_t>(m.n0) * m.n1 * m.n2c;
  std::lock_guard<std::mutex> lock(fftw_planner_mutex());
  m.rho = fftw_alloc_real(m.real_size);
  m.phi = fftw_alloc_real(m.real_size);
  m.spec = fftw_alloc_complex(m.complex_size);
  if (!m.rho || !m.phi || !m.spec) {
    fftw_free(m.rho);
    fftw_free(m.phi);
    fftw_free(m.spec);
    throw std::bad_alloc();
  }
  // The padding octants of rho stay zero for the solver's life: solves write only the first.
  std::memset(m.rho, 0, m.real_size * sizeof(double));
  // FFTW_ESTIMATE does not touch the arrays and picks the same plan every time (deterministic).
  m.forward = fftw_plan_dft_r2c_3d(m.n0, m.n1, m.n2, m.rho, m.spec, FFTW_ESTIMATE);
  m.backward = fftw_plan_dft_c2r_3d(m.n0, m.n1, m.n2, m.spec, m.phi, FFTW_ESTIMATE);
  if (!m.forward || !m.backward) {
    if (m.forward) fftw_destroy_plan(m.forward);
    if (m.backward) fftw_destroy_plan(m.backward);
    fftw_free(m.rho);
    fftw_free(m.phi);
    fftw_free(m.spec);
    throw Error(ExitCode::software, "space charge: FFTW could not plan the transforms");
  }
}

OpenPoissonSolver::~OpenPoissonSolver() {
  Impl& m = *impl_;
  std::lock_guard<std::mutex> lock(fftw_planner_mutex());
  fftw_destroy_plan(m.forward);
  fftw_destroy_plan(m.backward);
  fftw_free(m.rho);
  fftw_free(m.phi);
  fftw_free(m.spec);
}

size_t OpenPoissonSolver::outside() const { return impl_->outside; }
std::array<double, 3> OpenPoissonSolver::spacing() const { return impl_->h_last; }
const SolveTimes& OpenPoissonSolver::times() const { return impl_->times; }
GridSize OpenPoissonSolver::grid() const { return impl_->g; }

// Hockney's method (Hockney & Eastwood, Computer Simulation Using Particles, sec. 6-5-4): the
// aperiodic convolution of the nx*ny*nz charges is the cyclic one on the doubled grid with the
// Green's function mirrored, G2(i) = G(min(i, 2nx - i)); it is even, so its transform is real
// (the imaginary rounding is dropped, which keeps the kernel exactly symmetric).
void OpenPoissonSolver::Impl::build_green() {
  const auto t0 = Clock::now();
  const int cx = g.nx + 2, cy = g.ny + 2, cz = g.nz + 2;  // corners at (c - 1/2) h, c = 0..n+1
  std::vector<long double> corner(static_cast<size_t>(cx) * cy * cz);
  const long double hx = h[0], hy = h[1], hz = h[2];
  parallel_for(static_cast<size_t>(cx), threads, [&](size_t ci, unsigned) {
    const long double x = (static_cast<long double>(ci) - 0.5L) * hx;
    for (int cj = 0; cj < cy; ++cj)
      for (int ck = 0; ck < cz; ++ck)
        corner[(ci * cy + cj) * cz + ck] = antiderivative(x, (cj - 0.5L) * hy, (ck - 0.5L) * hz);
  });
  const long double scale = 1.0L / (hx * hy * hz) / (4 * static_cast<long double>(kPi) * kEpsilon0_F_m) /
                            (static_cast<long double>(n0) * n1 * n2);
  // Fill the mirrored Green's function into phi (free now) and transform it with the forward plan.
  parallel_for(static_cast<size_t>(n0), threads, [&](size_t i2, unsigned) {
    const int i = static_cast<int>(i2) <= g.nx ? static_cast<int>(i2) : n0 - static_cast<int>(i2);
    for (int j2 = 0; j2 < n1; ++j2) {
      const int j = j2 <= g.ny ? j2 : n1 - j2;
      for (int k2 = 0; k2 < n2; ++k2) {
        const int k = k2 <= g.nz ? k2 : n2 - k2;
        auto f = [&](int a, int b, int c) { return corner[(static_cast<size_t>(a) * cy + b) * cz + c]; };
        phi[at(static_cast<int>(i2), j2, k2)] = static_cast<double>(corner_difference(f, i, j, k) * scale);
      }
    }
  });
  fftw_execute_dft_r2c(forward, phi, spec);
  green_hat.resize(complex_size);
  for (size_t m = 0; m < complex_size; ++m) green_hat[m] = spec[m][0];
  times.green_s += seconds_since(t0);
  ++times.green_builds;
}

// Cloud-in-cell deposit, split between threads by x-slabs of nodes: each thread walks every
// particle in order and adds only to its own slabs, so every node sums its contributions in
// particle order whatever the thread count (bitwise the same result as one thread).
void OpenPoissonSolver::Impl::deposit(size_t n, const double* q) {
  for (int i = 0; i < g.nx; ++i)
    for (int j = 0; j < g.ny; ++j) std::memset(rho + at(i, j, 0), 0, sizeof(double) * g.nz);
  // Slab bounds with about equal particle counts (a bunch crowds the middle slabs).
  std::vector<size_t> count(static_cast<size_t>(g.nx) + 1, 0);
  size_t charged = 0;
  for (size_t p = 0; p < n; ++p)
    if (on_grid[p] && q[p] != 0) {
      ++count[static_cast<size_t>(cells[p].i)];
      ++charged;
    }
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(threads, std::max<size_t>(1, charged / 4096)));
  std::vector<int> bound(workers + 1, g.nx);
  bound[0] = 0;
  {
    size_t cum = 0;
    unsigned w = 1;
    for (int i = 0; i < g.nx && w < workers; ++i) {
      cum += count[static_cast<size_t>(i)];
      while (w < workers && cum * workers >= charged * w) bound[w++] = i + 1;
    }
  }
  run_workers(workers, [&](unsigned w) {
    const int lo = bound[w], hi = bound[w + 1];
    for (size_t p = 0; p < n; ++p) {
      if (!on_grid[p] || q[p] == 0) continue;
      const Cell& c = cells[p];
      if (c.i + 1 < lo || c.i >= hi) continue;
      const double wx[2] = {1 - c.fx, c.fx}, wy[2] = {1 - c.fy, c.fy}, wz[2] = {1 - c.fz, c.fz};
      for (int a = 0; a < 2; ++a) {
        const int i = c.i + a;
        if (i < lo || i >= hi) continue;
        const double qa = q[p] * wx[a];
        for (int b = 0; b < 2; ++b) {
          const double qab = qa * wy[b];
          double* row = rho + at(i, c.j + b, c.k);
          row[0] += qab * wz[0];
          row[1] += qab * wz[1];
        }
      }
    }
  });
}

// E = -grad phi by centred differences at every node of the charge's octant. The convolution is
// exact (aperiodic) on indices -1..n of each axis, so the neighbours of the octant's edge nodes
// are right too (index -1 is 2n-1 on the doubled grid).
void OpenPoissonSolver::Impl::field_on_nodes() {
  efield.resize(static_cast<size_t>(g.nx) * g.ny * g.nz * 3);
  const double sx = -0.5 / h[0], sy = -0.5 / h[1], sz = -0.5 / h[2];
  parallel_for(static_cast<size_t>(g.nx), threads, [&](size_t i2, unsigned) {
    const int i = static_cast<int>(i2);
    const int im = i == 0 ? n0 - 1 : i - 1;
    for (int j = 0; j < g.ny; ++j) {
      const int jm = j == 0 ? n1 - 1 : j - 1;
      double* e = efield.data() + (static_cast<size_t>(i) * g.ny + j) * g.nz * 3;
      const double* c = phi + at(i, j, 0);
      const double* xp = phi + at(i + 1, j, 0);
      const double* xm = phi + at(im, j, 0);
      const double* yp = phi + at(i, j + 1, 0);
      const double* ym = phi + at(i, jm, 0);
      for (int k = 0; k < g.nz; ++k) {
        const int km = k == 0 ? n2 - 1 : k - 1;
        e[3 * k] = sx * (xp[k] - xm[k]);
        e[3 * k + 1] = sy * (yp[k] - ym[k]);
        e[3 * k + 2] = sz * (c[k + 1] - c[km]);
      }
    }
  });
}

// Cloud-in-cell gather with the deposit's weights (Hockney & Eastwood sec. 5-3: the same
// assignment both ways is what cancels the self-force and conserves momentum).
void OpenPoissonSolver::Impl::gather(size_t n, double* E) const {
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(threads, std::max<size_t>(1, n / 4096)));
  run_workers(workers, [&](unsigned w) {
    const size_t begin = n * w / workers, end = n * (w + 1) / workers;
    for (size_t p = begin; p < end; ++p) {
      if (!on_grid[p]) continue;
      const Cell& c = cells[p];
      const double wx[2] = {1 - c.fx, c.fx}, wy[2] = {1 - c.fy, c.fy}, wz[2] = {1 - c.fz, c.fz};
      double ex = 0, ey = 0, ez = 0;
      for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b) {
          const double wab = wx[a] * wy[b];
          const double* e = efield.data() + ((static_cast<size_t>(c.i + a) * g.ny + c.j + b) * g.nz + c.k) * 3;
          for (int d = 0; d < 2; ++d) {
            const double wt = wab * wz[d];
            ex += wt * e[3 * d];
            ey += wt * e[3 * d + 1];
            ez += wt * e[3 * d + 2];
          }
        }
      E[3 * p] = ex;
      E[3 * p + 1] = ey;
      E[3 * p + 2] = ez;
    }
  });
}

void OpenPoissonSolver::solve(size_t n, const double* xyz, const double* q, double* E) {
  Impl& m = *impl_;
  const auto t0 = Clock::now();
  ++m.times.solves;
  for (size_t p = 0; p < n; ++p)
    if (!std::isfinite(xyz[3 * p]) || !std::isfinite(xyz[3 * p + 1]) || !std::isfinite(xyz[3 * p + 2]) ||
        !std::isfinite(q[p]))
      throw Error(ExitCode::data, "space charge: " + point_text(p, xyz, q) + " is not finite");
  std::fill(E, E + 3 * n, 0.0);
  m.outside = 0;
  if (n == 0) return;

  // Halo cut: mean and rms weighted by |q| (every point alike when none carries charge).
  m.on_grid.assign(n, 1);
  double wsum_all = 0;
  for (size_t p = 0; p < n; ++p) wsum_all += std::fabs(q[p]);
  auto weight = [&](size_t p) { return wsum_all > 0 ? std::fabs(q[p]) : 1.0; };
  if (halo_sigma > 0) {
    for (int pass = 0; pass < 3; ++pass) {
      double w = 0, mean[3] = {0, 0, 0}, var[3] = {0, 0, 0};
      for (size_t p = 0; p < n; ++p)
        if (m.on_grid[p]) {
          w += weight(p);
          for (int a = 0; a < 3; ++a) mean[a] += weight(p) * xyz[3 * p + a];
        }
      if (!(w > 0)) break;
      for (double& v : mean) v /= w;
      for (size_t p = 0; p < n; ++p)
        if (m.on_grid[p])
          for (int a = 0; a < 3; ++a) var[a] += weight(p) * (xyz[3 * p + a] - mean[a]) * (xyz[3 * p + a] - mean[a]);
      double cut[3], widest = 0;
      for (int a = 0; a < 3; ++a) widest = std::max(widest, std::sqrt(var[a] / w));
      // An axis with (next to) no spread cuts nothing: its rms is rounding, not a size.
      for (int a = 0; a < 3; ++a) {
        const double rms = std::sqrt(var[a] / w);
        cut[a] = rms > 1e-12 * widest ? halo_sigma * rms : HUGE_VAL;
      }
      size_t left = 0;
      for (size_t p = 0; p < n; ++p) {
        if (!m.on_grid[p]) continue;
        for (int a = 0; a < 3; ++a)
          if (std::fabs(xyz[3 * p + a] - mean[a]) > cut[a]) {
            m.on_grid[p] = 0;
            ++left;
            break;
          }
      }
      m.outside += left;
      if (left == 0) break;
    }
  }

  // The grid's box: the extent of the points on it with one spare cell each side.
  double lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (size_t p = 0; p < n; ++p)
    if (m.on_grid[p])
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(lo[a], xyz[3 * p + a]);
        hi[a] = std::max(hi[a], xyz[3 * p + a]);
      }
  const int na[3] = {m.g.nx, m.g.ny, m.g.nz};
  double need[3], widest = 0;
  for (int a = 0; a < 3; ++a) {
    need[a] = (hi[a] - lo[a]) / (na[a] - 3);
    widest = std::max(widest, need[a]);
  }

  // Monopole of the grid's charge, for the points left out.
  auto monopole = [&]() {
    if (m.outside == 0) return;
    double qg = 0, c[3] = {0, 0, 0};
    for (size_t p = 0; p < n; ++p)
      if (m.on_grid[p]) {
        qg += q[p];
        for (int a = 0; a < 3; ++a) c[a] += q[p] * xyz[3 * p + a];
      }
    if (qg == 0) return;
    for (double& v : c) v /= qg;
    const double k = qg / (4 * kPi * kEpsilon0_F_m);
    for (size_t p = 0; p < n; ++p) {
      if (m.on_grid[p]) continue;
      const double d[3] = {xyz[3 * p] - c[0], xyz[3 * p + 1] - c[1], xyz[3 * p + 2] - c[2]};
      const double r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
      if (!(r2 > 0)) continue;
      const double f = k / (r2 * std::sqrt(r2));
      for (int a = 0; a < 3; ++a) E[3 * p + a] = f * d[a];
    }
  };

  if (!(widest > 0)) {
    // Every point on the grid at one place: one point has no self-field and coincident charges
    // have no direction to push each other in.
    monopole();
    m.times.deposit_s += seconds_since(t0);
    return;
  }
  bool rebuild = false;
  double want[3];
  for (int a = 0; a < 3; ++a) {
    // A flat axis (all points in one plane) takes the widest spacing: its cells then are cubes
    // rather than slivers the charge's sheet would fall between.
    want[a] = need[a] > 0 ? std::max(need[a], kMinAspect * widest) : widest;
    if (!(m.h[a] > 0) || want[a] > m.h[a] || want[a] < kShrink * m.h[a]) rebuild = true;
  }
  if (rebuild)
    for (int a = 0; a < 3; ++a) m.h[a] = kHeadroom * want[a];
  m.h_last = m.h;
  // Centre the points: their span (at most (n-3) h) then lies in nodes 1..n-2.
  double origin[3];
  for (int a = 0; a < 3; ++a) origin[a] = 0.5 * (lo[a] + hi[a]) - 0.5 * (na[a] - 1) * m.h[a];

  m.cells.resize(n);
  {
    const unsigned workers = static_cast<unsigned>(std::min<size_t>(m.threads, std::max<size_t>(1, n / 4096)));
    run_workers(workers, [&](unsigned w) {
      for (size_t p = n * w / workers, end = n * (w + 1) / workers; p < end; ++p) {
        if (!m.on_grid[p]) continue;
        int idx[3];
        double frac[3];
        for (int a = 0; a < 3; ++a) {
          const double u = (xyz[3 * p + a] - origin[a]) / m.h[a];
          // Rounding may put an extreme point a hair outside nodes 1..n-2: clamp the stencil.
          const int i = std::min(std::max(static_cast<int>(std::floor(u)), 0), na[a] - 2);
          idx[a] = i;
          frac[a] = std::min(std::max(u - i, 0.0), 1.0);
        }
        m.cells[p] = Cell{idx[0], idx[1], idx[2], frac[0], frac[1], frac[2]};
      }
    });
  }
  m.deposit(n, q);
  m.times.deposit_s += seconds_since(t0);

  if (rebuild) m.build_green();

  auto t1 = Clock::now();
  fftw_execute(m.forward);
  const double* gh = m.green_hat.data();
  for (size_t k = 0; k < m.complex_size; ++k) {
    m.spec[k][0] *= gh[k];
    m.spec[k][1] *= gh[k];
  }
  fftw_execute(m.backward);
  m.times.fft_s += seconds_since(t1);

  t1 = Clock::now();
  m.field_on_nodes();
  m.gather(n, E);
  monopole();
  m.times.gather_s += seconds_since(t1);
}

void direct_field(size_t n, const double* xyz, const double* q, double* E, double soft_m) {
  const double k = 1 / (4 * kPi * kEpsilon0_F_m);
  const double s2 = soft_m * soft_m;
  for (size_t i = 0; i < n; ++i) {
    double e[3] = {0, 0, 0};
    for (size_t j = 0; j < n; ++j) {
      if (j == i || q[j] == 0) continue;
      const double d[3] = {xyz[3 * i] - xyz[3 * j], xyz[3 * i + 1] - xyz[3 * j + 1], xyz[3 * i + 2] - xyz[3 * j + 2]};
      const double r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + s2;
      if (!(r2 > 0)) continue;
      const double f = q[j] / (r2 * std::sqrt(r2));
      for (int a = 0; a < 3; ++a) e[a] += f * d[a];
    }
    for (int a = 0; a < 3; ++a) E[3 * i + a] = k * e[a];
  }
}

}  // namespace turnfit::sc
