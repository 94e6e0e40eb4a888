// Multi-objective problems: the interface the NSGA-II engine optimizes, and the built-in test
// problems (ZDT, DTLZ2, BNH, TNK, OSY, SRN, C2-DTLZ2) with their known Pareto fronts.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

namespace turnfit {

/// What one evaluation of a design x gave. Objectives are minimized; constraints follow the
/// convention g_j <= 0 is feasible, and the violation is sum_j max(0, g_j) (Deb 2002, sec. 5).
/// A failed evaluation (crash, timeout, lost particle, NaN) sets ok = false and says why in
/// `reason`; the engine then ranks the individual after every other with violation = +inf.
struct Evaluation {
  std::vector<double> f;  ///< objective values, one per objective (minimized)
  std::vector<double> g;  ///< constraint values, one per constraint (g <= 0 feasible)
  bool ok = true;         ///< false when the evaluation failed
  std::string reason;     ///< why it failed (empty when ok)
};

/// sum_j max(0, g_j), summed in index order (so the same g always gives the same bits).
double constraint_violation(const std::vector<double>& g);

/// A box-bounded multi-objective problem. evaluate() must be safe to call concurrently from
/// several threads (the thread-pool evaluator does so).
class Problem {
 public:
  /// A problem of lower.size() variables; names may be empty (then x0, x1, ... are implied).
  Problem(std::string name, std::vector<double> lower, std::vector<double> upper,
          size_t n_objectives, size_t n_constraints, std::vector<std::string> variable_names = {});
  virtual ~Problem() = default;

  /// The problem's name (e.g. "ZDT1").
  const std::string& name() const { return name_; }
  /// Number of design variables.
  size_t n_variables() const { return lower_.size(); }
  /// Number of objectives.
  size_t n_objectives() const { return n_objectives_; }
  /// Number of constraints (g_j <= 0 feasible).
  size_t n_constraints() const { return n_constraints_; }
  /// Lower bounds of the variables.
  const std::vector<double>& lower() const { return lower_; }
  /// Upper bounds of the variables.
  const std::vector<double>& upper() const { return upper_; }
  /// Names of the variables; empty if the problem has none.
  const std::vector<std::string>& variable_names() const { return variable_names_; }

  /// Objectives and constraints at x (x.size() == n_variables()). Thread-safe.
  virtual Evaluation evaluate(const std::vector<double>& x) const = 0;

  /// About `npoints` points of the true Pareto front in objective space (fewer for
  /// disconnected fronts); empty when the front is not known.
  virtual std::vector<std::vector<double>> true_front(size_t npoints) const;

 private:
  std::string name_;
  std::vector<double> lower_, upper_;
  size_t n_objectives_ = 0, n_constraints_ = 0;
  std::vector<std::string> variable_names_;
};

/// Names make_problem() knows: ZDT1, ZDT2, ZDT3, ZDT4, ZDT6, DTLZ2, BNH, TNK, OSY, SRN, C2-DTLZ2.
std::vector<std::string> builtin_problem_names();

/// A built-in test problem by name (case-insensitive). n_variables = 0 takes the usual size
/// (ZDT1-3: 30, ZDT4 and ZDT6: 10, DTLZ2 and C2-DTLZ2: 12 for 3 objectives; BNH, TNK, SRN: 2;
/// OSY: 6, fixed). n_objectives = 0 takes 3 for DTLZ2/C2-DTLZ2 (others are fixed at 2).
/// Unknown names or impossible sizes: Error with ExitCode::usage.
std::unique_ptr<Problem> make_problem(const std::string& name, size_t n_variables = 0,
                                      size_t n_objectives = 0);

/// The non-dominated subset of a point set (minimization), in input order; duplicates kept once.
std::vector<std::vector<double>> nondominated_points(const std::vector<std::vector<double>>& pts);

/// Generational distance: the mean over `points` of the Euclidean distance to the nearest
/// point of `front` (how far a result is from the true front).
double generational_distance(const std::vector<std::vector<double>>& points,
                             const std::vector<std::vector<double>>& front);

/// Inverted generational distance: the mean over `front` of the distance to the nearest of
/// `points` (small only when the result both reaches and covers the front).
double inverted_generational_distance(const std::vector<std::vector<double>>& points,
                                      const std::vector<std::vector<double>>& front);

}  // namespace turnfit
