// The turn-pattern problem: a machine, measured turns and design variables, evaluated in
// process (track + compare, no shell, no disk). What nsga, localsearch and diagnose optimize.
#pragma once

#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/metrics/metrics.hpp"
#include "turnfit/metrics/scan_noise.hpp"
#include "turnfit/optimize/problems.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit {

/// One design variable of a turn-pattern problem.
struct TurnVariable {
  std::string name;
  std::string unit;
  double lower = 0;  ///< the problem's bounds (the machine's unless the problem file overrides them)
  double upper = 0;
  double start = 0;  ///< its value in the machine as loaded
  /// Prior: the setting is known (control system, survey) within sigma of `start`; 0: none.
  /// A fit adds the residual (x - start) / sigma, so the variable cannot quietly absorb
  /// physics the model lacks.
  double sigma = 0;
};

/// The paper's six objectives (its Tab. of results): RRI2 turns 1-16 and five RRL ranges, each
/// the largest |dr|.
std::vector<Objective> paper_objectives();

/// What one design gives, turn by turn.
struct TurnPatternResult {
  bool ok = false;               ///< false: the design could not be simulated (reason says why)
  std::string reason;
  /// r_sim - r_meas per measured point (TurnPatternProblem::measured().points order); NaN where
  /// the simulation has no partner turn.
  std::vector<double> delta_mm;
  std::vector<unsigned char> matched;  ///< 1 where delta_mm is a residual
  size_t violation = 0;          ///< missing plus extra turns (0: the turn counts agree)
  std::vector<ObjectiveValue> objectives;  ///< one per problem objective
  TurnTable simulated;           ///< the simulated crossings (probe, turn, r) that were compared
  TrackEnd end;                  ///< how the track ended
};

/// What a probe measures is the bunch's centre, not the reference particle the model tracks:
/// with an RF phase spread the bunch gains less energy on average and its centre runs inside
/// the reference particle (0.07 mm on ring8's 2 deg bunch). The problem predicts the centre as
/// the reference particle's crossing plus a shift per (probe, turn), the bunch quadrature's
/// weighted mean minus the reference crossing, computed at one design (the shift's design) and
/// held fixed while that design's neighbours are evaluated: it changes slowly with the design,
/// and a fit recomputes it between passes.
struct CentroidShift {
  std::vector<double> x;                        ///< the design it was computed at (empty: none)
  std::vector<std::vector<double>> shift_mm;    ///< [model probe][turn - 1]; NaN where unknown
  size_t nodes = 0;                             ///< quadrature particles tracked
  size_t known = 0, unknown = 0;                ///< crossings with and without a shift (a node lost or short of the turn)
  double max_abs_mm = 0;                        ///< largest |shift|
  double rms_mm = 0;                            ///< over the known crossings
};

/// A turn-pattern problem (turnfit-problem(5), "TURN-PATTERN PROBLEMS"). Loading reads every
/// file once (machine, field map, profiles, measured peaks); evaluate() and simulate() read
/// nothing from disk and are safe to call from several threads at once.
class TurnPatternProblem : public Problem {
 public:
  /// From a parsed problem file `j` (turnfit-problem/1 with a "machine" key). `file` names it in
  /// messages; relative paths are resolved against `dir`. Errors: EX_DATAERR naming the file
  /// and key (an unknown variable, a probe an objective needs that the peaks lack, an
  /// objective that covers no measured turn), EX_NOINPUT for a missing machine or peaks file.
  static std::unique_ptr<TurnPatternProblem> from_json(const nlohmann::json& j, const std::string& file,
                                                       const std::string& dir);

  /// Objectives (the problem's, in mm) and the turn-count constraint (missing plus extra
  /// turns, <= 0 feasible) when the problem has it. A design that cannot be simulated, or an
  /// objective that matches no turn, is a failed evaluation (ok = false, with the reason).
  Evaluation evaluate(const std::vector<double>& x) const override;

  /// The design's turns compared with the measurement.
  TurnPatternResult simulate(const std::vector<double>& x) const;
  /// simulate() of several designs, their reference particles tracked together (the group
  /// stepper with a model per design: 1.15-1.4x the throughput of one at a time, bench/
  /// RESULTS.md): what simulate() gives each, bit for bit, whatever the thread count. On
  /// `threads` workers (0: all cores), the designs in contiguous chunks of at most a group's
  /// lanes, at least one per worker. For finite-difference Jacobians. Thread-safe.
  std::vector<TurnPatternResult> simulate_many(const std::vector<std::vector<double>>& xs,
                                               unsigned threads = 1) const;

