// NSGA-II (Deb, Pratap, Agarwal, Meyarivan 2002) with constraint-domination, deterministic
// per generation, evaluation separated from variation (threads, MPI, external commands plug in
// as Evaluators), and exact resume from a log of evaluated individuals.
//
// How a run goes: generation 0 is `population` random designs; each generation t = 1 ..
// `generations` makes `population` offspring from the current population (binary tournament by
// crowded comparison, SBX, polynomial mutation) and keeps the best `population` of parents and
// offspring (constraint-domination fronts, then crowding distance). A run evaluates
// population * (generations + 1) designs. Individual i of generation t has id t * population + i.
//
// Determinism: every random draw of generation t comes from Rng::for_generation(seed, t) on the
// calling thread, and the engine sees evaluations by index, never in completion order, so a
// seed gives bit-identical populations with any number of threads or ranks. Resume replays the
// run from the seed and takes the evaluations a log already has (matched by id, checked by x),
// evaluating only the missing ones, so it ends exactly where the uninterrupted run ends.
#pragma once

#include <cstdint>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "turnfit/optimize/problems.hpp"

namespace turnfit {

/// xoshiro256** (Blackman and Vigna 2018) seeded through SplitMix64: a small generator whose
/// outputs are the same on every platform (unlike std:: distributions).
class Rng {
 public:
  /// A generator seeded from one 64-bit value.
  explicit Rng(std::uint64_t seed);
  /// The generator of one generation of a run: depends on (seed, generation) only.
  static Rng for_generation(std::uint64_t seed, std::uint64_t generation);
  /// The next 64 random bits.
  std::uint64_t next();
  /// A uniform double in [0, 1) from the top 53 bits.
  double uniform();
  /// A uniform integer in [0, n) without modulo bias (n > 0).
  std::uint64_t below(std::uint64_t n);

