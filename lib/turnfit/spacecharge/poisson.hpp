// Space charge: the electric field of a bunch's point charges in free space, by particle-in-cell.
#pragma once

#include <array>
#include <cstddef>
#include <memory>
#include <string>

namespace turnfit::sc {

/// Vacuum permittivity [F/m] (CODATA 2018); physics/particle.hpp has no electric constants yet.
inline constexpr double kEpsilon0_F_m = 8.8541878128e-12;

/// Grid points per axis of the solver's grid (before Hockney's doubling).
struct GridSize { int nx = 32, ny = 32, nz = 32; };

/// Parses "32x32x32" or "32" (every axis); throws turnfit::Error with EX_USAGE naming the text
/// for anything else; each axis must be 8..512 (fewer points cannot resolve a bunch).
GridSize parse_grid(const std::string& text);

/// Where the solver's time went, summed over solves [s].
struct SolveTimes { double deposit_s = 0, fft_s = 0, gather_s = 0, green_s = 0; long solves = 0, green_builds = 0; };

/// Electric field of point charges with open boundaries (free space), by particle-in-cell:
/// cloud-in-cell deposit, Hockney's doubled-grid FFT convolution with the integrated Green's
/// function, E = -grad phi by centred differences on the grid, cloud-in-cell gather with the
/// deposit's weights (no self-force, total momentum conserved: the kernel is antisymmetric).
/// Results are bitwise the same for every thread count.
class OpenPoissonSolver {
 public:
  /// A solver for grid `g` (each axis 8..512, at most 2^24 points in all: EX_USAGE otherwise)
  /// on `threads` threads (0: every hardware thread). Plans the FFTs once, here.
  explicit OpenPoissonSolver(GridSize g, unsigned threads = 1);
  /// Frees the FFT plans and arrays.
  ~OpenPoissonSolver();
  OpenPoissonSolver(const OpenPoissonSolver&) = delete;
  OpenPoissonSolver& operator=(const OpenPoissonSolver&) = delete;

  /// Field E [V/m] at each of n points xyz[3i..3i+2] [m] of the charges q[i] [C] at the same
  /// points (q = 0: a probe point that feels the field and sets the grid's extent but carries no
  /// charge). Writes E[3i..3i+2]. Points beyond `halo_sigma` rms from the charge-weighted mean
  /// along an axis (0: none) are left out of the grid and feel the monopole field of the charge
  /// on the grid (a far halo particle must not stretch the grid and wash out the core); their
  /// own charge is left out of every field. A non-finite coordinate or charge throws turnfit::Error (EX_DATAERR) naming the point.
  void solve(size_t n, const double* xyz, const double* q, double* E);
  /// Halo cut in rms of the charge-weighted distribution per axis (0: every point on the grid).
  /// The mean and rms are those of the points kept so far, recomputed until no more leave (at
  /// most 3 passes), so that one far outlier among few points cannot hide in the rms it inflates.
  double halo_sigma = 0;
  /// Points left out of the grid by the last solve.
  size_t outside() const;
  /// Grid spacing [m] of the last solve, per axis (0 before the first solve with an extent).
  std::array<double, 3> spacing() const;
  /// Where the time went, summed over every solve.
  const SolveTimes& times() const;
  /// The grid this solver was made for.
  GridSize grid() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Reference: E [V/m] at each point from every other point's charge by the direct Coulomb sum
/// (O(n^2)), with Plummer softening `soft_m` (|r|^2 -> |r|^2 + soft^2). Deterministic. Points
/// at the same place as the field point (with no softening) add nothing rather than infinity.
void direct_field(size_t n, const double* xyz, const double* q, double* E, double soft_m = 0);

/// Cell average of 1/r [1/m] over the cell of spacings h [m] centred at offset
/// (i hx, j hy, k hz) from the origin: the integrated Green's function of the solver before its
/// 1/(4 pi eps0), exposed for tests (finite everywhere, also at i = j = k = 0).
double integrated_green(int i, int j, int k, const std::array<double, 3>& h_m);

}  // namespace turnfit::sc
