// Everything a tracker needs from a machine: total magnetic field, gaps, probes, particle.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "turnfit/field/field_map.hpp"
#include "turnfit/field/opal_map.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/physics/particle.hpp"
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
  /// A probe-offset effect moved the probe without its readout knowing: phi, a and shift
  /// above are where it is, a_read_m and shift_read_m what the readout assumes (the machine
  /// file's values), and recorded radii convert the reading s - shift with the latter.
  bool hidden_offset = false;
  double a_read_m = 0, shift_read_m = 0;
  /// turns.csv's r [m] of a crossing at radius r_m, position s_m along the line: the true
  /// radius minus the shift, or for a hidden offset the radius the readout's geometry gives
  /// its reading, hypot(s - shift + shift_read, a_read) - shift_read (the same number when
  /// nothing is hidden).
  double recorded_r(double r_m, double s_m) const {
    if (!hidden_offset) return r_m - shift_m;
    return std::hypot(s_m - shift_m + shift_read_m, a_read_m) - shift_read_m;
  }
};

/// Field effects of the machine file (`field-harmonic`, `sector-strength`) on top of the map
/// and the trim coils. Filled by apply_effects; `active` false keeps the field path as it was.
struct FieldEffects {
  /// b += amplitude g(r) cos(n (theta - phase)), g(r) = exp(-(r - r0)^2 inv_width2 / 2).
  struct Harmonic {
    int n = 1;
    double amplitude_T = 0, phase_rad = 0, r0_m = 0;
    double inv_width2 = 0;  ///< 1 / width^2 [1/m^2]; 0: g = 1 at every radius
  };
  bool active = false;
  std::vector<Harmonic> harmonics;
  /// Relative strength change of each sector magnet (index k - 1 for sector k); empty: none.
  std::vector<double> sector_relative;
  double pitch_rad = 0;            ///< 2 pi / sector count
  double half_transition_rad = 0;  ///< half width of the switch between neighbouring sectors
  double inv_pitch_rad = 0, inv_half_transition_rad = 0;  ///< their inverses (set with them)
  /// Main-field factor 1 + sum_k relative_k w_k(theta) and its theta derivative; the windows w_k
  /// add up to 1 at every azimuth.
  double sector_factor(double theta_rad, double& dfactor_dth) const;
};

// (Inline: the fast steppers call it at every field sample of a machine with sector-strength.)
inline double FieldEffects::sector_factor(double th, double& dfactor) const {
  dfactor = 0;
  const int n = static_cast<int>(sector_relative.size());
  if (n == 0) return 1;
  // Sector k is centred on azimuth (k - 1) pitch (the trim coils' convention, trimcoil.cpp):
  // u is the azimuth from the centre of the sector j (0-based) that holds theta.
  // (Multiplications by stored inverses and no integer modulo: this runs at every field
  // sample of a machine with sector-strength effects, inside the step's dependency chain.)
  double a = th + 0.5 * pitch_rad;
  // In [0, 2 pi) (std::fmod is several times slower, and floor without SSE4.1 a dozen
  // instructions: the fast steppers pass azimuths within a turn, which need no floor).
  if (!(a >= 0 && a < 2 * kPi)) {
    a -= 2 * kPi * std::floor(a * (1 / (2 * kPi)));
    if (a >= 2 * kPi) a = 0;
  }
  const int j = std::min(static_cast<int>(a * inv_pitch_rad), n - 1);
  const double u = a - (j + 0.5) * pitch_rad;
  // Within half a switch width of the valley after sector j (u near +pitch/2) or before it
  // (u near -pitch/2) the factor blends the two magnets; elsewhere it is sector j's alone.
  const double h = half_transition_rad, half_pitch = 0.5 * pitch_rad;
  const auto rel = [&](int k) { return sector_relative[static_cast<size_t>(k < 0 ? k + n : k >= n ? k - n : k)]; };
  double lo, hi, x;
  if (u > half_pitch - h) {
    lo = rel(j);
    hi = rel(j + 1);
    x = (u - half_pitch) * inv_half_transition_rad;
  } else if (u < h - half_pitch) {
    lo = rel(j - 1);
    hi = rel(j);
    x = (u + half_pitch) * inv_half_transition_rad;
  } else {
    return 1 + rel(j);
  }
  if (x <= -1) return 1 + lo;
  if (x >= 1) return 1 + hi;
  const double t = 0.5 * (x + 1);
  const double S = t * t * t * (t * (6 * t - 15) + 10);
  dfactor = (hi - lo) * 15 * t * t * (1 - t) * (1 - t) * inv_half_transition_rad;
  return 1 + lo + (hi - lo) * S;
}