 private:
  std::uint64_t s_[4];
};

/// NSGA-II's settings; the defaults are Deb's (Deb et al. 2002, sec. VI).
struct Nsga2Settings {
  size_t population = 100;            ///< N, parents and offspring per generation (>= 2)
  size_t generations = 250;           ///< offspring generations after the initial population
  std::uint64_t seed = 1;             ///< the run's seed
  double crossover_probability = 0.9; ///< probability that a pair of parents is crossed
  double eta_c = 20;                  ///< SBX distribution index
  double crossover_variable_probability = 0.5;  ///< per-variable chance of SBX within a crossing
  double mutation_probability = -1;   ///< per-variable mutation probability; < 0 means 1/n
  double eta_m = 20;                  ///< polynomial mutation distribution index
  /// Hypervolume reference for progress (empty: none). Computed every generation on the
  /// feasible individuals: cheap for 2-3 objectives (8000 points: < 10 ms), costly beyond
  /// (measured on a sphere front: 4 objectives 8000 points 7 s, 6 objectives 1000 points 0.8 s,
  /// 8000 points 22 s), so leave it empty for large many-objective runs.
  std::vector<double> reference;
};

/// One design of a run and what its evaluation gave.
struct Individual {
  std::uint64_t id = 0;      ///< unique over the run: generation * population + index
  size_t generation = 0;     ///< the generation that created it (0: initial population)
  std::vector<double> x;     ///< design variables, within the problem's bounds
  std::vector<double> f;     ///< objectives (minimized); NaN-filled if a failed evaluation gave none
  std::vector<double> g;     ///< constraint values (g <= 0 feasible)
  double violation = 0;      ///< sum max(0, g_j); +inf for a failed evaluation
  bool ok = true;            ///< false when the evaluation failed
  std::string reason;        ///< why the evaluation failed
  int rank = -1;             ///< front index in the last sort (0 best); -1 before any sort
  double crowding = std::numeric_limits<double>::quiet_NaN();  ///< crowding distance in its front
  /// True when the evaluation succeeded and every constraint holds.
  bool feasible() const { return ok && violation <= 0; }
};

/// Stores an evaluation in `ind` and checks it: a result with the wrong number of objectives or
/// constraints, or a NaN or infinite value, becomes a failure (ok = false, reason says which);
/// a failure gets violation = +inf and NaN objectives where it has none.
void apply_evaluation(Individual& ind, Evaluation e, size_t n_objectives, size_t n_constraints);

/// Constraint-domination (Deb 2002, sec. V): a feasible individual beats an infeasible one; of
/// two infeasible ones the smaller violation wins; of two feasible ones Pareto dominance decides.
bool constrained_dominates(const Individual& a, const Individual& b);

/// The fronts of `pop` by constraint-domination, best first, each a list of indices into pop
/// in increasing index order. Feasible individuals are sorted by the efficient non-dominated
/// sort with binary search (Zhang et al. 2015; one look at the last member per front for two
/// objectives, O(N log N)); the infeasible ones follow, one front per distinct violation in
/// increasing order (equal violations share a front).
std::vector<std::vector<size_t>> nondominated_sort(const std::vector<Individual>& pop);

/// Sets `crowding` of the members of one front (Deb 2002, sec. III-B): the sum over objectives
/// of the gap between each member's neighbours divided by the objective's range in the front;
/// the extreme members, and every member of a front of one or two, get +inf. Failed
/// evaluations (ok = false) and members with a NaN or infinite objective get 0 and are left
/// out of the others' neighbours.
void crowding_distance(std::vector<Individual>& pop, const std::vector<size_t>& front);

/// Sorts `pop` into fronts and sets every individual's rank and crowding; returns the fronts.
std::vector<std::vector<size_t>> rank_and_crowd(std::vector<Individual>& pop);

/// Crowded comparison (Deb 2002, sec. III-C): lower rank wins, then larger crowding. Returns
/// +1 if a wins, -1 if b wins, 0 on a tie.
int crowded_compare(const Individual& a, const Individual& b);

/// Simulated binary crossover, bounded variant (Deb and Agrawal 1995; Deb's nsga2 code):
/// each variable is crossed with probability p_variable when the parents differ there; the
/// spread factor's distribution is shrunk so that children fall inside [lo, hi], and the two
/// children swap sides with probability 1/2. Writes the children into c1 and c2.
void sbx_crossover(const std::vector<double>& p1, const std::vector<double>& p2,
                   const std::vector<double>& lo, const std::vector<double>& hi, double eta_c,
                   double p_variable, Rng& rng, std::vector<double>& c1, std::vector<double>& c2);

/// Polynomial mutation, bounded variant (Deb and Goyal 1996; Deb's nsga2 code): each variable
/// mutates with probability p_variable, with a perturbation whose distribution is scaled by its
/// distances to the bounds so that the result stays inside [lo, hi].
void polynomial_mutation(std::vector<double>& x, const std::vector<double>& lo,
                         const std::vector<double>& hi, double eta_m, double p_variable, Rng& rng);

/// Receives the result of design `index` of a batch.
using EvaluationSink = std::function<void(size_t index, Evaluation evaluation)>;

/// Evaluates batches of designs. Implementations may evaluate in any order and in parallel.
class Evaluator {
 public:
  virtual ~Evaluator() = default;
  /// Evaluates every design of `batch`, calling done(i, result) exactly once for each i, in
  /// any order, from any thread, concurrently if it likes; returns when all are done. A
  /// design that cannot be evaluated gets a result with ok = false and the reason.
  virtual void evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) = 0;
};

