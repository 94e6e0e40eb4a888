// Tracking models built in code for tests: analytic fields on polar grids.
#pragma once

#include <cmath>
#include <string>

#include "turnfit/track/model.hpp"

namespace turnfit::test {

/// A uniform field B [T] from 0.2 to 4 m on 1 deg cells, with RF at f_MHz and harmonic 1 (so
/// the rk4 time step is 1/(steps_per_turn f)).
inline TrackModel uniform_model(double B, double f_MHz = 10) {
  PolarGrid g;
  g.r_min_mm = 200;
  g.dr_mm = 20;
  g.nr = 191;
  g.ntheta = 90;
  g.symmetry = 4;
  TrackModel m;
  m.map = make_field_map(g, [&](double, double) { return B; }, "uniform");
  m.rf_MHz = f_MHz;
  m.harmonic = 1;
  return m;
}

/// A probe line at azimuth phi [deg], offset a [mm], moved outwards by shift [mm], over
/// s in [s_min, s_max] [mm] (paper Eq. 1).
inline ProbeLine probe(const std::string& name, double phi_deg, double a_mm = 0, double shift_mm = 0,
                       double s_min_mm = 200, double s_max_mm = 5000) {
  constexpr double kDeg = 3.14159265358979323846 / 180;
  ProbeLine p;
  p.name = name;
  p.phi_rad = phi_deg * kDeg;
  p.sin_phi = std::sin(p.phi_rad);
  p.cos_phi = std::cos(p.phi_rad);
  p.a_m = a_mm * 1e-3;
  p.shift_m = shift_mm * 1e-3;
  p.s_min_m = s_min_mm * 1e-3;
  p.s_max_m = s_max_mm * 1e-3;
  return p;
}

}  // namespace turnfit::test
