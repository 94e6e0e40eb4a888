// Point sets for the Poisson solver's tests and benchmark (tests/unit/test_poisson.cpp,
// bench/bench_poisson.cpp): quiet lattices and Gaussians, random Gaussians, probe directions.
#pragma once

#include <array>
#include <cmath>
#include <random>
#include <vector>

#include "turnfit/physics/particle.hpp"
#include "turnfit/spacecharge/poisson.hpp"

namespace turnfit::sc::testing {

using turnfit::kPi;
inline const double kCoulomb = 1 / (4 * kPi * kEpsilon0_F_m);  // 1/(4 pi eps0) [m/F]

// Points and charges as the solver takes them, probes (q = 0) appended after the charges.
struct Points {
  std::vector<double> xyz, q;
  size_t size() const { return q.size(); }
  void add(double x, double y, double z, double charge) {
    xyz.insert(xyz.end(), {x, y, z});
    q.push_back(charge);
  }
  std::array<double, 3> at(size_t i) const { return {xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]}; }
};

inline double halton(size_t i, unsigned base) {
  double f = 1, r = 0;
  for (; i > 0; i /= base) {
    f /= base;
    r += f * static_cast<double>(i % base);
  }
  return r;
}

// A quiet start: a cubic lattice of m points across, turned off the grid's axes (a lattice
// aligned with the grid beats against it), keeping the points inside the ellipsoid a, b, c.
inline Points lattice_ellipsoid(int m, double a, double b, double c, double charge) {
  Points p;
  const double ca = std::cos(0.3), sa = std::sin(0.3), cb = std::cos(0.5), sb = std::sin(0.5);
  for (int i = 0; i < m; ++i)
    for (int j = 0; j < m; ++j)
      for (int k = 0; k < m; ++k) {
        const double u = -1 + (i + 0.5) * 2 / m, v = -1 + (j + 0.5) * 2 / m, w = -1 + (k + 0.5) * 2 / m;
        const double u2 = ca * u - sa * v, v2 = sa * u + ca * v;
        const double v3 = cb * v2 - sb * w, w3 = sb * v2 + cb * w;
        if (u2 * u2 + v3 * v3 + w3 * w3 < 1) p.add(a * u2, b * v3, c * w3, 1);
      }
  for (double& q : p.q) q = charge / static_cast<double>(p.size());
  return p;
}

// The standard normal quantile, by bisection of erfc (slow, exact to rounding, test-only).
inline double normal_quantile(double u) {
  double lo = -12, hi = 12;
  for (int it = 0; it < 44; ++it) {  // 24 / 2^44: 1e-12
    const double mid = 0.5 * (lo + hi);
    (0.5 * std::erfc(-mid / std::sqrt(2.0)) < u ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

// A quiet Gaussian: Halton points through the normal quantile on each axis.
inline Points quiet_gaussian(size_t n, double sx, double sy, double sz, double charge) {
  Points p;
  for (size_t i = 1; i <= n; ++i)
    p.add(sx * normal_quantile(halton(i, 2)), sy * normal_quantile(halton(i, 3)),
          sz * normal_quantile(halton(i, 5)), charge / static_cast<double>(n));
  return p;
}

// A random Gaussian (Box-Muller on mt19937_64, whose sequence the standard fixes).
inline Points random_gaussian(size_t n, double sx, double sy, double sz, double charge, unsigned seed) {
  std::mt19937_64 rng(seed);
  auto uniform = [&] { return (static_cast<double>(rng() >> 11) + 0.5) / 9007199254740992.0; };
  auto normal = [&] { return std::sqrt(-2 * std::log(uniform())) * std::cos(2 * kPi * uniform()); };
  Points p;
  for (size_t i = 0; i < n; ++i) {
    const double x = sx * normal(), y = sy * normal(), z = sz * normal();
    p.add(x, y, z, charge / static_cast<double>(n));
  }
  return p;
}

// Probe directions that are no axis or diagonal of the grid (Halton on the sphere).
inline std::array<double, 3> direction(size_t i) {
  const double ct = 2 * halton(i + 1, 7) - 1, ph = 2 * kPi * halton(i + 1, 11);
  const double st = std::sqrt(1 - ct * ct);
  return {st * std::cos(ph), st * std::sin(ph), ct};
}

}  // namespace turnfit::sc::testing
