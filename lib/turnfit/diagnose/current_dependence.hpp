// The space-charge candidate of turnfit-diagnose: with the turns measured at two or more beam
// currents, the part of the residual that changes with the current is space charge's signature.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/optimize/turn_problem.hpp"
#include "turnfit/spacecharge/poisson.hpp"

namespace turnfit {

/// One measurement of the same machine at a beam current: its peaks file.
struct CurrentMeasurement {
  double current_uA = 0;
  std::vector<std::string> peaks;  ///< turnfit-peakfind CSVs (one per probe, or one with every probe)
};

/// How the space-charge candidate is computed and judged.
struct CurrentTestSettings {
  size_t particles = 2000;      ///< bunch tracked for the signature (the machine's bunch block)
  sc::GridSize grid{16, 16, 16};  ///< the solver's grid
  int every_steps = 1;
  std::uint64_t seed = 1;
  unsigned threads = 1;
  double margin = 10;           ///< chi2 gain beyond BIC's ln N to name it (diagnose's margin)
};

/// The candidate's verdict and figures (the report's "space_charge" object).
struct CurrentTest {
  bool named = false;
  nlohmann::json report;
};

/// Scores space charge on measurements at several currents (`ms`, at least two, of the machine
/// of problem `p`, whose file `problem_json` is, resolved against `dir`): each measurement is
/// compared with the model at design x, linearized in the design variables, which each
/// measurement moves by its own amounts (a run's drift), and a per-turn error common to all
/// measurements is left free (what does not change with the current: every other missing
/// effect). What is left is the current-dependent part, fitted by alpha times the signature:
/// the change of the bunch's centroids with space charge at each current (the bunch tracked
/// with and without it, the same particles), computed at x. Named when its chi2 gain passes
/// margin + ln N and alpha > 0; the report gives alpha with its error, the gain, the threshold,
/// and the gain the model's own space charge (alpha = 1) would give, the detection limit.
/// EX_USAGE for fewer than two measurements or two at one current; errors reading a peaks
/// file name it.
CurrentTest space_charge_candidate(const TurnPatternProblem& p, const nlohmann::json& problem_json,
                                   const std::string& dir, const std::vector<double>& x,
                                   const std::vector<CurrentMeasurement>& ms, const CurrentTestSettings& s);

/// The statistics of the test on given residuals and signatures, for tests and the candidate:
/// y[k][i] measurement k's residual (measured minus model) at common point i, sigma[k][i] its
/// noise, J[k][i] its row of d(measured - model)/dx, sig[k][i] the signature. Returns alpha, its
/// error, the gain, the chi2 without and with it, the points and the gain at alpha = 1.
struct CurrentFit {
  double alpha = 0, alpha_sigma = 0, gain = 0, chi2_without = 0, chi2_with = 0, gain_at_one = 0;
  size_t points = 0, dof = 0;
};
CurrentFit fit_current_dependence(const std::vector<std::vector<double>>& y,
                                  const std::vector<std::vector<double>>& sigma,
                                  const std::vector<std::vector<std::vector<double>>>& J,
                                  const std::vector<std::vector<double>>& sig);

}  // namespace turnfit