/// The machine as trackers see it.
struct TrackModel {
  PolarFieldMap map;                 ///< main field (already scaled)
  /// If set, the main field is sampled as OPAL-cycl does (bilinear, from `map`'s grid values)
  /// instead of by `map`'s spline.
  std::optional<OpalBilinearMap> opal_map;
  std::vector<TrimCoilField> coils;  ///< trim coils
  double threshold_T = 0;            ///< trim coil threshold
  /// The coils that act at every azimuth, summed into one table, and the indices of the
  /// others with a nonzero bmax (evaluated one by one). Built by sum_coils() (make_track_model
  /// calls it); field() uses them while `coils` keeps the size they were built for, and every
  /// coil one by one otherwise (a model built by hand, or coils added later).
  TrimCoilSum coil_sum;
  std::vector<size_t> single_coils;
  /// Coils that share a window (a sector list, a PHIMIN/PHIMAX range) summed into one table
  /// each, with the index of one of them for the window test (ModelOptions::sum_window_coils).
  struct WindowSum {
    size_t window_of;
    TrimCoilSum sum;
  };
  std::vector<WindowSum> window_sums;
  /// (Re)builds coil_sum and single_coils from `coils`: call it after changing a coil in place.
  /// With sum = false every coil stays single (OPAL's compatible model keeps its formulas).
  /// With `windows`, coils that share a window are summed as well (one table and one window
  /// test per window instead of one per coil).
  void sum_coils(bool sum = true, bool windows = true);
  std::vector<Gap> gaps;
  std::vector<ProbeLine> probes;
  double mass_MeV = 938.27208816;
  double charge_e = 1;
  double rf_MHz = 0;                 ///< main RF frequency (phase reference of the turn records)
  int harmonic = 1;
  FieldEffects effects;              ///< field effects (apply_effects)
  /// Azimuth of sector 1's centre line against radius (a spiral turns it), fitted to the phase
  /// of the map's N-th azimuthal harmonic: theta_c = sum_k c_k x^k, x = (r - r_mid) / r_half.
  /// Sector windows (trim coil sector lists, sector-strength) follow it. Zero for a map
  /// without sectors. make_track_model fits it only when `sector_windows` (something uses it).
  std::array<double, 5> sector_centre_coef{};
  double sector_r_mid_m = 0, sector_r_half_m = 1, sector_r_inv_half = 1;  ///< (inv_half = 1 / half)
  bool sector_windows = false;
  /// theta_c(r) [rad] and its slope [rad/m].
  double sector_centre(double r_m, double& dc_dr) const;

  /// Total bending field b (> 0 bends a positive particle moving with increasing azimuth;
  /// physical Bz = -b) and its derivatives; false outside the field map.
  bool field(double r_m, double theta_rad, FieldSample& out) const;
  /// field() given the main field's sample at (r, theta) in `out` (as `map` or `opal_map`
  /// gives it): adds the effects and the coils. The fast steppers sample the main field their
  /// own way (FieldRowTable) and finish here.
  /// What add_to_main needs from the azimuth alone, for many samples at one azimuth: cos and
  /// sin of n (theta - phase) of the first kAzimuthHarmonics field harmonics.
  static constexpr size_t kAzimuthHarmonics = 4;
  struct AzimuthTerms {
    double cos_h[kAzimuthHarmonics], sin_h[kAzimuthHarmonics];
  };
  void azimuth_terms(double theta_rad, AzimuthTerms& t) const;
  /// A particle's places in the summed coil tables (TrimCoilSum::Hint), kept by the fast
  /// steppers from one sample to the next: coil_sum's and the first kHintedWindows window sums'.
  static constexpr size_t kHintedWindows = 8;
  struct CoilHints {
    TrimCoilSum::Hint all, window[kHintedWindows];
  };
  /// With `terms` (azimuth_terms of this theta), the azimuth's part is not computed again; with
  /// `hints`, the coil tables are looked up from them (the same numbers).
  void add_to_main(double r_m, double theta_rad, FieldSample& out, const AzimuthTerms* terms = nullptr,
                   CoilHints* hints = nullptr) const {
    if (effects.active) {
      field_with_effects(r_m, theta_rad, out, terms, hints);
      return;
    }
    if (coils.empty() || no_coil_field()) return;
    const FieldSample main = out;
    double dc = 0;
    const double centre = sector_windows ? sector_centre(r_m, dc) : 0.0;
    add_coils(r_m, theta_rad, main, centre, out, hints);
  }
  /// add_to_main for the n (<= kMaxLanes) particles of a group at one azimuth th: main fields
  /// bz, br, bt at radii r in, totals out, hints[l] each particle's coil hints. The same numbers
  /// as add_to_main lane by lane (the same expressions in the same order), with the spiral's
  /// centre line, the sector factor and the harmonics as loops over the lanes.
  static constexpr int kMaxLanes = 16;
  void add_to_main_lanes(int n, const double* r_m, double theta_rad, double* bz, double* br, double* bt,
                         const AzimuthTerms* terms, CoilHints* const* hints) const;
  /// add_to_main_lanes with a model per lane (an optimizer's designs on one map): lane l gets
  /// models[l]->add_to_main's numbers with terms[l] (its model's azimuth terms, or nullptr),
  /// and a lane whose model adds nothing (main_field_only) is left as it came.
  static void add_to_main_models(int n, const TrackModel* const* models, const double* r_m, double theta_rad,
                                 double* bz, double* br, double* bt, const AzimuthTerms* const* terms,
                                 CoilHints* const* hints);
  /// Whether field() is the main field alone (no effects, no coils).
  bool main_field_only() const { return !effects.active && (coils.empty() || no_coil_field()); }
  /// Whether the coils add nothing (every one at bmax 0, as sum_coils() found them).
  bool no_coil_field() const {
    return summed_for_ == coils.size() && coil_sum.empty() && window_sums.empty() && single_coils.empty();
  }

