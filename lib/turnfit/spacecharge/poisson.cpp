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
// The gather differences the potential at each point's 8 stencil nodes itself, rather than at
// every node first, when there are fewer points than nodes over this. Gather times per solve (1
// thread): at 32^3, 2000 points 0.07 ms at the stencils against 0.09 ms by every node, 8000
// points 0.25 against 0.13; at 64^3, 30000 points 1.2 against 1.9, 1e5 points 4.6 against 3.1.
constexpr size_t kStencilCost = 8;

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

// Arrays from fftw_malloc (the alignment FFTW's SIMD code wants), freed by fftw_free.
struct FftwFree {
  void operator()(void* p) const { fftw_free(p); }
};
template <class T>
using FftwArray = std::unique_ptr<T[], FftwFree>;

template <class T>
FftwArray<T> fftw_array(size_t count) {
  void* p = fftw_malloc(sizeof(T) * std::max<size_t>(count, 1));
  if (!p) throw std::bad_alloc();
  std::memset(p, 0, sizeof(T) * std::max<size_t>(count, 1));
  return FftwArray<T>(static_cast<T*>(p));
}

// A point on the grid, as the deposit and the gather read it after sorting by x index: its
// cloud-in-cell stencil (lower node's j, k; fractions towards the upper node), charge and index.
struct GridPoint {
  size_t p;
  int j, k;
  double fx, fy, fz, q;
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

// Hockney's doubled grid is n0 x n1 x n2 = 2nx x 2ny x 2nz; its transform is computed as 1-D
// transforms axis by axis (k contiguous, then j, then i), each only where its input is not
// known to be zero and only where its output is read afterwards:
//   forward:  r2c along k for the nx*ny charged rows, c2c along j for the nx charged planes,
//             c2c along i for every (j, k) column (per j, through a worker's zero-padded block);
//   inverse:  c2c along i for every column, c2c along j and c2r along k only for the planes
//             and rows the centred differences read: indices 0..n and -1 (= 2n-1) of i and j.
// Every 1-D transform is computed by one plan whichever thread runs it, so the result does not
// depend on the thread count.
struct OpenPoissonSolver::Impl {
  GridSize g;
  unsigned threads = 1;
  int n0 = 0, n1 = 0, n2 = 0;  // doubled grid
  int n2c = 0;                 // complex points along k (r2c): nz + 1
  size_t block = 0;            // complex points of one j's (i, k) block: n0 * n2c
  FftwArray<double> rho;       // charge [C]: nx*ny rows of n2 (k >= nz stays zero)
  FftwArray<fftw_complex> spec;  // nx+2 planes (i = 0..nx, then -1) of n1 x n2c
  FftwArray<double> phi;       // potential [V]: (nx+2) x (ny+2) rows of n2 (index nx+1, ny+1: -1)
  FftwArray<fftw_complex> work;  // per worker: the i transform's zero-padded input and its output
  FftwArray<double> green;     // transform of the mirrored Green's function, with 1/(4 pi eps0 N):
                               // (nx+1) x (ny+1) x (nz+1), mirrored at use (see build_green)
  fftw_plan rows_r2c = nullptr, planes_fwd = nullptr, columns_fwd = nullptr, columns_bwd = nullptr,
            planes_bwd = nullptr, rows_c2r = nullptr, row_c2r = nullptr, green_dct = nullptr;

  std::array<double, 3> h{{0, 0, 0}};       // cached spacing of green [m]
  std::array<double, 3> h_last{{0, 0, 0}};  // spacing of the last solve
  std::array<double, 3> origin{{0, 0, 0}};  // position of node (0, 0, 0) in the last solve [m]
  std::vector<double> efield;               // E [V/m] at the nx*ny*nz nodes, xyz interleaved
  bool at_stencils = false;                 // the gather differences phi at the stencils' nodes
  std::vector<Cell> cells;                  // each point's stencil, unless at_stencils
  std::vector<unsigned char> on_grid;
  std::vector<size_t> histogram;            // per worker's particle chunk: points per x index
  std::vector<size_t> bucket;               // first point of each x index in `sorted`
  std::vector<GridPoint> sorted;            // the points on the grid by x index, in particle order within one
  size_t outside = 0;
  SolveTimes times;