  /// The machine as loaded (variables at their start values).
  const Machine& machine() const { return machine_; }
  /// The machine with the design's values set (EX_USAGE if a value is outside its bounds).
  Machine machine_at(const std::vector<double>& x) const;
  /// The variables, in the order of x.
  const std::vector<TurnVariable>& variables() const { return vars_; }
  /// Start values (the machine's), in the order of x.
  std::vector<double> start() const;
  /// The measured turns (every probe of the peaks files).
  const TurnTable& measured() const { return measured_; }
  /// The objectives.
  const std::vector<Objective>& objectives() const { return objectives_; }
  /// Whether the turn-count constraint is on.
  bool turn_count_constraint() const { return turn_count_; }
  /// Peak-position uncertainty per measured point [mm] from the problem's sigma_mm; empty when
  /// the file gives none (a fit then estimates it).
  const std::vector<double>& sigma_mm() const { return sigma_mm_; }
  /// The probe drive's correlated error (the problem file's "scan_noise"; inactive by default):
  /// a fit with it weighs each probe's residuals by their full covariance (Whitener).
  const ScanNoise& scan_noise() const { return scan_noise_; }
  /// Sets it (not while evaluations run).
  void set_scan_noise(const ScanNoise& s) { scan_noise_ = s; }
  /// The tracking settings every simulation uses (the machine's, with the problem's turns).
  const TrackSettings& track_settings() const { return settings_; }
  /// Tracks with the reference stepper (TrackSettings::reference_stepper): for benchmarks.
  void set_reference_stepper(bool on) { settings_.reference_stepper = on; }
  /// "centroid" (the measured bunch's centre: the reference particle plus the centroid shift)
  /// or "reference" (the reference particle alone): the problem file's "bunch"; by default
  /// "centroid" when the machine has a bunch with spread, else "reference".
  const std::string& bunch_mode() const { return bunch_mode_; }
  /// The bunch quadrature the centroid shift tracks (empty in "reference" mode).
  const std::vector<QuadratureNode>& bunch_nodes() const { return nodes_; }
  /// The centroid shift at design x (tracks the reference and every quadrature particle on
  /// `threads` threads; reads nothing from disk). Empty shift in "reference" mode.
  /// EX_DATAERR if the reference particle cannot be simulated at x.
  CentroidShift centroid_shift(const std::vector<double>& x, unsigned threads) const;
  /// Sets the shift that simulate() and evaluate() add from now on (loading sets the one at the
  /// start, when the start can be simulated). Not while evaluations run.
  void set_centroid_shift(CentroidShift s) { shift_ = std::move(s); }
  /// Computes the shift at x and sets it; returns the largest change [mm] of a shift known
  /// before and after (0 in "reference" mode, and when there was none before).
  double update_centroid_shift(const std::vector<double>& x, unsigned threads);
  /// The shift in use (empty x: none yet, simulate() gives the reference particle's turns).
  const CentroidShift& current_centroid_shift() const { return shift_; }
  /// The problem file, for messages.
  const std::string& file() const { return file_; }

  /// The same measurement, objectives and model files with another machine document and
  /// variables: `m` is this problem's machine changed in memory (e.g. effects added to its
  /// `effects`, each with design variables bound to their parameters), `vars` design variables
  /// of `m` in the order of x. Reads nothing from disk (the model's files are this problem's:
  /// `m` must name no other file). The centroid shift in use is kept, as computed at the design
  /// `shift_x` (x of the new variables); with `hold_shift` it stays the shift of every later
  /// evaluation (the copy tracks no bunch: a fit of it never recomputes the shift). EX_SOFTWARE
  /// for a variable `m` lacks.
  std::unique_ptr<TurnPatternProblem> with_machine(Machine m, std::vector<TurnVariable> vars,
                                                   const std::vector<double>& shift_x, bool hold_shift = false) const;
  /// Sets the peak-position uncertainty per measured point [mm] (empty: a fit estimates it).
  /// Not while evaluations run.
  void set_sigma_mm(std::vector<double> sigma);
  /// Moves each measured radius by dr_mm (one per measured point, 0 leaves it): a simulated
  /// measurement with the same turns, numbers and uncertainties, for checks of what a fit can
  /// take up. Not while evaluations run; EX_SOFTWARE for a wrong size or a non-finite move.
  void shift_measured(const std::vector<double>& dr_mm);

 private:
  /// simulate() of count designs xs[0..count) in one call of the group stepper.
  std::vector<TurnPatternResult> simulate_group(const std::vector<double>* xs, size_t count) const;
  TurnPatternProblem(std::string name, std::vector<double> lower, std::vector<double> upper,
                     std::vector<std::string> names, size_t n_objectives, size_t n_constraints);
  std::string file_;
  Machine machine_;
  ModelFiles files_;
  TrackSettings settings_;
  std::vector<TurnVariable> vars_;
  std::vector<std::string> names_;
  TurnTable measured_;
  std::vector<Objective> objectives_;
  ObjectivePlan plan_;
  bool turn_count_ = true;
  std::vector<double> sigma_mm_;
  ScanNoise scan_noise_;
  std::string bunch_mode_ = "reference";
  std::vector<QuadratureNode> nodes_;
  CentroidShift shift_;
};

/// The measured turns of one or more peaks files (turnfit-peakfind's CSV; "-" is stdin), as one
/// table: a probe may come from one file only, a repeated (probe, turn) is EX_DATAERR.
TurnTable read_measured_turns(const std::vector<std::string>& paths);

}  // namespace turnfit