 private:
  bool field_with_effects(double r_m, double theta_rad, FieldSample& out, const AzimuthTerms* terms,
                          CoilHints* hints) const;
  /// cos and sin of n (theta - phase) of harmonic k, from `terms` when they hold it.
  void harmonic_terms(size_t k, double theta_rad, const AzimuthTerms* terms, double& c, double& sn) const;
  void add_coils(double r_m, double theta_rad, const FieldSample& main, double sector_centre_rad, FieldSample& out,
                 CoilHints* hints) const;
  /// add_coils for the lanes of add_to_main_lanes (each lane's centre line given).
  void add_coils_lanes(int n, const double* r_m, double theta_rad, const double* centre, double* bz, double* br,
                       double* bt, CoilHints* const* hints) const;
  size_t summed_for_ = static_cast<size_t>(-1);  // coils.size() when sum_coils() ran
};

/// Fits TrackModel::sector_centre_coef to a map: per radius the phase of the N-th azimuthal
/// harmonic (the hill centre), unwrapped across radii, then a degree-4 polynomial weighted by
/// the harmonic's amplitude (smooth through measurement noise). All zero without sectors.
void fit_sector_centre(TrackModel& t);

/// How the model is built.
struct ModelOptions {
  /// OPAL-cycl 2022.1's field: bilinear interpolation in (r, theta) of Bz, with dBz/dr and
  /// dBz/dtheta from 5-point stencils (one-sided at the edges), instead of the bicubic spline.
  bool opal_map = false;
  /// Sum the coils that act at every azimuth into one table (TrimCoilSum); off: one by one
  /// (for comparisons; the OPAL-compatible model never sums).
  bool sum_coils = true;
  /// Also sum the coils that share a window (trim coils on some sectors only: ring8's truth puts
  /// nine on the odd sectors); off: those stay one by one, as before issue 17.
  bool sum_window_coils = true;
};

/// What make_track_model reads from disk, read once: an optimizer builds a model per design,
/// and its design variables never change a file name (they set numbers: voltages, phases,
/// coil strengths, probe and injection positions). read_model_files fills it from a machine.
struct ModelFiles {
  /// The main field as load_main_field gives it (scaled), and what it was built from.
  std::shared_ptr<const PolarFieldMap> map;
  std::string map_path, map_format;
  int map_symmetry = 0;
  double map_scale = 1;
  std::map<std::string, VoltageProfile> profiles;  ///< cavity profiles by resolved path
  std::map<std::string, CoilTable> coil_tables;  ///< trim coil tables (type table) by resolved path
  /// The machine's trim coils as built and tabulated over the map (their shapes do not depend
  /// on bmax, which a design changes): a model takes a copy instead of tabulating again.
  std::vector<TrimCoilField> coils;
};

/// Reads every file the machine's model needs (EX_NOINPUT / EX_DATAERR naming the file).
ModelFiles read_model_files(const Machine& m);

/// Builds the model of a machine: reads the map, the cavity profiles and trim coil tables,
/// then applies the machine's effects (all but injection-offset, which acts on the start:
/// effective_injection in tracker.hpp). With `files`, takes what they hold instead of reading
/// it again (a file the machine names that `files` lacks, or a main field with another path,
/// format, symmetry or scale, is still read).
TrackModel make_track_model(const Machine& m, const ModelOptions& opt = {}, const ModelFiles* files = nullptr);

/// Applies machine effects to a model built without them: field harmonics and sector strengths
/// to the field, trimcoil-sectors to the coils (rebuilt, and tabulated unless opt.opal_map),
/// gap-bow and voltage-tilt to the gaps, probe-offset to the probes (turnfit-machine(5),
/// "EFFECTS"). Elements are found by name; a sector outside the map's sector count, or an
/// element the model lacks, is EX_DATAERR naming `file` and the effect's JSON path.
void apply_effects(TrackModel& t, const Effects& fx, const std::string& file = "<machine>",
                   const ModelOptions& opt = {});

/// The effects an OPAL-cycl 2022.1 input cannot state as element parameters, one line each
/// ("gap-bow (/effects/2): ..." saying what OPAL would need), in the order of the `effects`
/// array. probe-offset, injection-offset and trimcoil-sectors map onto PROBE, RINIT/PRINIT/
/// PHIINIT and per-sector PHIMIN/PHIMAX, so they are not listed.
std::vector<std::string> effects_without_opal_input(const Effects& fx);

}  // namespace turnfit