  ~Impl();
  double* rho_row(int i, int j) const { return rho.get() + (static_cast<size_t>(i) * g.ny + j) * n2; }
  fftw_complex* plane(int p) const { return spec.get() + static_cast<size_t>(p) * n1 * n2c; }
  // Row of phi at i, j in -1..n (the convolution is exact, aperiodic, on these indices).
  const double* phi_row(int i, int j) const {
    const size_t p = i < 0 ? g.nx + 1 : i, r = j < 0 ? g.ny + 1 : j;
    return phi.get() + (p * (g.ny + 2) + r) * n2;
  }

  // Lower node of point p's cloud-in-cell stencil along axis a, and the fraction towards the upper.
  int node(const double* xyz, size_t p, int a, double& frac) const {
    const double u = (xyz[3 * p + a] - origin[a]) / h[a];
    const int n = a == 0 ? g.nx : a == 1 ? g.ny : g.nz;
    // Rounding may put an extreme point a hair outside nodes 1..n-2: clamp the stencil.
    // Truncation, not floor (a libm call on plain x86-64): they differ only for u < 0, where
    // both clamp to 0.
    const int i = std::min(std::max(static_cast<int>(u), 0), n - 2);
    frac = std::min(std::max(u - i, 0.0), 1.0);
    return i;
  }

  void plan();
  void build_green();
  void assign(size_t n, const double* xyz, const double* q);
  void deposit();
  void convolve();
  void field_on_nodes();
  void gather(size_t n, double* E);
};

OpenPoissonSolver::Impl::~Impl() {
  std::lock_guard<std::mutex> lock(fftw_planner_mutex());
  for (fftw_plan p : {rows_r2c, planes_fwd, columns_fwd, columns_bwd, planes_bwd, rows_c2r, row_c2r, green_dct})
    if (p) fftw_destroy_plan(p);
}

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
  m.block = static_cast<size_t>(m.n0) * m.n2c;
  // Zeroed once: rho's k >= nz and the padding rows i >= nx of each worker's input block are
  // never written again.
  m.rho = fftw_array<double>(static_cast<size_t>(g.nx) * g.ny * m.n2);
  m.spec = fftw_array<fftw_complex>(static_cast<size_t>(g.nx + 2) * m.n1 * m.n2c);
  m.phi = fftw_array<double>(static_cast<size_t>(g.nx + 2) * (g.ny + 2) * m.n2);
  m.work = fftw_array<fftw_complex>(2 * m.block * m.threads);
  m.green = fftw_array<double>(static_cast<size_t>(g.nx + 1) * (g.ny + 1) * (g.nz + 1));
  m.plan();
}

