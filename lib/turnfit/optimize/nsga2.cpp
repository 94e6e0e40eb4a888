// NSGA-II engine: sorting, crowding, operators, the generation loop, resume, thread pool.
#include "turnfit/optimize/nsga2.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>
#include <numeric>
#include <unordered_map>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/optimize/hypervolume.hpp"

namespace turnfit {

// ---- random numbers --------------------------------------------------------------------

namespace {

/// SplitMix64 (Steele, Lea, Flood 2014): expands one seed into well-mixed words.
std::uint64_t splitmix(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9e3779b97f4a7c15ULL);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

std::uint64_t rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

}  // namespace

Rng::Rng(std::uint64_t seed) {
  std::uint64_t st = seed;
  for (auto& s : s_) s = splitmix(st);
}

Rng Rng::for_generation(std::uint64_t seed, std::uint64_t generation) {
  std::uint64_t st = seed;
  const std::uint64_t a = splitmix(st);
  std::uint64_t st2 = generation ^ 0x6a09e667f3bcc909ULL;
  const std::uint64_t b = splitmix(st2);
  return Rng(a ^ rotl(b, 17));
}

std::uint64_t Rng::next() {
  const std::uint64_t result = rotl(s_[1] * 5, 7) * 9;
  const std::uint64_t t = s_[1] << 17;
  s_[2] ^= s_[0];
  s_[3] ^= s_[1];
  s_[1] ^= s_[2];
  s_[0] ^= s_[3];
  s_[2] ^= t;
  s_[3] = rotl(s_[3], 45);
  return result;
}

double Rng::uniform() { return double(next() >> 11) * 0x1.0p-53; }

std::uint64_t Rng::below(std::uint64_t n) {
  // Reject the lowest (2^64 mod n) values so every residue is equally likely.
  const std::uint64_t threshold = (0 - n) % n;
  for (;;) {
    const std::uint64_t r = next();
    if (r >= threshold) return r % n;
  }
}

// ---- evaluation results ------------------------------------------------------------------

void apply_evaluation(Individual& ind, Evaluation e, size_t n_objectives, size_t n_constraints) {
  ind.ok = e.ok;
  ind.reason = std::move(e.reason);
  ind.f = std::move(e.f);
  ind.g = std::move(e.g);
  if (ind.ok) {
    if (ind.f.size() != n_objectives) {
      ind.ok = false;
      ind.reason = "evaluation gave " + std::to_string(ind.f.size()) + " objectives, expected " +
                   std::to_string(n_objectives);
    } else if (ind.g.size() != n_constraints) {
      ind.ok = false;
      ind.reason = "evaluation gave " + std::to_string(ind.g.size()) + " constraints, expected " +
                   std::to_string(n_constraints);
    } else {
      for (size_t i = 0; i < ind.f.size() && ind.ok; ++i)
        if (!std::isfinite(ind.f[i])) {
          ind.ok = false;
          ind.reason = "objective " + std::to_string(i) + " is " + (std::isnan(ind.f[i]) ? "NaN" : "infinite");
        }
      for (size_t j = 0; j < ind.g.size() && ind.ok; ++j)
        if (std::isnan(ind.g[j])) {
          ind.ok = false;
          ind.reason = "constraint " + std::to_string(j) + " is NaN";
        }
    }
  }
  if (ind.ok) {
    ind.violation = constraint_violation(ind.g);
    ind.reason.clear();
  } else {
    if (ind.reason.empty()) ind.reason = "evaluation failed";
    ind.violation = kInf;
    if (ind.f.size() != n_objectives) ind.f.assign(n_objectives, kNaN);
  }
}

// ---- sorting and crowding ------------------------------------------------------------------

bool constrained_dominates(const Individual& a, const Individual& b) {
  const bool fa = a.feasible(), fb = b.feasible();
  if (fa && !fb) return true;
  if (!fa && fb) return false;
  if (!fa) return a.violation < b.violation;
  bool strict = false;
  for (size_t i = 0; i < a.f.size(); ++i) {
    if (a.f[i] > b.f[i]) return false;
    if (a.f[i] < b.f[i]) strict = true;
  }
  return strict;
}

namespace {

/// Does t (lexicographically before s, so t[0] <= s[0]) dominate s? Without branches in
/// the loop: in a front of thousands the outcome of each comparison is a coin toss, and a
/// mispredicted branch costs more than the remaining comparisons (twice as fast here).
template <size_t M>
bool dominates_fixed(const double* t, const double* s) {
  bool worse = false, better = false;
  for (size_t k = 0; k < M; ++k) {
    worse |= t[k] > s[k];
    better |= t[k] < s[k];
  }
  return !worse && better;
}

bool dominates_any(const double* t, const double* s, size_t m) {
  bool worse = false, better = false;
  for (size_t k = 0; k < m; ++k) {
    worse |= t[k] > s[k];
    better |= t[k] < s[k];
  }
  return !worse && better;
}

/// Is s dominated by one of the `count` rows of `rows` (M objectives each)? Latest rows first:
/// they are the closest in lexicographic order and the likeliest dominators. (A column layout
/// with blocks the compiler vectorizes measured 2.5 times slower.)
template <size_t M>
bool any_dominates(const double* rows, size_t count, const double* s) {
  for (size_t j = count; j-- > 0;)
    if (dominates_fixed<M>(rows + j * M, s)) return true;
  return false;
}

bool any_dominates(const double* rows, size_t count, const double* s, size_t m) {
  switch (m) {
    case 3: return any_dominates<3>(rows, count, s);
    case 4: return any_dominates<4>(rows, count, s);
    case 5: return any_dominates<5>(rows, count, s);
    case 6: return any_dominates<6>(rows, count, s);
    case 7: return any_dominates<7>(rows, count, s);
    case 8: return any_dominates<8>(rows, count, s);
    default: break;
  }
  for (size_t j = count; j-- > 0;)
    if (dominates_any(rows + j * m, s, m)) return true;
  return false;
}

/// Efficient non-dominated sort with binary search (ENS-BS, Zhang, Tian, Cheng, Jin 2015) of
/// the rows `idx` of the row-major objectives `f` (m per row). Taken in lexicographic order, a
/// row can only be dominated by rows before it; it joins the first front none of whose members
/// dominates it, and by transitivity "front k dominates it" is monotone in k.
std::vector<std::vector<size_t>> ens_sort(const std::vector<double>& f, size_t m, std::vector<size_t> idx) {
  auto row = [&](size_t i) { return f.data() + i * m; };
  std::sort(idx.begin(), idx.end(), [&](size_t a, size_t b) {
    const double *ra = row(a), *rb = row(b);
    for (size_t k = 0; k < m; ++k)
      if (ra[k] != rb[k]) return ra[k] < rb[k];
    return a < b;
  });
  std::vector<std::vector<size_t>> fronts;
  std::vector<std::vector<double>> front_rows;  // members' objectives, contiguous per front
  auto front_dominates = [&](size_t k, const double* s) {
    const std::vector<double>& rows = front_rows[k];
    const size_t count = rows.size() / m;
    // Members of a two-objective front in lexicographic order have falling f2: the last one
    // dominates s if any member does, so two objectives cost O(N log N) in all.
    if (m <= 2) return dominates_any(rows.data() + (count - 1) * m, s, m);
    return any_dominates(rows.data(), count, s, m);
  };
  for (size_t i : idx) {
    const double* s = row(i);
    size_t lo = 0, hi = fronts.size();
    while (lo < hi) {
      const size_t mid = lo + (hi - lo) / 2;
      if (front_dominates(mid, s)) lo = mid + 1;
      else hi = mid;
    }
    if (lo == fronts.size()) {
      fronts.emplace_back();
      front_rows.emplace_back();
    }
    fronts[lo].push_back(i);
    front_rows[lo].insert(front_rows[lo].end(), s, s + m);
  }
  for (auto& fr : fronts) std::sort(fr.begin(), fr.end());
  return fronts;
}

}  // namespace

std::vector<std::vector<size_t>> nondominated_sort(const std::vector<Individual>& pop) {
  const size_t n = pop.size();
  std::vector<std::vector<size_t>> fronts;
  if (n == 0) return fronts;
  const size_t m = pop[0].f.size();
  std::vector<double> f(n * m);
  std::vector<size_t> feasible, infeasible;
  for (size_t i = 0; i < n; ++i) {
    if (pop[i].f.size() != m) throw Error(ExitCode::software, "nondominated_sort: individuals differ in objective count");
    std::copy(pop[i].f.begin(), pop[i].f.end(), f.begin() + long(i * m));
    (pop[i].feasible() ? feasible : infeasible).push_back(i);
  }
  if (!feasible.empty()) fronts = ens_sort(f, m, std::move(feasible));
  // Infeasible: only the violation counts (constraint-domination), ties share a front.
  std::stable_sort(infeasible.begin(), infeasible.end(),
                   [&](size_t a, size_t b) { return pop[a].violation < pop[b].violation; });
  for (size_t k = 0; k < infeasible.size(); ++k) {
    if (k == 0 || pop[infeasible[k]].violation != pop[infeasible[k - 1]].violation) fronts.emplace_back();
    fronts.back().push_back(infeasible[k]);
  }
  for (auto& fr : fronts) std::sort(fr.begin(), fr.end());
  return fronts;
}

void crowding_distance(std::vector<Individual>& pop, const std::vector<size_t>& front) {
  std::vector<size_t> members;
  members.reserve(front.size());
  for (size_t i : front) {
    // A failed evaluation's objectives (NaN, or partial values a log may not keep) never
    // count, so a resumed run crowds exactly as the uninterrupted one.
    bool finite = pop[i].ok;
    for (double v : pop[i].f) finite = finite && std::isfinite(v);
    if (finite) {
      members.push_back(i);
      pop[i].crowding = 0;
    } else {
      pop[i].crowding = 0;
    }
  }
  const size_t n = members.size();
  if (n == 0) return;
  if (n <= 2) {
    for (size_t i : members) pop[i].crowding = kInf;
    return;
  }
  const size_t m = pop[members[0]].f.size();
  std::vector<size_t> order(members);
  for (size_t k = 0; k < m; ++k) {
    // Ties broken by index, so the order (and the extremes) never depend on the sort algorithm.
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) {
      return pop[a].f[k] != pop[b].f[k] ? pop[a].f[k] < pop[b].f[k] : a < b;
    });
    const double lo = pop[order.front()].f[k], hi = pop[order.back()].f[k];
    pop[order.front()].crowding = kInf;
    pop[order.back()].crowding = kInf;
    if (!(hi > lo)) continue;  // a flat objective separates no one
    const double scale = 1 / (hi - lo);
    for (size_t j = 1; j + 1 < n; ++j)
      pop[order[j]].crowding += (pop[order[j + 1]].f[k] - pop[order[j - 1]].f[k]) * scale;
  }
}

