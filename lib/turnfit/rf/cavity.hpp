// Single-gap RF cavities (OPAL RFCAVITY TYPE="SINGLEGAP"): geometry, radial voltage profile,
// transit-time factor, energy kick and RF magnetic deflection at the gap crossing.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"

namespace turnfit {

/// A radial voltage profile V_n(rho_n) on [0, 1] (OPAL rffield file: a row count, then rows
/// "rho_n V dV/drho_n"), interpolated as a cubic Hermite curve through the given slopes.
class VoltageProfile {
 public:
  /// A flat profile (V_n = 1, dV_n = 0).
  VoltageProfile() = default;
  /// Reads an OPAL-style profile file; errors name the file and line.
  static VoltageProfile read(const std::string& path);
  /// Parses profile text (name for messages).
  static VoltageProfile parse(const std::string& text, const std::string& name);
  /// V_n and dV_n/drho_n at rho_n in [0, 1].
  double eval(double rho_n, double& dv) const;

 private:
  std::vector<double> x_, v_, d_;
};

/// What one gap crossing did.
struct GapKick {
  bool active = false;   ///< inside the gap's radial extent
  double rho_n = 0;      ///< normalized position along the gap
  double phase_deg = 0;  ///< RF phase at the crossing, 2 pi f t - PHI0
  double transit = 1;    ///< transit-time factor T
  double de_MeV = 0;     ///< energy gain
  double deflection_rad = 0;  ///< rotation of the transverse momentum by the RF magnetic field
  bool stopped = false;  ///< the gap decelerated the particle to rest (a loss)
};

/// How gap kicks follow OPAL.
enum class GapPhysics {
  turnfit,  ///< RF magnetic deflection from Faraday's law: delta = dV/drho sin(phi) / (omega B rho)
  opal,     ///< OPAL 2022.1's formula, which divides the deflection by a further 2 pi
};

/// One single-gap cavity. The gap is the line x sin(A) - y cos(A) = PDIS (A the angle); the
/// particle, circulating with increasing azimuth, crosses it from positive to negative distance.
class Gap {
 public:
  /// Builds the gap from its description; rf_MHz is the machine's RF frequency.
  Gap(const Cavity& c, double rf_MHz, VoltageProfile profile);
  /// Signed distance of (x, y) from the gap line [m], measured along the straight line's
  /// normal; positive before the crossing. A bowed gap (set_bow) adds its bow at the point's
  /// position along the chord, so the zero set is the bowed line.
  double distance(double x_m, double y_m) const {
    const double d = x_m * sin_a_ - y_m * cos_a_ - pdis_m_;
    return bow_m_ == 0 ? d : d + bow(x_m * cos_a_ + y_m * sin_a_);
  }
  /// Azimuth [rad, in (-pi, pi]] where the circle of radius r meets the gap line (bowed, if
  /// set) on the gap's side of the machine; NaN if r < PDIS.
  double crossing_azimuth(double r_m) const;
  /// Bows the gap line (machine effect `gap-bow`): the middle of [rmin, rmax] moves by
  /// `sagitta_m` along the gap normal (> 0: downstream, the direction the particle crosses in),
  /// the ends stay, and the line between is the parabola through these three points. Kicks
  /// then act along the local normal of the bowed line.
  void set_bow(double sagitta_m);
  /// Tilts the voltage profile (machine effect `voltage-tilt`): V_n(rho_n) becomes
  /// V_n(rho_n) (1 + slope (rho_n - pivot)), and its slope (the RF deflection) follows.
  void set_tilt(double slope, double pivot_rho_n);
  /// Sagitta of the bow [m] (0: straight).
  double sagitta_m() const { return bow_m_; }
  /// Displacement of the bowed line along the normal at chord position rho [m] (0 beyond the
  /// ends), and its slope d(bow)/d(rho).
  double bow(double rho_m) const;
  double bow_slope(double rho_m) const;
  /// Applies the kick at a point of the gap line: updates the momentum (px, py, pz in units of
  /// m c, i.e. beta gamma components) and returns what happened. t_s is the time since start.
  GapKick kick(double x_m, double y_m, double t_s, double mass_MeV, double charge_e, GapPhysics physics,
               double& px, double& py, double pz) const;
  /// The cavity's name.
  const std::string& name() const { return name_; }
  /// RF frequency of this cavity [Hz].
  double frequency_Hz() const { return freq_hz_; }

 private:
  std::string name_;
  double sin_a_, cos_a_, angle_rad_, pdis_m_;
  double rmin_m_, rmax_m_, volt_MV_, freq_hz_, phi0_rad_, gap_m_;
  double bow_m_ = 0, bow_mid_m_ = 0, bow_inv_half_ = 0;  // gap-bow: sagitta, chord middle, 1/half chord
  double tilt_ = 0, tilt_pivot_ = 0.5;                   // voltage-tilt
  VoltageProfile profile_;
};

/// Builds the machine's gaps, reading each profile file (EX_NOINPUT / EX_DATAERR on failure).
/// `profiles`, when given, holds profiles already read, by resolved path: those are not read again.
std::vector<Gap> make_gaps(const Machine& m, const std::map<std::string, VoltageProfile>* profiles = nullptr);

}  // namespace turnfit