// Plans once, for new-array execution on every row, plane and block (FFTW's execute is thread
// safe, its planner is not). New-array execution needs the alignment the plan was made for;
// fftw_malloc'd arrays have it at their start and every row here is a multiple of 16 bytes from
// it, which is all this FFTW asks (fftw_alignment_of), but should a build ask for more, a row at
// an odd offset (n2c odd) would not have it: then every plan is made for unaligned arrays.
void OpenPoissonSolver::Impl::plan() {
  bool aligned = true;
  auto check = [&](const void* p) {
    aligned = aligned && fftw_alignment_of(static_cast<double*>(const_cast<void*>(p))) == 0;
  };
  for (int i = 0; i < g.nx; ++i) check(rho_row(i, 0));
  for (int p = 0; p < g.nx + 2; ++p) {
    check(plane(p));
    check(plane(p) + static_cast<size_t>(n1 - 1) * n2c);
    check(phi_row(p == g.nx + 1 ? -1 : p, 0));
    check(phi_row(p == g.nx + 1 ? -1 : p, -1));
  }
  for (unsigned w = 0; w < threads; ++w) {
    check(work.get() + 2 * w * block);
    check(work.get() + (2 * w + 1) * block);
  }
  // FFTW_ESTIMATE does not touch the arrays and picks the same plan every time (deterministic).
  const unsigned flags = FFTW_ESTIMATE | (aligned ? 0u : static_cast<unsigned>(FFTW_UNALIGNED));
  const int len_k[1] = {n2}, len_j[1] = {n1}, len_i[1] = {n0};
  fftw_complex* in = work.get();
  fftw_complex* out = work.get() + block;
  std::lock_guard<std::mutex> lock(fftw_planner_mutex());
  rows_r2c = fftw_plan_many_dft_r2c(1, len_k, g.ny, rho.get(), nullptr, 1, n2, spec.get(), nullptr, 1, n2c, flags);
  planes_fwd = fftw_plan_many_dft(1, len_j, n2c, spec.get(), nullptr, n2c, 1, spec.get(), nullptr, n2c, 1,
                                  FFTW_FORWARD, flags);
  columns_fwd = fftw_plan_many_dft(1, len_i, n2c, in, nullptr, n2c, 1, out, nullptr, n2c, 1, FFTW_FORWARD, flags);
  columns_bwd = fftw_plan_many_dft(1, len_i, n2c, out, nullptr, n2c, 1, out, nullptr, n2c, 1, FFTW_BACKWARD, flags);
  planes_bwd = fftw_plan_many_dft(1, len_j, n2c, spec.get(), nullptr, n2c, 1, spec.get(), nullptr, n2c, 1,
                                  FFTW_BACKWARD, flags);
  rows_c2r = fftw_plan_many_dft_c2r(1, len_k, g.ny + 1, spec.get(), nullptr, 1, n2c, phi.get(), nullptr, 1, n2, flags);
  row_c2r = fftw_plan_dft_c2r_1d(n2, plane(0) + static_cast<size_t>(n1 - 1) * n2c,
                                 phi.get() + static_cast<size_t>(g.ny + 1) * n2, flags);
  green_dct = fftw_plan_r2r_3d(g.nx + 1, g.ny + 1, g.nz + 1, green.get(), green.get(), FFTW_REDFT00, FFTW_REDFT00,
                               FFTW_REDFT00, FFTW_ESTIMATE);
  for (fftw_plan p : {rows_r2c, planes_fwd, columns_fwd, columns_bwd, planes_bwd, rows_c2r, row_c2r, green_dct})
    if (!p) throw Error(ExitCode::software, "space charge: FFTW could not plan the transforms");
}

OpenPoissonSolver::~OpenPoissonSolver() = default;

size_t OpenPoissonSolver::outside() const { return impl_->outside; }
std::array<double, 3> OpenPoissonSolver::spacing() const { return impl_->h_last; }
const SolveTimes& OpenPoissonSolver::times() const { return impl_->times; }
GridSize OpenPoissonSolver::grid() const { return impl_->g; }

// Hockney's method (Hockney & Eastwood, Computer Simulation Using Particles, sec. 6-5-4): the
// aperiodic convolution of the nx*ny*nz charges is the cyclic one on the doubled grid with the
// Green's function mirrored, G2(i) = G(min(i, 2nx - i)). G2 is even on every axis, so its DFT
// is real and is the DCT-I (FFTW's REDFT00) of G on 0..n per axis:
// X(k) = G(0) + (-1)^k G(n) + 2 sum_{i=1}^{n-1} G(i) cos(pi i k / n), X(2n - k) = X(k).
// Computing it as a DCT keeps the kernel exactly real and symmetric, on an eighth of the points.
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
  const int gy = g.ny + 1, gz = g.nz + 1;
  parallel_for(static_cast<size_t>(g.nx + 1), threads, [&](size_t i, unsigned) {
    auto f = [&](int a, int b, int c) { return corner[(static_cast<size_t>(a) * cy + b) * cz + c]; };
    for (int j = 0; j < gy; ++j)
      for (int k = 0; k < gz; ++k)
        green[(i * gy + j) * gz + k] = static_cast<double>(corner_difference(f, static_cast<int>(i), j, k) * scale);
  });
  fftw_execute(green_dct);
  times.green_s += seconds_since(t0);
  ++times.green_builds;
}