/// Evaluates a function on `threads` std::threads that take the next index from an atomic
/// counter (`--threads`): a slow design holds up only its own thread. An exception thrown by
/// the function becomes a failed evaluation with the exception's message as the reason.
class ThreadPoolEvaluator : public Evaluator {
 public:
  /// The function evaluated per design; must be safe to call concurrently.
  using Function = std::function<Evaluation(const std::vector<double>&)>;
  /// Evaluates `fn` on `threads` threads (0: std::thread::hardware_concurrency()).
  ThreadPoolEvaluator(Function fn, size_t threads);
  /// Evaluates problem.evaluate (the problem must outlive the evaluator).
  ThreadPoolEvaluator(const Problem& problem, size_t threads);
  /// Evaluates the batch; returns when every design is done.
  void evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) override;
  /// The number of threads used.
  size_t threads() const { return threads_; }

 private:
  Function fn_;
  size_t threads_;
};

/// The state after one generation, for progress reports.
struct Nsga2Progress {
  size_t generation = 0;        ///< 0 for the initial population
  size_t evaluations = 0;       ///< individuals evaluated so far, those taken from a log included
  size_t new_evaluations = 0;   ///< of which evaluated by this process
  size_t feasible = 0;          ///< feasible individuals in the population
  double hypervolume = std::numeric_limits<double>::quiet_NaN();  ///< of the feasible front, if a reference is set
  double best_sum = std::numeric_limits<double>::quiet_NaN();     ///< least sum of objectives of a feasible individual (the paper's "best individual")
  std::uint64_t best_id = 0;    ///< the id of that individual
  const std::vector<Individual>* population = nullptr;  ///< the population after selection (ranks and crowding set)
};

/// What the engine reports during a run. Both may be empty.
struct Nsga2Callbacks {
  /// Called once per design evaluated by this process (not for those taken from the log),
  /// never concurrently (calls are serialized by the engine), in id order: a design is
  /// reported as soon as it and every design before it in its batch are evaluated, so the
  /// sequence is the same for any thread count or evaluator. Rank is -1 and crowding NaN (not
  /// known yet). Write and flush the log line here.
  std::function<void(const Individual&)> on_evaluated;
  /// Called after each generation's selection (generation 0 included), on the calling thread.
  std::function<void(const Nsga2Progress&)> on_generation;
};

/// The outcome of a run.
struct Nsga2Result {
  std::vector<Individual> population;  ///< the final population, best front first (ranks and crowding set)
  size_t evaluations = 0;              ///< designs evaluated in the whole run, log included
  size_t new_evaluations = 0;          ///< of which by this process
  size_t reused = 0;                   ///< of which taken from the resume log
};

/// Runs NSGA-II on `problem` (bounds, sizes) with `evaluator` computing the objectives and
/// constraints. `log` holds individuals evaluated by an earlier run with the same problem and
/// settings (any order, any subset, a generation possibly cut short; only id, x, f, g,
/// violation, ok and reason are read): they are not evaluated again and the run ends with the
/// same population as an uninterrupted one. If `g` of a log entry has the problem's number of
/// constraints the violation is recomputed from it, else its `violation` is taken. Errors:
/// ExitCode::usage for bad settings, ExitCode::data when a log entry's x differs from the
/// design this run makes under that id (another seed, population or problem).
Nsga2Result run_nsga2(const Problem& problem, const Nsga2Settings& settings, Evaluator& evaluator,
                      const Nsga2Callbacks& callbacks = {}, const std::vector<Individual>& log = {});

/// The same with problem.evaluate on a ThreadPoolEvaluator of `threads` threads.
Nsga2Result run_nsga2(const Problem& problem, const Nsga2Settings& settings, size_t threads,
                      const Nsga2Callbacks& callbacks = {}, const std::vector<Individual>& log = {});

/// The final non-dominated feasible set of a population: the feasible individuals no other
/// feasible one dominates, sorted by objectives (then id). Duplicated objective vectors are
/// all kept.
std::vector<Individual> pareto_front(const std::vector<Individual>& pop);

/// The hypervolume of pareto_front(pop) w.r.t. reference (0 when no individual is feasible).
double front_hypervolume(const std::vector<Individual>& pop, const std::vector<double>& reference);

}  // namespace turnfit