std::vector<std::vector<size_t>> rank_and_crowd(std::vector<Individual>& pop) {
  auto fronts = nondominated_sort(pop);
  for (size_t r = 0; r < fronts.size(); ++r) {
    for (size_t i : fronts[r]) pop[i].rank = int(r);
    crowding_distance(pop, fronts[r]);
  }
  return fronts;
}

int crowded_compare(const Individual& a, const Individual& b) {
  if (a.rank != b.rank) return a.rank < b.rank ? 1 : -1;
  if (a.crowding != b.crowding) return a.crowding > b.crowding ? 1 : -1;
  return 0;
}

// ---- variation operators -----------------------------------------------------------------

namespace {

/// The SBX spread factor for one side: the polynomial distribution of Deb and Agrawal,
/// renormalized to the part of it that keeps the child inside the bound (beta = 1 + 2 *
/// distance to the bound / parent distance; alpha = 2 - beta^-(eta + 1)).
double sbx_betaq(double u, double beta, double eta) {
  const double alpha = 2 - std::pow(beta, -(eta + 1));
  if (u <= 1 / alpha) return std::pow(u * alpha, 1 / (eta + 1));
  return std::pow(1 / (2 - u * alpha), 1 / (eta + 1));
}

}  // namespace

void sbx_crossover(const std::vector<double>& p1, const std::vector<double>& p2,
                   const std::vector<double>& lo, const std::vector<double>& hi, double eta_c,
                   double p_variable, Rng& rng, std::vector<double>& c1, std::vector<double>& c2) {
  const size_t n = p1.size();
  c1 = p1;
  c2 = p2;
  for (size_t i = 0; i < n; ++i) {
    if (!(rng.uniform() < p_variable)) continue;
    if (!(std::fabs(p1[i] - p2[i]) > 1e-14)) continue;
    const double y1 = std::min(p1[i], p2[i]), y2 = std::max(p1[i], p2[i]);
    const double d = y2 - y1;
    const double u = rng.uniform();
    double a = 0.5 * ((y1 + y2) - sbx_betaq(u, 1 + 2 * (y1 - lo[i]) / d, eta_c) * d);
    double b = 0.5 * ((y1 + y2) + sbx_betaq(u, 1 + 2 * (hi[i] - y2) / d, eta_c) * d);
    a = std::min(std::max(a, lo[i]), hi[i]);
    b = std::min(std::max(b, lo[i]), hi[i]);
    if (rng.uniform() < 0.5) std::swap(a, b);
    c1[i] = a;
    c2[i] = b;
  }
}