// Each on-grid point's cloud-in-cell stencil, sorted by its x index (a stable counting sort:
// within an index, particle order, whatever the thread count) for the deposit to take the
// charges slab by slab and the gather to read the grid's field plane by plane.
void OpenPoissonSolver::Impl::assign(size_t n, const double* xyz, const double* q) {
  const size_t nx = static_cast<size_t>(g.nx);
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(threads, std::max<size_t>(1, n / 4096)));
  histogram.assign(workers * nx, 0);
  run_workers(workers, [&](unsigned w) {
    size_t* count = histogram.data() + w * nx;
    double f;
    for (size_t p = n * w / workers, end = n * (w + 1) / workers; p < end; ++p)
      if (on_grid[p]) ++count[node(xyz, p, 0, f)];
  });
  // Chunk w's points of index i go after those of every earlier chunk: histogram becomes each
  // chunk's next slot per index.
  bucket.assign(nx + 1, 0);
  size_t total = 0;
  for (size_t i = 0; i < nx; ++i) {
    bucket[i] = total;
    for (unsigned w = 0; w < workers; ++w) {
      const size_t c = histogram[w * nx + i];
      histogram[w * nx + i] = total;
      total += c;
    }
  }
  bucket[nx] = total;
  sorted.resize(total);
  at_stencils = total * kStencilCost < static_cast<size_t>(g.nx) * g.ny * g.nz;
  if (!at_stencils) cells.resize(n);
  run_workers(workers, [&](unsigned w) {
    size_t* next = histogram.data() + w * nx;
    for (size_t p = n * w / workers, end = n * (w + 1) / workers; p < end; ++p) {
      if (!on_grid[p]) continue;
      GridPoint c;
      c.p = p;
      c.q = q[p];
      const int i = node(xyz, p, 0, c.fx);
      c.j = node(xyz, p, 1, c.fy);
      c.k = node(xyz, p, 2, c.fz);
      sorted[next[i]++] = c;
      if (!at_stencils) cells[p] = Cell{i, c.j, c.k, c.fx, c.fy, c.fz};
    }
  });
}

// Cloud-in-cell deposit, split between threads by x-slabs of nodes. A thread reads only the
// points whose stencil reaches its slabs (x index lo-1 .. hi-1), so every node plane i sums the
// charges of index i-1, then those of index i, each in particle order: the same sums in the same
// order whatever the thread count (bitwise the same result as one thread).
void OpenPoissonSolver::Impl::deposit() {
  const size_t points = sorted.size();
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(threads, std::max<size_t>(1, points / 4096)));
  // Slab bounds with about equal point counts (a bunch crowds the middle slabs).
  std::vector<int> bound(workers + 1, g.nx);
  bound[0] = 0;
  {
    size_t cum = 0;
    unsigned w = 1;
    for (int i = 0; i < g.nx && w < workers; ++i) {
      cum += bucket[static_cast<size_t>(i) + 1] - bucket[static_cast<size_t>(i)];
      while (w < workers && cum * workers >= points * w) bound[w++] = i + 1;
    }
  }
  run_workers(workers, [&](unsigned w) {
    const int lo = bound[w], hi = bound[w + 1];
    for (int i = lo; i < hi; ++i)
      for (int j = 0; j < g.ny; ++j) std::memset(rho_row(i, j), 0, sizeof(double) * g.nz);
    for (int i = std::max(lo - 1, 0); i < hi; ++i)
      for (size_t s = bucket[static_cast<size_t>(i)]; s < bucket[static_cast<size_t>(i) + 1]; ++s) {
        const GridPoint& c = sorted[s];
        if (c.q == 0) continue;  // a probe
        const double wx[2] = {1 - c.fx, c.fx}, wy[2] = {1 - c.fy, c.fy}, wz[2] = {1 - c.fz, c.fz};
        for (int a = 0; a < 2; ++a) {
          if (i + a < lo || i + a >= hi) continue;
          const double qa = c.q * wx[a];
          for (int b = 0; b < 2; ++b) {
            const double qab = qa * wy[b];
            double* row = rho_row(i + a, c.j + b) + c.k;
            row[0] += qab * wz[0];
            row[1] += qab * wz[1];
          }
        }
      }
  });
}

