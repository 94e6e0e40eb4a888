// turnfit-tc-fit as a library function: trim coil phase-shift data in, rational field profiles out.
#pragma once

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <map>
#include <ostream>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/trimcoil/rational_fit.hpp"

namespace turnfit {

/// Everything turnfit-tc-fit is asked to do.
struct TcFitOptions {
  cli::CommonOptions common;
  std::vector<std::string> inputs;     ///< phase-shift CSV files ("-" for stdin)
  std::string degrees = "auto";        ///< "N/M" or "auto"
  std::string criterion = "aicc";      ///< auto: aicc | bic
  int max_numerator = 5;               ///< auto: largest numerator degree tried
  int max_denominator = 6;             ///< auto: largest denominator degree tried
  double rmin_mm = 0;                  ///< window start (0: per coil, see window())
  double rmax_mm = 0;                  ///< window end
  std::string model = "paper";         ///< paper | local | tracked (what f/g describes, see --help)
  std::string type;                    ///< psi-phase | psi-bfield (empty: psi-phase for paper, else psi-bfield)
  std::string report;                  ///< report JSON path (empty: none)
  std::string machine;                 ///< machine whose coils are replaced (empty: none)
  double grid_mm = 1;                  ///< csv: spacing of the fine grid
  int max_iterations = 400;            ///< Levenberg-Marquardt iterations per start
  std::string turns;                   ///< track's turns table: weights V_turn/beta (empty: none)
  double response_step_mm = 10;        ///< knot spacing of the response's B-spline basis
  double phase_azimuth_deg = 0;        ///< phase probes' azimuth (default: the scan's '# azimuth_deg=')
  bool phase_azimuth_given = false;
  double mass_MeV = 0;                 ///< rest mass for beta (0: the machine's particle, else proton)
};

/// The slowly varying factor between a phase-shift slope and the field that causes it. For a
/// field change dB (azimuthal mean) on an isochronous orbit, the frequency changes by
/// dB / (B gamma^2) at fixed energy, and sin(phi) drifts by 2 pi h dw/w per turn over the
/// energy gain per turn qV; with dE/dr = gamma (gamma + 1) E / r this gives
///   dB = -(V_turn / (2 pi h beta c)) d(delta sin phi)/dr,
/// so the field follows the slope times V_turn / beta. (The paper's Eq. 4 carries
/// q B V r / (E gamma (gamma + 1)), which differs by gamma^2; ring8's synthetic scans, made by
/// tracking, follow V/beta.) Built from a turns table (track's output).
struct SlopeWeight {
  std::vector<double> r_mm;   ///< increasing radii (between consecutive turns)
  std::vector<double> w;      ///< V_turn [MV] / beta there
  /// w at r (linear, clamped at the ends).
  double at(double r) const;
};

/// Reads a turns table (r_mm, energy_MeV, turn; of several probes the one with most turns) into
/// the weight V_turn / beta. EX_DATAERR if fewer than 3 turns or energies do not increase.
SlopeWeight read_slope_weight(const std::string& path, double mass_MeV);

/// Registers turnfit-tc-fit's options.
void add_tcfit_options(CLI::App& app, TcFitOptions& o);

/// One coil's phase-shift scan as read.
struct PhaseData {
  std::string name;                 ///< coil name
  std::string source;               ///< file it came from (for messages)
  std::vector<double> r_mm, dsinphi;
  std::vector<long> lines;          ///< source line of each point
  double excitation_T = 0;          ///< '# excitation_T=' of the scan (0: not given)
  double azimuth_deg = 0;           ///< '# azimuth_deg=' of the phase probes (0: not given)
  std::string error;                ///< non-empty: the data cannot be used (message)
};

/// Reads phase-shift scans: `r_mm,dsinphi` per file (coil from '# coil=' or the file stem) or
/// one file with a `coil` column. Points are sorted by radius. A coil whose rows are bad (not a
/// number, duplicate radius) is returned with `error` set, so the other coils still fit; a
/// file that cannot be read at all throws.
std::vector<PhaseData> read_phase_data(const std::string& path);

/// One coil's fit and what became of it.
struct CoilFit {
  PhaseData data;
  std::string error;                ///< non-empty: no fit (message)
  double r_lo_mm = 0, r_hi_mm = 0;  ///< fit window = the coil's support
  RationalFit fit;                  ///< the chosen fit of delta sin(phi)
  std::string selected_by;          ///< "--degrees" or the criterion
  std::vector<RationalFit> candidates;  ///< auto: every fit tried (failures left out)
  std::vector<std::string> candidate_errors;  ///< auto: "n/m: why" for those that failed
  TrimCoil coil;                    ///< the machine-file entry (normalized: peak field shape +1)
  double peak_r_mm = 0;             ///< where |field shape| peaks
  double slope_per_m = 0;           ///< -d(dsinphi)/dr there (the normalization divisor) [1/m]
  double representation_error = 0; ///< max |shape(machine-file coefficients) - shape(scaled fit)|
  double opal_representation_error = 0;  ///< the same for OPAL's coefficients in r itself
  TrimCoil opal_coil;               ///< the entry with coefficients in r (origin 0), for OPAL
  bool weighted = false;            ///< the scan was corrected by a SlopeWeight
  double weight_lo = 1, weight_hi = 1;  ///< the weight at the window's ends over its centre value
};

/// Fits one coil's data (its window from the options or `machine_coil`, else its data range).
/// With a weight, the scan is first turned into a field-proportional phase:
/// S'(r_i+1) = S'(r_i) + w(r_mid)/w(centre) (S(r_i+1) - S(r_i)), whose slope follows the field.
CoilFit fit_coil(const PhaseData& data, const TcFitOptions& o, const TrimCoil* machine_coil = nullptr,
                 const SlopeWeight* weight = nullptr, const LinearResponse* response = nullptr);

/// The tracked response of a coil's scan (--model tracked): cubic B-splines on knots every
/// `step_mm` over the window (exact partition of unity, held by in-memory tables with exact
/// slopes), each added to the machine as a coil with the machine coil's sectors and azimuth
/// window, the reference particle tracked (turnfit-synth's phase scan), and the phase shifts
/// at the scan's radii taken per tesla; then the quasi-interpolant (-R_{j-1} + 8 R_j - R_{j+1}) / 6
/// maps field samples R(t_j) to spline coefficients, so K R(t) is the predicted scan. `cache`
/// keeps the runs of knots already tracked (shared by coils with the same sectors and window).
LinearResponse coil_response(const Machine& m, const TrimCoil* machine_coil, const std::vector<double>& r_mm,
                             double r_lo, double r_hi, double step_mm, double azimuth_deg, unsigned threads,
                             std::map<std::string, std::vector<double>>& cache);

/// One-sigma uncertainty of the normalized field shape at r (delta method through the fit's
/// covariance, including the normalization at the peak); NaN without a covariance.
double fitted_shape_sigma(const CoilFit& c, double r_mm);

/// The normalized field shape s(r) and ds/dr [1/m] of a fit, from the scaled fit itself
/// (what the machine-file coefficients must reproduce): s = -(dq/dr) / slope.
void fitted_shape(const CoilFit& c, double r_mm, double& s, double& ds_dr_per_m);

/// Writes the fitted coils in the options' format (json, opal or csv).
void write_tcfit_output(std::ostream& os, const std::vector<CoilFit>& fits, const TcFitOptions& o);

/// The report document: per coil window, degrees (and why), residual rms and max, condition
/// number, scaled coefficients with their uncertainties, candidates, failures.
nlohmann::json tcfit_report(const std::vector<CoilFit>& fits, const TcFitOptions& o);

/// Runs turnfit-tc-fit; returns the exit code (65 if any coil could not be fitted, after
/// writing the others).
int run_tcfit(const TcFitOptions& o);

}  // namespace turnfit