void polynomial_mutation(std::vector<double>& x, const std::vector<double>& lo,
                         const std::vector<double>& hi, double eta_m, double p_variable, Rng& rng) {
  const double power = 1 / (eta_m + 1);
  for (size_t i = 0; i < x.size(); ++i) {
    if (!(rng.uniform() < p_variable)) continue;
    const double range = hi[i] - lo[i];
    if (!(range > 0)) continue;
    const double u = rng.uniform();
    double dq;
    if (u < 0.5) {
      const double xy = 1 - (x[i] - lo[i]) / range;
      const double val = 2 * u + (1 - 2 * u) * std::pow(xy, eta_m + 1);
      dq = std::pow(val, power) - 1;
    } else {
      const double xy = 1 - (hi[i] - x[i]) / range;
      const double val = 2 * (1 - u) + 2 * (u - 0.5) * std::pow(xy, eta_m + 1);
      dq = 1 - std::pow(val, power);
    }
    x[i] = std::min(std::max(x[i] + dq * range, lo[i]), hi[i]);
  }
}

// ---- thread pool ---------------------------------------------------------------------------

ThreadPoolEvaluator::ThreadPoolEvaluator(Function fn, size_t threads)
    : fn_(std::move(fn)), threads_(resolve_thread_count(static_cast<unsigned>(threads))) {}