// The convolution of rho with the Green's function into phi (see the comment above Impl).
void OpenPoissonSolver::Impl::convolve() {
  const size_t row_bytes = sizeof(fftw_complex) * n2c;
  // Below 2^13 points (a 16^3 grid's transforms take about 0.1 ms) starting threads costs more
  // than it saves, more so on a loaded machine.
  const unsigned fft_threads = static_cast<long>(g.nx) * g.ny * g.nz < (1L << 13) ? 1 : threads;
  parallel_for(static_cast<size_t>(g.nx), fft_threads, [&](size_t i, unsigned) {
    fftw_complex* s = plane(static_cast<int>(i));
    fftw_execute_dft_r2c(rows_r2c, rho_row(static_cast<int>(i), 0), s);
    std::memset(s + static_cast<size_t>(g.ny) * n2c, 0, row_bytes * (n1 - g.ny));
    fftw_execute_dft(planes_fwd, s, s);
  });
  const int gy = g.ny + 1, gz = g.nz + 1;
  parallel_for(static_cast<size_t>(n1), fft_threads, [&](size_t j, unsigned w) {
    fftw_complex* in = work.get() + 2 * w * block;
    fftw_complex* out = in + block;
    for (int i = 0; i < g.nx; ++i) std::memcpy(in + static_cast<size_t>(i) * n2c, plane(i) + j * n2c, row_bytes);
    fftw_execute_dft(columns_fwd, in, out);
    const size_t mj = static_cast<int>(j) <= g.ny ? j : n1 - j;
    for (int i = 0; i < n0; ++i) {
      const size_t mi = i <= g.nx ? i : n0 - i;
      const double* gr = green.get() + (mi * gy + mj) * gz;
      fftw_complex* o = out + static_cast<size_t>(i) * n2c;
      for (int k = 0; k < n2c; ++k) {
        o[k][0] *= gr[k];
        o[k][1] *= gr[k];
      }
    }
    fftw_execute_dft(columns_bwd, out, out);
    for (int i = 0; i <= g.nx; ++i) std::memcpy(plane(i) + j * n2c, out + static_cast<size_t>(i) * n2c, row_bytes);
    std::memcpy(plane(g.nx + 1) + j * n2c, out + static_cast<size_t>(n0 - 1) * n2c, row_bytes);
  });
  parallel_for(static_cast<size_t>(g.nx + 2), fft_threads, [&](size_t p, unsigned) {
    fftw_complex* s = plane(static_cast<int>(p));
    double* rows = phi.get() + p * (g.ny + 2) * n2;
    fftw_execute_dft(planes_bwd, s, s);
    fftw_execute_dft_c2r(rows_c2r, s, rows);
    fftw_execute_dft_c2r(row_c2r, s + static_cast<size_t>(n1 - 1) * n2c, rows + static_cast<size_t>(g.ny + 1) * n2);
  });
}

