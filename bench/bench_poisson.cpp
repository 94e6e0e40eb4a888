// Benchmark: the space-charge Poisson solver's accuracy against analytic fields and its time per solve, by stage.
// Figures: the uniform sphere's errors against grid and particle count; a Gaussian's core
// against grid (the grid's smoothing); time per solve split into deposit/FFT/gather/Green's
// function at 32^3 and 64^3 with 1e5 particles on 1 and 2 threads (ratios to the 1-thread run),
// and at 32^3 with 2000 particles (a space-charge run's usual bunch);
// the direct O(n^2) sum against the solver for 4000 particles (ratio of times, rms difference).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "turnfit/spacecharge/poisson.hpp"
#include "../tests/poisson_points.hpp"

using namespace turnfit::sc;
using namespace turnfit::sc::testing;
using Clock = std::chrono::steady_clock;

namespace {

// Radial errors at 60 probes out to 2R: worst inside (0.3..0.8 R, relative), outside
// (1.2..2 R, relative), near the centre (relative to E(R)), and rms over all.
void sphere_row(int grid, int lattice) {
  const double R = 1e-3, Q = 1e-9;
  Points p = lattice_ellipsoid(lattice, R, R, R, Q);
  const size_t charges = p.size();
  for (int k = 0; k < 60; ++k) {
    const double r = (0.05 + k * 1.95 / 59) * R;
    const auto d = direction(static_cast<size_t>(k));
    p.add(r * d[0], r * d[1], r * d[2], 0);
  }
  OpenPoissonSolver s({grid, grid, grid});
  std::vector<double> e(3 * p.size());
  s.solve(p.size(), p.xyz.data(), p.q.data(), e.data());
  const double eR = kCoulomb * Q / (R * R);
  double inside = 0, outside = 0, centre = 0, sum2 = 0;
  for (size_t i = charges; i < p.size(); ++i) {
    const double* x = &p.xyz[3 * i];
    const double r = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    const double er = (e[3 * i] * x[0] + e[3 * i + 1] * x[1] + e[3 * i + 2] * x[2]) / r;
    const double exact = r < R ? eR * r / R : kCoulomb * Q / (r * r);
    const double rel = std::fabs(er - exact) / exact;
    if (r < 0.3 * R) centre = std::max(centre, std::fabs(er - exact) / eR);
    else if (r < 0.8 * R) inside = std::max(inside, rel);
    else if (r > 1.2 * R) outside = std::max(outside, rel);
    const double rs = std::fabs(er - exact) / std::max(exact, 0.3 * eR);
    sum2 += rs * rs;
  }
  std::printf("  %4d^3  %7zu  %8.3f  %8.3f  %8.3f  %8.3f\n", grid, charges, 100 * inside, 100 * outside, 100 * centre,
              100 * std::sqrt(sum2 / 60));
}

// Core of a spherical Gaussian (100 k quiet particles): mean signed radial error at r <= 1.5 sigma.
void gaussian_row(int grid, const Points& base, double s, double Q) {
  Points p = base;
  const size_t charges = p.size();
  for (int k = 0; k < 30; ++k) {
    const double r = (0.3 + k * 1.2 / 29) * s;
    const auto d = direction(static_cast<size_t>(k));
    p.add(r * d[0], r * d[1], r * d[2], 0);
  }
  OpenPoissonSolver solver({grid, grid, grid});
  std::vector<double> e(3 * p.size());
  solver.solve(p.size(), p.xyz.data(), p.q.data(), e.data());
  double mean = 0;
  for (size_t i = charges; i < p.size(); ++i) {
    const double* x = &p.xyz[3 * i];
    const double r = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    const double er = (e[3 * i] * x[0] + e[3 * i + 1] * x[1] + e[3 * i + 2] * x[2]) / r;
    const double exact = kCoulomb * Q / (r * r) *
                         (std::erf(r / (std::sqrt(2.0) * s)) - std::sqrt(2 / kPi) * (r / s) * std::exp(-r * r / (2 * s * s)));
    mean += (er / exact - 1) / 30;
  }
  const double h = solver.spacing()[0] / s;
  std::printf("  %4d^3  %6.3f  %+8.2f  %+8.2f\n", grid, h, 100 * mean, -100 * h * h);
}

struct Timing { double deposit, fft, gather, green, total; };

// Time per solve over `solves` solves of a bunch that drifts a little each time (the Green's
// function is built once: its time is per build, not per solve).
Timing time_solves(int grid, unsigned threads, const Points& base, int solves) {
  OpenPoissonSolver s({grid, grid, grid}, threads);
  Points p = base;
  std::vector<double> e(3 * p.size());
  const auto t0 = Clock::now();
  for (int k = 0; k < solves; ++k) {
    for (size_t i = 0; i < p.size(); ++i) p.xyz[3 * i + 2] = base.xyz[3 * i + 2] + 1e-5 * k;
    s.solve(p.size(), p.xyz.data(), p.q.data(), e.data());
  }
  const double total = std::chrono::duration<double>(Clock::now() - t0).count();
  const SolveTimes& t = s.times();
  return {t.deposit_s / solves, t.fft_s / solves, t.gather_s / solves, t.green_s / std::max(1L, t.green_builds),
          (total - t.green_s) / solves};
}

}  // namespace

