// Turn-pattern errors: matching measured and simulated turns, norms, and the paper's objectives.
//
// Everything here is a pure function of in-memory data (no files, no streams), so that the
// optimizer can evaluate objectives thousands of times in-process: plan once against the
// measured turns (plan_objectives), then per model match_turns + evaluate_objectives, which
// reuse caller-owned buffers and do not allocate.
#pragma once

#include <array>
#include <climits>
#include <cmath>
#include <cstddef>
#include <nlohmann/json.hpp>
#include <string>
#include <string_view>
#include <vector>

namespace turnfit {

class CsvTable;

/// How an objective aggregates the residuals dr_i = r_sim_i - r_meas_i of its turns.
enum class Norm {
  linf,  ///< max |dr| (paper Eq. "matching quality", Sec. "Aggregation of turns")
  l2,    ///< sqrt(sum dr^2) / N, the paper's l2 aggregate (OPAL's sumErrSqRadialPeak)
  rms,   ///< sqrt(sum dr^2 / N)
  mae,   ///< sum |dr| / N
  mse,   ///< sum dr^2 / N (mm^2)
  wl2,   ///< sqrt(mean over parts of each part's MSE): every part weighs the same (local search)
  max2,  ///< the 2nd largest |dr| (local search)
  max3,  ///< the 3rd largest |dr| (local search)
};

/// The norm's name as written in specs and JSON ("linf", "l2", ...).
const char* norm_name(Norm norm);
/// Parses a norm name; false if it is not one.
bool parse_norm(std::string_view name, Norm* norm);
/// The list of norm names, for messages ("linf, l2, rms, mae, mse, wl2, max2, max3").
std::string norm_names();
/// The unit of a norm's value: "mm2" for mse, "mm" for the rest.
const char* norm_unit(Norm norm);

/// Error statistics of a set of residuals (mm). With no residual every value is NaN; a NaN
/// residual makes every value NaN (a failed simulation must not look like a good one).
struct ErrorStats {
  size_t n = 0;        ///< residuals counted
  double linf_mm = 0;  ///< max |dr|
  double mae_mm = 0;   ///< mean |dr|
  double mse_mm2 = 0;  ///< mean dr^2
  double rms_mm = 0;   ///< sqrt(mse)
  double l2_mm = 0;    ///< sqrt(sum dr^2) / n, the paper's l2 (= rms / sqrt(n))
  /// The three largest |dr|, largest first (NaN where there are fewer residuals).
  std::array<double, 3> largest_mm{};
  /// Caller's index of each of the three largest (SIZE_MAX where absent); ties keep the
  /// residual added first.
  std::array<size_t, 3> largest_index{};
};

/// One-pass accumulation of residuals: the building block of every norm (no allocation).
class ErrorAccumulator {
 public:
  /// Adds one residual; index is the caller's label for it (reported for the largest three).
  void add(double delta_mm, size_t index) {
    ++n_;
    const double a = delta_mm < 0 ? -delta_mm : delta_mm;
    if (std::isnan(a)) {
      nan_ = true;
      return;
    }
    sum_abs_ += a;
    sum_sq_ += a * a;
    // Keep the top three with strict '>' so that the first of equal residuals stays ahead.
    if (top_n_ < 3 || a > top_[2]) {
      int k = top_n_ < 3 ? top_n_++ : 2;
      while (k > 0 && a > top_[k - 1]) {
        top_[k] = top_[k - 1];
        top_index_[k] = top_index_[k - 1];
        --k;
      }
      top_[k] = a;
      top_index_[k] = index;
    }
  }
  /// Residuals added so far.
  size_t n() const { return n_; }
  /// Sum of dr^2 (NaN after a NaN residual).
  double sum_sq_mm2() const;
  /// The statistics of everything added.
  ErrorStats stats() const;

 private:
  size_t n_ = 0;
  double sum_abs_ = 0;
  double sum_sq_ = 0;
  bool nan_ = false;
  int top_n_ = 0;
  std::array<double, 3> top_{};
  std::array<size_t, 3> top_index_{};
};

/// Statistics of n residuals (ErrorAccumulator over an array; indices are array positions).
ErrorStats error_stats(const double* delta_mm, size_t n);

/// One turn of one probe: a measured peak or a simulated crossing.
struct TurnPoint {
  int probe = 0;     ///< index into TurnTable::probes
  int turn = 0;      ///< turn number as the file gives it (the paper's RRL starts at 9)
  double r_mm = 0;   ///< the compared column: radius along the probe
  long line = 0;     ///< source line (0: not from a file)
  std::string flag;  ///< peakfind's flag for merged or weak peaks ("" when none)
  double r_err_mm = std::nan("");  ///< peakfind's 1-sigma position uncertainty (NaN: the table has no r_err_mm column)
};

/// The turn radii of one data set, sorted by probe (in first-appearance order) then turn,
/// with each (probe, turn) once.
struct TurnTable {
  std::string source;               ///< name used in messages (file name or "<stdin>")
  std::string format;               ///< "peaks", "turns" or "" (built in memory)
  std::vector<std::string> probes;  ///< probe names, in order of first appearance
  std::vector<TurnPoint> points;    ///< sorted by (probe, turn)

