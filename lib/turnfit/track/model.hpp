// Everything a tracker needs from a machine: total magnetic field, gaps, probes, particle.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "turnfit/field/field_map.hpp"
#include "turnfit/field/opal_map.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/rf/cavity.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

namespace turnfit {

/// A straight radial wire probe (paper Eq. 1): points s (cos phi, sin phi) + a (sin phi, -cos phi)
/// for s in [s_min, s_max]. Its readout is zeroed at its nominal place: a probe that sits
/// `shift` further out reads every turn `shift` lower (recorded = true - shift).
struct ProbeLine {
  std::string name;
  double sin_phi = 0, cos_phi = 1, phi_rad = 0;
  double a_m = 0, s_min_m = 0, s_max_m = 0, shift_m = 0, step_m = 0.5e-3;
  /// Signed distance from the probe line [m]; positive before a crossing.
  double distance(double x, double y) const { return x * sin_phi - y * cos_phi - a_m; }
  /// Position along the probe [m].
  double along(double x, double y) const { return x * cos_phi + y * sin_phi; }
  /// Azimuth where the circle of radius r meets the probe line (NaN if r < |a|).
  double crossing_azimuth(double r_m) const;
};

/// The machine as trackers see it.
struct TrackModel {
  PolarFieldMap map;                 ///< main field (already scaled)
  /// If set, the main field is sampled as OPAL-cycl does (bilinear, from `map`'s grid values)
  /// instead of by `map`'s spline.
  std::optional<OpalBilinearMap> opal_map;
  std::vector<TrimCoilField> coils;  ///< trim coils
  double threshold_T = 0;            ///< trim coil threshold
  std::vector<Gap> gaps;
  std::vector<ProbeLine> probes;
  double mass_MeV = 938.27208816;
  double charge_e = 1;
  double rf_MHz = 0;                 ///< main RF frequency (phase reference of the turn records)
  int harmonic = 1;

  /// Total bending field b (> 0 bends a positive particle moving with increasing azimuth;
  /// physical Bz = -b) and its derivatives; false outside the field map.
  bool field(double r_m, double theta_rad, FieldSample& out) const;
};

/// How the model is built.
struct ModelOptions {
  /// OPAL-cycl 2022.1's field: bilinear interpolation in (r, theta) of Bz, with dBz/dr and
  /// dBz/dtheta from 5-point stencils (one-sided at the edges), instead of the bicubic spline.
  bool opal_map = false;
};

/// Builds the model of a machine: reads the map, the cavity profiles and trim coil tables.
TrackModel make_track_model(const Machine& m, const ModelOptions& opt = {});

}  // namespace turnfit