ThreadPoolEvaluator::ThreadPoolEvaluator(const Problem& problem, size_t threads)
    : ThreadPoolEvaluator([&problem](const std::vector<double>& x) { return problem.evaluate(x); }, threads) {}

void ThreadPoolEvaluator::evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) {
  parallel_for(batch.size(), static_cast<unsigned>(threads_), [&](size_t i, unsigned) {
    Evaluation e;
    try {
      e = fn_(batch[i]);
    } catch (const std::exception& ex) {
      e = Evaluation{};
      e.ok = false;
      e.reason = ex.what();
    } catch (...) {
      e = Evaluation{};
      e.ok = false;
      e.reason = "unknown exception";
    }
    done(i, std::move(e));
  });
}

// ---- the engine ----------------------------------------------------------------------------

namespace {

/// Binary tournament by crowded comparison, a fair coin on ties.
size_t tournament(const std::vector<Individual>& pop, size_t a, size_t b, Rng& rng) {
  const int c = crowded_compare(pop[a], pop[b]);
  if (c > 0) return a;
  if (c < 0) return b;
  return rng.uniform() < 0.5 ? a : b;
}

/// The offspring designs of generation t (Deb's scheme: two shuffles of the population give 2N
/// entrants, N tournaments give N parents, consecutive parents mate).
std::vector<std::vector<double>> make_offspring(const std::vector<Individual>& pop, const Problem& problem,
                                                const Nsga2Settings& s, double pm, size_t t) {
  const size_t n = pop.size();
  Rng rng = Rng::for_generation(s.seed, t);
  std::vector<size_t> entrants(2 * n);
  for (size_t half = 0; half < 2; ++half) {
    size_t* p = entrants.data() + half * n;
    std::iota(p, p + n, size_t(0));
    for (size_t i = n - 1; i > 0; --i) std::swap(p[i], p[rng.below(i + 1)]);  // Fisher-Yates
  }
  std::vector<size_t> parents(n);
  for (size_t k = 0; k < n; ++k) parents[k] = tournament(pop, entrants[2 * k], entrants[2 * k + 1], rng);
  std::vector<std::vector<double>> kids;
  kids.reserve(n + 1);
  std::vector<double> c1, c2;
  for (size_t k = 0; k < n; k += 2) {
    const auto& x1 = pop[parents[k]].x;
    const auto& x2 = pop[parents[k + 1 < n ? k + 1 : 0]].x;
    if (rng.uniform() < s.crossover_probability) {
      sbx_crossover(x1, x2, problem.lower(), problem.upper(), s.eta_c, s.crossover_variable_probability, rng, c1, c2);
    } else {
      c1 = x1;
      c2 = x2;
    }
    polynomial_mutation(c1, problem.lower(), problem.upper(), s.eta_m, pm, rng);
    polynomial_mutation(c2, problem.lower(), problem.upper(), s.eta_m, pm, rng);
    kids.push_back(c1);
    if (kids.size() < n) kids.push_back(c2);
  }
  return kids;
}

/// Evaluates a generation's designs: entries found in the log are taken from it, the others
/// go to the evaluator. Results land by index, so completion order does not matter.
std::vector<Individual> evaluate_generation(const Problem& problem, std::vector<std::vector<double>> xs,
                                            size_t t, size_t n_pop, Evaluator& evaluator,
                                            const Nsga2Callbacks& cb,
                                            const std::unordered_map<std::uint64_t, const Individual*>& log,
                                            size_t& reused, size_t& fresh) {
  const size_t n = xs.size();
  const size_t nobj = problem.n_objectives(), ncon = problem.n_constraints();
  std::vector<Individual> out(n);
  std::vector<size_t> todo;
  for (size_t i = 0; i < n; ++i) {
    Individual& ind = out[i];
    ind.id = std::uint64_t(t) * n_pop + i;
    ind.generation = t;
    ind.x = std::move(xs[i]);
    auto it = log.find(ind.id);
    if (it == log.end()) {
      todo.push_back(i);
      continue;
    }
    const Individual& old = *it->second;
    if (old.x != ind.x)
      throw Error(ExitCode::data, "resume: individual " + std::to_string(ind.id) +
                                      " in the log has other variables than this run makes"
                                      " (another seed, population size, problem or settings?)");
    Evaluation e;
    e.f = old.f;
    e.g = old.g;
    e.ok = old.ok;
    e.reason = old.reason;
    const bool have_g = old.g.size() == ncon;
    apply_evaluation(ind, std::move(e), nobj, ncon);
    if (!have_g && old.ok && ind.f.size() == nobj) {
      // A log that keeps only the violation: take it as it was recorded.
      bool finite = true;
      for (double v : old.f) finite = finite && std::isfinite(v);
      if (finite) {
        ind.ok = true;
        ind.reason.clear();
        ind.violation = old.violation;
      }
    }
    ++reused;
  }
  if (!todo.empty()) {
    std::vector<std::vector<double>> batch(todo.size());
    for (size_t k = 0; k < todo.size(); ++k) batch[k] = out[todo[k]].x;
    // Results are reported in id order, whatever order they complete in: the longest finished
    // prefix goes out as soon as it grows. So the log is the same for any thread count or MPI
    // layout; a kill loses at most the finished designs behind an unfinished one.
    std::mutex mu;
    std::vector<char> seen(todo.size(), 0);
    size_t next = 0;
    auto flush_prefix = [&] {
      for (; next < todo.size() && seen[next]; ++next)
        if (cb.on_evaluated) cb.on_evaluated(out[todo[next]]);
    };
    evaluator.evaluate(batch, [&](size_t k, Evaluation e) {
      if (k >= todo.size()) return;
      Individual& ind = out[todo[k]];
      std::lock_guard<std::mutex> lock(mu);
      if (seen[k]) return;  // an evaluator must report once; a second report is ignored
      apply_evaluation(ind, std::move(e), nobj, ncon);
      seen[k] = 1;
      flush_prefix();
    });
    for (size_t k = 0; k < todo.size(); ++k)
      if (!seen[k]) {
        Individual& ind = out[todo[k]];
        Evaluation e;
        e.ok = false;
        e.reason = "the evaluator returned no result";
        apply_evaluation(ind, std::move(e), nobj, ncon);
        seen[k] = 1;
      }
    flush_prefix();
    fresh += todo.size();
  }
  return out;
}

/// Elitist (mu + lambda) selection: whole fronts while they fit, then the most spread-out
/// members of the front that does not fit (Deb 2002, sec. III-C).
std::vector<Individual> select(std::vector<Individual>&& all, size_t n) {
  auto fronts = rank_and_crowd(all);
  std::vector<Individual> next;
  next.reserve(n);
  for (auto& fr : fronts) {
    if (next.size() >= n) break;
    if (next.size() + fr.size() > n) {
      std::stable_sort(fr.begin(), fr.end(), [&](size_t a, size_t b) { return all[a].crowding > all[b].crowding; });
      fr.resize(n - next.size());
      std::sort(fr.begin(), fr.end());
    }
    for (size_t i : fr) next.push_back(std::move(all[i]));
  }
  return next;
}

void report(const Nsga2Settings& s, const Nsga2Callbacks& cb, size_t t, size_t evaluations, size_t fresh,
            const std::vector<Individual>& pop) {
  if (!cb.on_generation) return;
  Nsga2Progress p;
  p.generation = t;
  p.evaluations = evaluations;
  p.new_evaluations = fresh;
  p.population = &pop;
  for (const auto& ind : pop) {
    if (!ind.feasible()) continue;
    ++p.feasible;
    double sum = 0;
    for (double v : ind.f) sum += v;
    if (std::isnan(p.best_sum) || sum < p.best_sum) {
      p.best_sum = sum;
      p.best_id = ind.id;
    }
  }
  if (!s.reference.empty()) p.hypervolume = front_hypervolume(pop, s.reference);
  cb.on_generation(p);
}

}  // namespace