  /// Index of a probe name in probes, -1 if absent.
  int probe_index(const std::string& name) const;
  /// Points [first, second) of probe p (contiguous because points are sorted).
  std::pair<size_t, size_t> probe_range(int probe) const;
};

/// Sorts a table's points by (probe, turn) and rejects a repeated (probe, turn) with
/// EX_DATAERR "source:line: probe P turn T appears twice (first at line L)".
void finish_turn_table(TurnTable& table);

/// Takes the turns of a parsed CSV: peaks (probe,turn,r_mm,height,area,width_mm[,r_err_mm][,flag],
/// from turnfit-peakfind; r_err_mm is read when present) or turns (probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg, from
/// turnfit-track); only probe, turn and r_mm are required. Turn numbers must be integers.
TurnTable turn_table_from_csv(const CsvTable& csv);

/// Turn counts of one probe in both data sets; a simulation with fewer or more turns than
/// measured violates the comparison's constraint (missing or extra non-empty).
struct TurnCount {
  std::string probe;        ///< probe name
  size_t measured = 0;      ///< measured turns of this probe
  size_t simulated = 0;     ///< simulated turns of this probe
  size_t matched = 0;       ///< turns in both
  std::vector<int> missing; ///< measured turns with no simulated partner
  std::vector<int> extra;   ///< simulated turns with no measured partner
};

/// A measured turn and its simulated partner.
struct Residual {
  int probe = 0;          ///< index into Comparison::probes
  int turn = 0;           ///< turn number
  double r_meas_mm = 0;   ///< measured radius
  double r_sim_mm = 0;    ///< simulated radius
  double delta_mm = 0;    ///< r_sim - r_meas
  size_t meas_index = 0;  ///< index of the measured point
};

/// Measured and simulated turns matched by probe name and turn number.
struct Comparison {
  /// The measured probes, in their order (residuals and counts refer to these).
  std::vector<std::string> probes;
  /// Simulated probes the measurement does not have: not compared and not a violation (a
  /// machine may carry more probes than were measured).
  std::vector<std::string> simulated_only;
  std::vector<Residual> residuals;  ///< matched turns, in measured order
  std::vector<TurnCount> counts;    ///< per probe, parallel to probes
  /// Missing plus extra turns over all probes (0: the turn counts agree).
  size_t violation() const;
};

/// Matches every measured turn with the simulated turn of the same probe and number.
Comparison compare_turns(const TurnTable& measured, const TurnTable& simulated);

/// The hot-loop form of compare_turns: fills delta_mm and matched (resized to
/// measured.points.size(), aligned with it) and returns the number of missing plus extra
/// turns. Allocates only when the buffers grow.
size_t match_turns(const TurnTable& measured, const TurnTable& simulated, std::vector<double>& delta_mm,
                   std::vector<unsigned char>& matched);

/// A turn range of one probe; turns [first_turn, last_turn], both included.
struct TurnRange {
  std::string probe;           ///< probe name, or "*": one part per measured probe
  int first_turn = INT_MIN;    ///< first turn (INT_MIN: from the first)
  int last_turn = INT_MAX;     ///< last turn (INT_MAX: to the last)
};

/// An objective sigma: a norm over one or more turn ranges (paper Sec. "Aggregation of turns").
struct Objective {
  std::string name;              ///< label in reports; the canonical spec when not given
  std::vector<TurnRange> parts;  ///< turn ranges; residuals of all parts are pooled (wl2: weighed)
  Norm norm = Norm::linf;        ///< aggregation
};

/// The canonical spec of an objective, e.g. "RRL:9-31:linf" or "RRI2:1-16+RRL:9-182:wl2".
std::string objective_spec(const Objective& obj);

/// Parses --objectives: comma-separated [NAME=]PART[+PART...]:NORM, where PART is PROBE,
/// PROBE:N or PROBE:L-U and PROBE may be '*'. Throws EX_USAGE naming the bad item.
std::vector<Objective> parse_objectives_spec(const std::string& spec);

/// Parses a JSON objectives array (the problem file's "objectives"; turnfit-compare(1), OBJECTIVES):
/// each entry an object {"name"?, "probe", "turns"?, "norm"} or {"name"?, "parts": [{"probe",
/// "turns"?}, ...], "norm"}, or a spec string. Throws EX_DATAERR "where: objectives[i]...: ...".
std::vector<Objective> parse_objectives_json(const nlohmann::json& j, const std::string& where);

/// Reads objectives from a JSON document: a problem file (an object with "objectives") or a
/// bare objectives array.
std::vector<Objective> objectives_from_document(const nlohmann::json& doc, const std::string& where);

/// An objective in the JSON shape parse_objectives_json reads.
nlohmann::json objective_to_json(const Objective& obj);

/// Objectives resolved against the measured turns: each part is a contiguous run of measured
/// points, so evaluation is a loop over index ranges.
struct ObjectivePlan {
  /// Measured points [begin, end) of one part.
  struct Part {
    size_t begin = 0;
    size_t end = 0;
  };
  /// One objective.
  struct Item {
    Norm norm = Norm::linf;
    std::vector<Part> parts;
    size_t measured = 0;  ///< measured turns the objective covers (the paper's N when complete)
  };
  std::vector<Item> items;  ///< parallel to the objectives planned
};

/// Resolves objectives against measured turns. EX_DATAERR if an objective names a probe the
/// measurement does not have ("did you mean"), or covers no measured turn.
ObjectivePlan plan_objectives(const std::vector<Objective>& objectives, const TurnTable& measured);

/// Value and coverage of one evaluated objective.
struct ObjectiveValue {
  double value = 0;  ///< the norm (mm, or mm^2 for mse); NaN when no turn is matched
  size_t n = 0;      ///< matched turns used (the N of the l2 norm)
  size_t missing = 0;  ///< covered measured turns without a simulated partner
};

/// Evaluates every planned objective on residuals aligned with the measured points (from
/// match_turns); unmatched points are left out and counted as missing. out must hold
/// plan.items.size() values. No allocation.
void evaluate_objectives(const ObjectivePlan& plan, const double* delta_mm, const unsigned char* matched,
                         ObjectiveValue* out);

}  // namespace turnfit
