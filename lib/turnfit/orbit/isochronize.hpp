// Isochronization of an analytic sector field: the hill-field profile is adjusted until the
// revolution frequency of the equilibrium orbits equals f_rf / h over an energy range.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "turnfit/field/sector_field.hpp"
#include "turnfit/orbit/closed_orbit.hpp"

namespace turnfit {

/// How the hill field is adjusted.
struct IsochronizeSettings {
  std::vector<double> energies_MeV;  ///< where f_rev must equal f_rf / h
  double tolerance = 1e-5;           ///< goal: max |f_rev h / f_rf - 1| over the energies
  int max_iterations = 30;           ///< Gauss-Newton iterations before giving up
  /// Spacing of the hill-field nodes [mm] over the spec's grid (0: keep the spec's nodes).
  double node_spacing_mm = 0;
  /// Start from the hill field of the ideal isochronous mean field, B_hill(r) =
  /// gamma(r) B_0 / <S>(r) with B_0 = m omega / q, instead of the spec's hill table.
  bool start_from_mean_field = false;
  /// Weight of the smoothness penalty (second differences of each correction, relative to
  /// the frequency residuals): it fixes nodes no orbit samples and keeps corrections from
  /// putting wiggles shorter than an orbit's scalloping into the field.
  double smoothing = 1e-3;
};

/// One Gauss-Newton iteration, for the report.
struct IsochronizeStep {
  int iteration = 0;
  double max_rel = 0;        ///< max |f_rev h / f_rf - 1| after the step
  double rms_rel = 0;        ///< rms of the same
  double max_slip_deg = 0;   ///< max |RF phase slip per turn| [deg]
  double lambda = 0;         ///< Levenberg-Marquardt damping used
};

/// The isochronized field and how it got there.
struct IsochronizeResult {
  SectorFieldSpec spec;                  ///< the spec with the adjusted hill table
  std::vector<IsochronizeStep> history;  ///< one entry per accepted iteration (0: the start)
  std::vector<OrbitRow> rows;            ///< the final orbits at the energies
  bool converged = false;                ///< max_rel <= tolerance
};

/// Adjusts spec.hill_T so that every closed orbit at the energies revolves at f_rf / h
/// (settings.harmonic and settings.rf_MHz must be set). Levenberg-Marquardt on the hill nodes
/// with a finite-difference Jacobian of the orbit frequencies. EX_USAGE for missing RF or
/// energies; EX_DATAERR when the start has no closed orbit at some energy. `log` (may be empty)
/// receives one line per iteration.
IsochronizeResult isochronize(const SectorFieldSpec& spec, const OrbitSettings& settings,
                              const IsochronizeSettings& iso, unsigned threads,
                              const std::function<void(const std::string&)>& log = {});

/// The hill field of the ideal isochronous mean field at r [T]: gamma(r) B_0 divided by the
/// azimuthal mean of the sector shape, B_0 = m omega / q, omega = 2 pi f_rf / h
/// (gamma(r) = 1 / sqrt(1 - (omega r / c)^2): the classical isochronous condition, exact for
/// a field without flutter).
double mean_field_hill_T(const SectorFieldSpec& spec, const OrbitSettings& settings, double r_mm);

}  // namespace turnfit