Nsga2Result run_nsga2(const Problem& problem, const Nsga2Settings& s, Evaluator& evaluator,
                      const Nsga2Callbacks& cb, const std::vector<Individual>& log) {
  const size_t n = s.population;
  if (n < 2) throw usage_error("nsga2: the population must have at least 2 individuals");
  if (!(s.crossover_probability >= 0 && s.crossover_probability <= 1))
    throw usage_error("nsga2: the crossover probability must be in [0, 1]");
  if (!(s.crossover_variable_probability >= 0 && s.crossover_variable_probability <= 1))
    throw usage_error("nsga2: the per-variable crossover probability must be in [0, 1]");
  if (!(s.mutation_probability <= 1)) throw usage_error("nsga2: the mutation probability must be at most 1");
  if (!(s.eta_c >= 0) || !(s.eta_m >= 0)) throw usage_error("nsga2: distribution indices must be >= 0");
  if (!s.reference.empty() && s.reference.size() != problem.n_objectives())
    throw usage_error("nsga2: the reference point needs one value per objective");
  const double pm = s.mutation_probability < 0 ? 1.0 / double(problem.n_variables()) : s.mutation_probability;

  std::unordered_map<std::uint64_t, const Individual*> by_id;
  for (const auto& ind : log) by_id.emplace(ind.id, &ind);  // the first entry of an id wins

  Nsga2Result res;
  const auto& lo = problem.lower();
  const auto& hi = problem.upper();
  // Generation 0: uniform in the box.
  std::vector<std::vector<double>> xs(n, std::vector<double>(problem.n_variables()));
  {
    Rng rng = Rng::for_generation(s.seed, 0);
    for (auto& x : xs)
      for (size_t i = 0; i < x.size(); ++i) x[i] = std::min(hi[i], lo[i] + rng.uniform() * (hi[i] - lo[i]));
  }
  std::vector<Individual> pop =
      evaluate_generation(problem, std::move(xs), 0, n, evaluator, cb, by_id, res.reused, res.new_evaluations);
  res.evaluations = n;
  rank_and_crowd(pop);
  report(s, cb, 0, res.evaluations, res.new_evaluations, pop);
  for (size_t t = 1; t <= s.generations; ++t) {
    auto kids = evaluate_generation(problem, make_offspring(pop, problem, s, pm, t), t, n, evaluator, cb, by_id,
                                    res.reused, res.new_evaluations);
    res.evaluations += n;
    for (auto& k : kids) pop.push_back(std::move(k));
    pop = select(std::move(pop), n);
    report(s, cb, t, res.evaluations, res.new_evaluations, pop);
  }
  res.population = std::move(pop);
  return res;
}

Nsga2Result run_nsga2(const Problem& problem, const Nsga2Settings& settings, size_t threads,
                      const Nsga2Callbacks& callbacks, const std::vector<Individual>& log) {
  ThreadPoolEvaluator ev(problem, threads);
  return run_nsga2(problem, settings, ev, callbacks, log);
}

std::vector<Individual> pareto_front(const std::vector<Individual>& pop) {
  std::vector<Individual> feasible;
  for (const auto& ind : pop)
    if (ind.feasible()) feasible.push_back(ind);
  if (feasible.empty()) return feasible;
  auto fronts = nondominated_sort(feasible);
  std::vector<Individual> out;
  for (size_t i : fronts[0]) out.push_back(feasible[i]);
  std::sort(out.begin(), out.end(), [](const Individual& a, const Individual& b) {
    return a.f != b.f ? a.f < b.f : a.id < b.id;
  });
  return out;
}

double front_hypervolume(const std::vector<Individual>& pop, const std::vector<double>& reference) {
  std::vector<double> flat;
  for (const auto& ind : pop)
    if (ind.feasible()) flat.insert(flat.end(), ind.f.begin(), ind.f.end());
  if (flat.empty()) return 0;
  return hypervolume_flat(flat, reference);
}

}  // namespace turnfit