// E = -grad phi by centred differences at every node of the charge's octant. The convolution is
// exact (aperiodic) on indices -1..n of each axis, so the neighbours of the octant's edge nodes
// are right too (index -1 is 2n-1 on the doubled grid).
void OpenPoissonSolver::Impl::field_on_nodes() {
  efield.resize(static_cast<size_t>(g.nx) * g.ny * g.nz * 3);
  const double sx = -0.5 / h[0], sy = -0.5 / h[1], sz = -0.5 / h[2];
  // About 2 ns a node: threads pay only from about 64^3 nodes on.
  const unsigned workers = static_cast<long>(g.nx) * g.ny * g.nz < (1L << 17) ? 1 : threads;
  parallel_for(static_cast<size_t>(g.nx), workers, [&](size_t i2, unsigned) {
    const int i = static_cast<int>(i2);
    for (int j = 0; j < g.ny; ++j) {
      double* e = efield.data() + (static_cast<size_t>(i) * g.ny + j) * g.nz * 3;
      const double* c = phi_row(i, j);
      const double* xp = phi_row(i + 1, j);
      const double* xm = phi_row(i - 1, j);
      const double* yp = phi_row(i, j + 1);
      const double* ym = phi_row(i, j - 1);
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
// assignment both ways is what cancels the self-force and conserves momentum). Many points read
// E from every node, in particle order, so that E is written in order (in x order the scattered
// writes took twice the time); few points on a large grid difference the potential at their
// stencils' nodes themselves, by field_on_nodes' expressions (the same numbers), taken in x
// order so that the potential is read plane by plane. Either way, a point's sum is the same
// whichever thread computes it.
void OpenPoissonSolver::Impl::gather(size_t n, double* E) {
  const size_t points = sorted.size();
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(threads, std::max<size_t>(1, points / 4096)));
  if (!at_stencils) {
    field_on_nodes();
    run_workers(workers, [&](unsigned w) {
      for (size_t p = n * w / workers, end = n * (w + 1) / workers; p < end; ++p) {
        if (!on_grid[p]) continue;
        const Cell& c = cells[p];
        const int i = c.i, j = c.j, k = c.k;
        const double wx[2] = {1 - c.fx, c.fx}, wy[2] = {1 - c.fy, c.fy}, wz[2] = {1 - c.fz, c.fz};
        double ex = 0, ey = 0, ez = 0;
        for (int a = 0; a < 2; ++a)
          for (int b = 0; b < 2; ++b) {
            const double wab = wx[a] * wy[b];
            const double* e = efield.data() + ((static_cast<size_t>(i + a) * g.ny + j + b) * g.nz + k) * 3;
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
    return;
  }
  const double sx = -0.5 / h[0], sy = -0.5 / h[1], sz = -0.5 / h[2];
  run_workers(workers, [&](unsigned w) {
    for (int i = 0; i < g.nx - 1; ++i)
      for (size_t s = std::max(bucket[static_cast<size_t>(i)], points * w / workers),
                  end = std::min(bucket[static_cast<size_t>(i) + 1], points * (w + 1) / workers);
           s < end; ++s) {
        const GridPoint& c = sorted[s];
        const double wx[2] = {1 - c.fx, c.fx}, wy[2] = {1 - c.fy, c.fy}, wz[2] = {1 - c.fz, c.fz};
        double ex = 0, ey = 0, ez = 0;
        for (int a = 0; a < 2; ++a)
          for (int b = 0; b < 2; ++b) {
            const double wab = wx[a] * wy[b];
            const int x = i + a, y = c.j + b;
            const double* cr = phi_row(x, y);
            const double* xp = phi_row(x + 1, y);
            const double* xm = phi_row(x - 1, y);
            const double* yp = phi_row(x, y + 1);
            const double* ym = phi_row(x, y - 1);
            for (int d = 0; d < 2; ++d) {
              const int k = c.k + d, km = k == 0 ? n2 - 1 : k - 1;
              const double wt = wab * wz[d];
              ex += wt * (sx * (xp[k] - xm[k]));
              ey += wt * (sy * (yp[k] - ym[k]));
              ez += wt * (sz * (cr[k + 1] - cr[km]));
            }
          }
        E[3 * c.p] = ex;
        E[3 * c.p + 1] = ey;
        E[3 * c.p + 2] = ez;
      }
  });
}

void OpenPoissonSolver::solve(size_t n, const double* xyz, const double* q, double* E) {
  Impl& m = *impl_;
  const auto t0 = Clock::now();
  ++m.times.solves;
  // The passes over every point are split in chunks between threads where their answer cannot
  // depend on the split (a first index, "any", min and max). With 1e5 points a solve is bound by
  // memory traffic, so the first pass also takes the box of all points (the grid's box unless the
  // halo cut leaves some out), and E is written once, not cleared first.
  const unsigned chunks = static_cast<unsigned>(std::min<size_t>(m.threads, std::max<size_t>(1, n / 4096)));
  std::vector<size_t> first_bad(chunks, n);
  std::vector<unsigned char> charged(chunks, 0);
  using Box = std::array<double, 6>;  // lower x, y, z, then upper x, y, z [m]
  const Box empty{{HUGE_VAL, HUGE_VAL, HUGE_VAL, -HUGE_VAL, -HUGE_VAL, -HUGE_VAL}};
  std::vector<Box> box(chunks, empty);
  auto extend = [&](Box& b, size_t p) {
    for (int a = 0; a < 3; ++a) {
      b[a] = std::min(b[a], xyz[3 * p + a]);
      b[3 + a] = std::max(b[3 + a], xyz[3 * p + a]);
    }
  };
  run_workers(chunks, [&](unsigned w) {
    for (size_t p = n * w / chunks, end = n * (w + 1) / chunks; p < end; ++p) {
      if (!std::isfinite(xyz[3 * p]) || !std::isfinite(xyz[3 * p + 1]) || !std::isfinite(xyz[3 * p + 2]) ||
          !std::isfinite(q[p])) {
        first_bad[w] = p;
        return;
      }
      if (q[p] != 0) charged[w] = 1;
      extend(box[w], p);
    }
  });
  const size_t bad = *std::min_element(first_bad.begin(), first_bad.end());
  if (bad < n) throw Error(ExitCode::data, "space charge: " + point_text(bad, xyz, q) + " is not finite");
  m.outside = 0;
  if (n == 0) return;

  // Halo cut: mean and rms weighted by |q| (every point alike when none carries charge).
  m.on_grid.assign(n, 1);
  const bool any_charge = std::find(charged.begin(), charged.end(), 1) != charged.end();
  auto weight = [&](size_t p) { return any_charge ? std::fabs(q[p]) : 1.0; };
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
  if (m.outside > 0)
    run_workers(chunks, [&](unsigned w) {
      box[w] = empty;
      for (size_t p = n * w / chunks, end = n * (w + 1) / chunks; p < end; ++p)
        if (m.on_grid[p]) extend(box[w], p);
    });
  double lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (const auto& b : box)
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], b[a]);
      hi[a] = std::max(hi[a], b[3 + a]);
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
    for (size_t p = 0; p < n; ++p)
      if (!m.on_grid[p]) std::fill(E + 3 * p, E + 3 * p + 3, 0.0);
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
    std::fill(E, E + 3 * n, 0.0);
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
  for (int a = 0; a < 3; ++a) m.origin[a] = 0.5 * (lo[a] + hi[a]) - 0.5 * (na[a] - 1) * m.h[a];

  m.assign(n, xyz, q);
  m.deposit();
  m.times.deposit_s += seconds_since(t0);

  if (rebuild) m.build_green();

  auto t1 = Clock::now();
  m.convolve();
  m.times.fft_s += seconds_since(t1);

  t1 = Clock::now();
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