int main() {
  std::printf("bench_poisson: open-boundary PIC Poisson solver (CIC, Hockney FFT, integrated Green's function)\n\n");

  std::printf("Uniform sphere, radius R, 60 probes to 2R (they set the grid), errors in %%:\n");
  std::printf("  grid    particles   inside   outside  centre/E(R)  rms\n");
  for (int grid : {16, 32, 64})
    for (int lattice : {27, 58}) sphere_row(grid, lattice);

  std::printf("\nSpherical Gaussian core (100 k quiet particles, probes 0.3..1.5 sigma): mean radial error %%\n");
  std::printf("against the grid's smoothing estimate -(h/sigma)^2:\n");
  std::printf("  grid    h/sigma   mean err   -(h/s)^2\n");
  {
    const double s = 1e-3, Q = 1e-9;
    const Points g = quiet_gaussian(100000, s, s, s, Q);
    for (int grid : {32, 48, 64, 96}) gaussian_row(grid, g, s, Q);
  }

  std::printf("\nTime per solve [ms], 1e5 particles of a Gaussian bunch (1, 1.5, 4 mm), 20 solves;\n");
  std::printf("green: per build (once per run here); ratio: total against the 1-thread run of that grid\n");
  std::printf("  grid  threads  deposit     fft  gather   total   green  ratio\n");
  const Points bunch = random_gaussian(100000, 1e-3, 1.5e-3, 4e-3, 1e-9, 1);
  for (int grid : {32, 64}) {
    double reference = 0;
    for (unsigned threads : {1u, 2u}) {
      const Timing t = time_solves(grid, threads, bunch, 20);
      if (threads == 1) reference = t.total;
      std::printf("  %4d  %7u  %7.2f %7.2f %7.2f %7.2f %7.1f  %5.2f\n", grid, threads, 1e3 * t.deposit, 1e3 * t.fft,
                  1e3 * t.gather, 1e3 * t.total, 1e3 * t.green, t.total / reference);
    }
  }
  {
    // The size of ring8's space-charge runs: the FFT and the gather's grid field dominate.
    const Points small = random_gaussian(2000, 1e-3, 1.5e-3, 4e-3, 1e-9, 2);
    double reference = 0;
    for (unsigned threads : {1u, 2u}) {
      const Timing t = time_solves(32, threads, small, 200);
      if (threads == 1) reference = t.total;
      std::printf("  %4d  %7u  %7.2f %7.2f %7.2f %7.2f %7.1f  %5.2f  (2000 particles)\n", 32, threads,
                  1e3 * t.deposit, 1e3 * t.fft, 1e3 * t.gather, 1e3 * t.total, 1e3 * t.green, t.total / reference);
    }
  }
  {
    const Timing t = time_solves(128, 2, bunch, 3);
    std::printf("  %4d  %7u  %7.2f %7.2f %7.2f %7.2f %7.1f\n", 128, 2u, 1e3 * t.deposit, 1e3 * t.fft, 1e3 * t.gather,
                1e3 * t.total, 1e3 * t.green);
  }

  std::printf("\nDirect O(n^2) sum against PIC, 4000 particles of a Gaussian bunch (1, 1, 2 mm):\n");
  {
    const Points p = random_gaussian(4000, 1e-3, 1e-3, 2e-3, 1e-9, 3);
    std::vector<double> e(3 * p.size()), d(3 * p.size());
    for (int grid : {32, 64}) {
      OpenPoissonSolver s({grid, grid, grid});
      const auto t0 = Clock::now();
      s.solve(p.size(), p.xyz.data(), p.q.data(), e.data());
      const double first = std::chrono::duration<double>(Clock::now() - t0).count();
      const auto t1 = Clock::now();
      s.solve(p.size(), p.xyz.data(), p.q.data(), e.data());
      const double pic = std::chrono::duration<double>(Clock::now() - t1).count();
      const auto h = s.spacing();
      const auto t2 = Clock::now();
      direct_field(p.size(), p.xyz.data(), p.q.data(), d.data(), std::cbrt(h[0] * h[1] * h[2]));
      const double direct = std::chrono::duration<double>(Clock::now() - t2).count();
      double diff2 = 0, field2 = 0;
      for (size_t i = 0; i < e.size(); ++i) {
        diff2 += (e[i] - d[i]) * (e[i] - d[i]);
        field2 += d[i] * d[i];
      }
      std::printf("  %d^3: PIC %.2f ms (first solve with its Green's function %.1f ms), direct %.1f ms, direct/PIC %.1f;"
                  " rms difference %.2f %% of the rms field (softening one cell)\n",
                  grid, 1e3 * pic, 1e3 * first, 1e3 * direct, direct / pic, 100 * std::sqrt(diff2 / field2));
    }
  }
  return 0;
}
