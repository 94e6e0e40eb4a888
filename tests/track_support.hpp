// Tracking models built in code for tests: analytic fields on polar grids.
#pragma once

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

}  // namespace turnfit::test
