// NSGA-II: sorting and crowding on hand-worked sets, operator statistics, exact hypervolume,
// ZDT and constrained runs, determinism over threads, resume from a cut log, failed evaluations.
#include <catch2/catch.hpp>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <map>
#include <set>
#include <stdexcept>

#include "../support.hpp"
#include "turnfit/optimize/hypervolume.hpp"
#include "turnfit/optimize/nsga2.hpp"

using namespace turnfit;
using turnfit::test::error_code;

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

Individual ind(std::vector<double> f, double violation = 0, bool ok = true) {
  Individual i;
  i.f = std::move(f);
  i.violation = ok ? violation : kInf;
  i.ok = ok;
  return i;
}

/// Fronts by peeling: the individuals no remaining one constraint-dominates, again and again
/// (the definition, O(N^3)).
std::vector<std::vector<size_t>> peel(const std::vector<Individual>& pop) {
  std::vector<std::vector<size_t>> fronts;
  std::vector<bool> done(pop.size(), false);
  size_t left = pop.size();
  while (left > 0) {
    std::vector<size_t> front;
    for (size_t i = 0; i < pop.size(); ++i) {
      if (done[i]) continue;
      bool dominated = false;
      for (size_t j = 0; j < pop.size() && !dominated; ++j)
        dominated = !done[j] && j != i && constrained_dominates(pop[j], pop[i]);
      if (!dominated) front.push_back(i);
    }
    for (size_t i : front) done[i] = true;
    left -= front.size();
    fronts.push_back(front);
  }
  return fronts;
}

/// Union of the boxes [p, ref] by inclusion-exclusion over all subsets (exact, small sets).
double hv_inclusion_exclusion(const std::vector<std::vector<double>>& pts, const std::vector<double>& ref) {
  const size_t n = pts.size(), d = ref.size();
  double total = 0;
  for (unsigned mask = 1; mask < (1u << n); ++mask) {
    std::vector<double> corner(d, -kInf);
    int bits = 0;
    for (size_t i = 0; i < n; ++i)
      if (mask & (1u << i)) {
        ++bits;
        for (size_t k = 0; k < d; ++k) corner[k] = std::max(corner[k], pts[i][k]);
      }
    double v = 1;
    for (size_t k = 0; k < d; ++k) v *= std::max(0.0, ref[k] - corner[k]);
    total += (bits % 2 ? 1 : -1) * v;
  }
  return total;
}

/// Bitwise equality of two populations (ids, variables, results, ranks and crowding).
void require_same_population(const std::vector<Individual>& a, const std::vector<Individual>& b) {
  REQUIRE(a.size() == b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    INFO("individual " << i);
    REQUIRE(a[i].id == b[i].id);
    REQUIRE(a[i].generation == b[i].generation);
    REQUIRE(a[i].x == b[i].x);
    REQUIRE(a[i].f == b[i].f);
    REQUIRE(a[i].violation == b[i].violation);
    REQUIRE(a[i].ok == b[i].ok);
    REQUIRE(a[i].rank == b[i].rank);
    REQUIRE(a[i].crowding == b[i].crowding);
  }
}

/// Evaluates a batch back to front on the calling thread (completion order reversed).
class ReverseEvaluator : public Evaluator {
 public:
  explicit ReverseEvaluator(const Problem& p) : p_(p) {}
  void evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) override {
    for (size_t i = batch.size(); i-- > 0;) done(i, p_.evaluate(batch[i]));
  }

 private:
  const Problem& p_;
};

}  // namespace

TEST_CASE("Rng: reproducible, per-generation streams, uniform", "[nsga2]") {
  Rng a(42), b(42), c(43);
  const auto a1 = a.next();
  CHECK(a1 == b.next());
  CHECK(a1 != c.next());
  Rng g1 = Rng::for_generation(7, 1), g1b = Rng::for_generation(7, 1), g2 = Rng::for_generation(7, 2);
  const auto v = g1.next();
  CHECK(v == g1b.next());
  CHECK(v != g2.next());
  CHECK(Rng::for_generation(8, 1).next() != v);
  Rng r(1);
  double sum = 0, lo = 1, hi = 0;
  std::vector<int> counts(7, 0);
  const int n = 200000;
  for (int i = 0; i < n; ++i) {
    const double u = r.uniform();
    sum += u;
    lo = std::min(lo, u);
    hi = std::max(hi, u);
    ++counts[r.below(7)];
  }
  CHECK(lo >= 0);
  CHECK(hi < 1);
  CHECK(sum / n == Approx(0.5).epsilon(0).margin(0.003));
  for (int c7 : counts) CHECK(double(c7) / n == Approx(1.0 / 7).epsilon(0).margin(0.004));
}

TEST_CASE("constraint-domination: feasible first, then the violation, then Pareto", "[nsga2]") {
  CHECK(constrained_dominates(ind({1, 1}), ind({2, 2})));
  CHECK_FALSE(constrained_dominates(ind({1, 3}), ind({2, 2})));
  CHECK_FALSE(constrained_dominates(ind({1, 1}), ind({1, 1})));  // equal: neither
  CHECK(constrained_dominates(ind({1, 1}), ind({1, 2})));
  CHECK(constrained_dominates(ind({9, 9}), ind({0, 0}, 0.1)));   // feasible beats infeasible
  CHECK(constrained_dominates(ind({9, 9}, 0.1), ind({0, 0}, 0.2)));
  CHECK_FALSE(constrained_dominates(ind({0, 0}, 0.2), ind({9, 9}, 0.2)));
  CHECK(constrained_dominates(ind({9, 9}, 5), ind({0, 0}, 0, false)));  // failed comes last
  CHECK_FALSE(constrained_dominates(ind({0, 0}, 0, false), ind({1, 1}, 0, false)));
}

TEST_CASE("non-dominated sort on hand-worked sets", "[nsga2]") {
  SECTION("two objectives with a duplicate") {
    //                      A       B       C       D       E       F (=B)  G
    std::vector<Individual> pop{ind({1, 4}), ind({2, 2}), ind({4, 1}), ind({3, 3}),
                                ind({4, 4}), ind({2, 2}), ind({5, 5})};
    auto fronts = nondominated_sort(pop);
    REQUIRE(fronts == std::vector<std::vector<size_t>>{{0, 1, 2, 5}, {3}, {4}, {6}});
  }
  SECTION("constraints: infeasible by violation, ties share a front, failures last") {
    std::vector<Individual> pop{ind({0, 0}, 0.5),  ind({3, 3}),        ind({10, 10}, 0.2),
                                ind({9, 9}, 0.5),  ind({0, 0}, 0, false), ind({1, 5}),
                                ind({5, 5}),       ind({-1, -1}, 0, false)};
    auto fronts = nondominated_sort(pop);
    REQUIRE(fronts == std::vector<std::vector<size_t>>{{1, 5}, {6}, {2}, {0, 3}, {4, 7}});
    rank_and_crowd(pop);
    CHECK(pop[4].rank == 4);
    CHECK(pop[2].rank == 2);
  }
  SECTION("three objectives") {
    std::vector<Individual> pop{ind({1, 2, 3}), ind({3, 2, 1}), ind({2, 2, 2}), ind({2, 3, 3}),
                                ind({3, 3, 3}), ind({1, 2, 3}), ind({0, 5, 5}), ind({4, 4, 4})};
    auto fronts = nondominated_sort(pop);
    REQUIRE(fronts == std::vector<std::vector<size_t>>{{0, 1, 2, 5, 6}, {3}, {4}, {7}});
  }
}

TEST_CASE("non-dominated sort agrees with peeling on random sets with ties", "[nsga2]") {
  Rng rng(11);
  for (size_t m : {2, 3, 4, 6, 9}) {
    for (int rep = 0; rep < 4; ++rep) {
      std::vector<Individual> pop;
      const size_t n = 150;
      for (size_t i = 0; i < n; ++i) {
        std::vector<double> f(m);
        for (auto& v : f) v = double(rng.below(rep % 2 ? 4 : 50));  // coarse values: many ties
        const double u = rng.uniform();
        pop.push_back(u < 0.7 ? ind(f) : u < 0.9 ? ind(f, double(rng.below(5) + 1)) : ind(f, 0, false));
      }
      INFO("m = " << m << ", rep " << rep);
      REQUIRE(nondominated_sort(pop) == peel(pop));
    }
  }
}

TEST_CASE("crowding distance on hand-worked fronts", "[nsga2]") {
  std::vector<Individual> pop{ind({0, 4}), ind({1, 2}), ind({3, 1}), ind({4, 0})};
  crowding_distance(pop, {0, 1, 2, 3});
  CHECK(pop[0].crowding == kInf);
  CHECK(pop[3].crowding == kInf);
  CHECK(pop[1].crowding == Approx(0.75 + 0.75));  // f1: (3 - 0)/4, f2: (4 - 1)/4
  CHECK(pop[2].crowding == Approx(0.75 + 0.5));   // f1: (4 - 1)/4, f2: (2 - 0)/4

  std::vector<Individual> dup{ind({0, 1}), ind({0.5, 0.5}), ind({0.5, 0.5}), ind({1, 0})};
  crowding_distance(dup, {0, 1, 2, 3});
  CHECK(dup[1].crowding == Approx(1.0));
  CHECK(dup[2].crowding == Approx(1.0));

  std::vector<Individual> two{ind({0, 1}), ind({1, 0})};
  crowding_distance(two, {0, 1});
  CHECK(two[0].crowding == kInf);
  CHECK(two[1].crowding == kInf);

  // A flat objective separates no one; a NaN objective (failed evaluation) gets 0.
  std::vector<Individual> flat{ind({1, 0}), ind({1, 1}), ind({1, 3}), ind({1, 4}),
                               ind({std::nan(""), 2}, 0, false)};
  crowding_distance(flat, {0, 1, 2, 3, 4});
  CHECK(flat[1].crowding == Approx(0.75));
  CHECK(flat[2].crowding == Approx(0.75));
  CHECK(flat[4].crowding == 0);

  // A failed evaluation's finite objectives do not count either (a log may not keep them).
  std::vector<Individual> failed{ind({0, 4}, 0, false), ind({1, 2}, 0, false), ind({3, 1}, 0, false),
                                 ind({4, 0}, 0, false), ind({2, 1.5}, 0, false)};
  crowding_distance(failed, {0, 1, 2, 3, 4});
  for (const auto& f : failed) CHECK(f.crowding == 0);

  Individual a = ind({0, 0}), b = ind({0, 0});
  a.rank = 0, b.rank = 1, a.crowding = 0, b.crowding = 5;
  CHECK(crowded_compare(a, b) == 1);
  b.rank = 0;
  CHECK(crowded_compare(a, b) == -1);
  a.crowding = 5;
  CHECK(crowded_compare(a, b) == 0);
}

TEST_CASE("SBX: children in bounds, mean kept, spread distributed as eta says", "[nsga2]") {
  Rng rng(3);
  std::vector<double> c1, c2;
  SECTION("bounds near the parents") {
    const std::vector<double> lo{0, -1}, hi{1, 1};
    for (int i = 0; i < 20000; ++i) {
      const std::vector<double> p1{rng.uniform() * 0.02, 1 - rng.uniform() * 0.02};
      const std::vector<double> p2{rng.uniform(), 2 * rng.uniform() - 1};
      sbx_crossover(p1, p2, lo, hi, 2, 1.0, rng, c1, c2);
      for (size_t k = 0; k < 2; ++k) {
        REQUIRE(c1[k] >= lo[k]);
        REQUIRE(c1[k] <= hi[k]);
        REQUIRE(c2[k] >= lo[k]);
        REQUIRE(c2[k] <= hi[k]);
      }
    }
  }
  SECTION("far bounds: the unbounded distribution") {
    const double eta = 20;
    const std::vector<double> lo{-1e6}, hi{1e6}, p1{0.4}, p2{0.6};
    const int n = 200000;
    double mean = 0;
    int le1 = 0, le09 = 0, gt11 = 0, first_low = 0;
    for (int i = 0; i < n; ++i) {
      sbx_crossover(p1, p2, lo, hi, eta, 1.0, rng, c1, c2);
      mean += 0.5 * (c1[0] + c2[0]);
      const double beta = std::fabs(c2[0] - c1[0]) / 0.2;
      le1 += beta <= 1;
      le09 += beta <= 0.9;
      gt11 += beta > 1.1;
      first_low += c1[0] < c2[0];
    }
    CHECK(mean / n == Approx(0.5).epsilon(0).margin(1e-6));
    // P(beta <= b) = b^(eta+1)/2 for b <= 1, P(beta > b) = b^-(eta+1)/2 for b >= 1.
    CHECK(double(le1) / n == Approx(0.5).epsilon(0).margin(0.004));
    CHECK(double(le09) / n == Approx(0.5 * std::pow(0.9, eta + 1)).epsilon(0).margin(0.002));
    CHECK(double(gt11) / n == Approx(0.5 * std::pow(1.1, -(eta + 1))).epsilon(0).margin(0.002));
    CHECK(double(first_low) / n == Approx(0.5).epsilon(0).margin(0.004));  // sides swapped half the time
  }
  SECTION("per-variable probability and equal parents") {
    const std::vector<double> lo(1000, 0.0), hi(1000, 1.0), p1(1000, 0.2), p2(1000, 0.8);
    sbx_crossover(p1, p2, lo, hi, 20, 0.5, rng, c1, c2);
    int crossed = 0;
    for (size_t k = 0; k < 1000; ++k) crossed += c1[k] != p1[k] && c1[k] != p2[k];
    CHECK(crossed == Approx(500).epsilon(0).margin(60));
    sbx_crossover(p1, p1, lo, hi, 20, 1.0, rng, c1, c2);
    CHECK(c1 == p1);
    CHECK(c2 == p1);
  }
}

TEST_CASE("polynomial mutation: in bounds, rate and distribution", "[nsga2]") {
  Rng rng(5);
  const double eta = 20;
  SECTION("at the bounds") {
    const std::vector<double> lo{0, 2}, hi{1, 3};
    for (int i = 0; i < 20000; ++i) {
      std::vector<double> x{i % 2 ? 0.0 : 1.0, i % 3 ? 2.0 : 3.0};
      polynomial_mutation(x, lo, hi, eta, 1.0, rng);
      REQUIRE(x[0] >= 0);
      REQUIRE(x[0] <= 1);
      REQUIRE(x[1] >= 2);
      REQUIRE(x[1] <= 3);
    }
  }
  SECTION("in the middle: P(|dx| > d) = (1 - d)^(eta + 1)") {
    const std::vector<double> lo{0}, hi{1};
    const int n = 200000;
    double mean = 0;
    int gt005 = 0, gt01 = 0;
    for (int i = 0; i < n; ++i) {
      std::vector<double> x{0.5};
      polynomial_mutation(x, lo, hi, eta, 1.0, rng);
      mean += x[0];
      gt005 += std::fabs(x[0] - 0.5) > 0.05;
      gt01 += std::fabs(x[0] - 0.5) > 0.1;
    }
    CHECK(mean / n == Approx(0.5).epsilon(0).margin(6e-4));  // 5 sigma
    CHECK(double(gt005) / n == Approx(std::pow(0.95, eta + 1)).epsilon(0).margin(0.004));
    CHECK(double(gt01) / n == Approx(std::pow(0.9, eta + 1)).epsilon(0).margin(0.003));
  }
  SECTION("rate") {
    const std::vector<double> lo(1000, 0.0), hi(1000, 1.0);
    std::vector<double> x(1000, 0.5);
    polynomial_mutation(x, lo, hi, eta, 0.1, rng);
    int changed = 0;
    for (double v : x) changed += v != 0.5;
    CHECK(changed == Approx(100).epsilon(0).margin(35));
    std::vector<double> y(1000, 0.5);
    polynomial_mutation(y, lo, hi, eta, 0.0, rng);
    CHECK(y == std::vector<double>(1000, 0.5));
  }
}

TEST_CASE("hypervolume: hand-worked values", "[nsga2][hypervolume]") {
  CHECK(hypervolume({{1, 3}, {2, 2}, {3, 1}}, {4, 4}) == Approx(6));
  // Dominated, duplicated and outside points add nothing.
  CHECK(hypervolume({{1, 3}, {2, 2}, {3, 1}, {3, 3}, {2, 2}, {5, 0}, {0, 4}}, {4, 4}) == Approx(6));
  CHECK(hypervolume({}, {1, 1}) == 0);
  CHECK(hypervolume({{0.5}}, {2}) == Approx(1.5));
  CHECK(hypervolume({{1, 1, 1}}, {2, 3, 4}) == Approx(6));
  CHECK(hypervolume({{0, 0, 1}, {1, 1, 0}}, {2, 2, 2}) == Approx(5));  // 4 + 2 - 1
  CHECK(hypervolume({{0, 0, 1, 1}, {1, 1, 0, 0}}, {2, 2, 2, 2}) == Approx(4 + 4 - 1));
  CHECK(hypervolume({{0, 0, 0, 0, 0}}, {1, 2, 3, 1, 2}) == Approx(12));
  CHECK(hypervolume({{std::nan(""), 0}}, {1, 1}) == 0);
  std::string msg;
  CHECK(error_code([] { hypervolume({{1, 2, 3}}, {4, 4}); }, &msg) == 64);
}

TEST_CASE("hypervolume agrees with inclusion-exclusion in 2 to 6 dimensions", "[nsga2][hypervolume]") {
  Rng rng(9);
  for (size_t d = 2; d <= 6; ++d) {
    for (int rep = 0; rep < 6; ++rep) {
      std::vector<std::vector<double>> pts;
      for (int i = 0; i < 11; ++i) {
        std::vector<double> p(d);
        for (auto& v : p) v = rep % 2 ? double(rng.below(4)) * 0.25 : rng.uniform();  // ties when coarse
        pts.push_back(p);
      }
      const std::vector<double> ref(d, 1.0);
      INFO("d = " << d << ", rep " << rep);
      CHECK(hypervolume(pts, ref) == Approx(hv_inclusion_exclusion(pts, ref)).epsilon(1e-12).margin(1e-14));
    }
  }
}

TEST_CASE("hypervolume agrees with Monte Carlo in 3-D and 4-D", "[nsga2][hypervolume]") {
  Rng rng(21);
  for (size_t d : {3, 4}) {
    // 60 points near the sphere front: mostly non-dominated.
    std::vector<std::vector<double>> pts;
    for (int i = 0; i < 60; ++i) {
      std::vector<double> p(d);
      double r = 0;
      for (auto& v : p) {
        v = rng.uniform() + 0.05;
        r += v * v;
      }
      for (auto& v : p) v /= std::sqrt(r) * (0.95 + 0.1 * rng.uniform());
      pts.push_back(p);
    }
    const std::vector<double> ref(d, 1.1);
    const int n = 400000;
    int hits = 0;
    std::vector<double> q(d);
    for (int s = 0; s < n; ++s) {
      for (auto& v : q) v = 1.1 * rng.uniform();
      for (const auto& p : pts) {
        bool dom = true;
        for (size_t k = 0; k < d && dom; ++k) dom = p[k] <= q[k];
        if (dom) {
          ++hits;
          break;
        }
      }
    }
    const double box = std::pow(1.1, double(d));
    const double frac = double(hits) / n;
    const double sigma = box * std::sqrt(frac * (1 - frac) / n);
    INFO("d = " << d);
    CHECK(std::fabs(hypervolume(pts, ref) - box * frac) < 4 * sigma);
  }
}

TEST_CASE("NSGA-II reaches the ZDT hypervolume targets", "[nsga2][slowish]") {
  Nsga2Settings s;
  s.population = 100;
  s.generations = 250;
  s.seed = 1;
  const std::vector<double> ref{1.1, 1.1};
  // Targets of issue 7 (means over 10 seeds; the engine's 10-seed means are 0.8694, 0.5362,
  // 1.3277, like DEAP's 0.8692, 0.5359, 1.3276).
  for (auto [name, target] : {std::pair<const char*, double>{"ZDT1", 0.865}, {"ZDT2", 0.532}, {"ZDT3", 1.323}}) {
    auto p = make_problem(name);
    auto r = run_nsga2(*p, s, 1);
    INFO(name);
    CHECK(r.evaluations == 100 * 251);
    CHECK(r.new_evaluations == r.evaluations);
    const double hv = front_hypervolume(r.population, ref);
    CHECK(hv >= target);
    // The front lies on the true front.
    std::vector<std::vector<double>> f;
    for (auto& i : pareto_front(r.population)) f.push_back(i.f);
    CHECK(generational_distance(f, p->true_front(2000)) < 2e-3);
  }
}

namespace {
struct ConstrainedCase {
  const char* name;
  size_t generations;
  double gd, igd;
};
// Seed 2, population 100. GD: mean distance to the true front; IGD: how well it is covered.
const ConstrainedCase kConstrained[] = {{"TNK", 100, 4e-3, 0.016}, {"OSY", 250, 0.9, 8}, {"BNH", 100, 0.13, 1.1},
                                        {"SRN", 100, 0.7, 2.4}, {"C2-DTLZ2", 150, 0.018, 0.12}};
Nsga2Result run_constrained(const Problem& p, const ConstrainedCase& c) {
  Nsga2Settings s;
  s.population = 100;
  s.generations = c.generations;
  s.seed = 2;
  return run_nsga2(p, s, 2);
}
}  // namespace

TEST_CASE("NSGA-II on constrained problems ends with every individual feasible on the front", "[nsga2]") {
  // Invariants, no thresholds: constraint domination drives every individual feasible, and a
  // run this long leaves the whole population on its own first front.
  for (const ConstrainedCase& c : kConstrained) {
    auto p = make_problem(c.name);
    auto r = run_constrained(*p, c);
    INFO(c.name);
    for (const auto& i : r.population) REQUIRE(i.feasible());
    REQUIRE(pareto_front(r.population).size() == r.population.size());
  }
}

TEST_CASE("NSGA-II on constrained problems: distance to the true fronts (regression)", "[nsga2][regression]") {
  // Regression: no independent figure exists for GD/IGD at this budget and seed (the
  // literature reports other budgets and metrics), so the thresholds are the engine's own
  // results from 5 seeds, about twice the worst seen; the objectives of OSY, BNH and SRN span
  // 50-250. OSY's IGD reaches 4.4: NSGA-II at this budget often thins out one of its five
  // pieces. Guards the constraint handling and the crowding against regressions that leave
  // the population feasible but off the front or bunched on a piece of it; the true fronts
  // (problems.cpp) are independent, analytic.
  for (const ConstrainedCase& c : kConstrained) {
    auto p = make_problem(c.name);
    auto r = run_constrained(*p, c);
    INFO(c.name);
    std::vector<std::vector<double>> f;
    for (auto& i : pareto_front(r.population)) f.push_back(i.f);
    auto truth = p->true_front(4000);
    CHECK(generational_distance(f, truth) < c.gd);
    // Spread along the front, not collapsed to a piece of it.
    CHECK(inverted_generational_distance(f, truth) < c.igd);
  }
}

TEST_CASE("NSGA-II: the same seed gives the same population on 1 and 2 threads", "[nsga2]") {
  auto p = make_problem("ZDT3", 12);
  Nsga2Settings s;
  s.population = 60;
  s.generations = 30;
  s.seed = 99;
  auto r1 = run_nsga2(*p, s, 1);
  auto r2 = run_nsga2(*p, s, 2);
  require_same_population(r1.population, r2.population);
  ReverseEvaluator rev(*p);
  auto r3 = run_nsga2(*p, s, rev);
  require_same_population(r1.population, r3.population);
  s.seed = 100;
  auto r4 = run_nsga2(*p, s, 2);
  CHECK(r4.population[0].x != r1.population[0].x);
}

TEST_CASE("NSGA-II: resume from a log cut mid-generation ends like the uninterrupted run", "[nsga2]") {
  auto p = make_problem("TNK");
  Nsga2Settings s;
  s.population = 40;
  s.generations = 25;
  s.seed = 5;
  std::vector<Individual> log;
  Nsga2Callbacks cb;
  cb.on_evaluated = [&](const Individual& i) { log.push_back(i); };
  auto full = run_nsga2(*p, s, 2, cb);
  REQUIRE(log.size() == 40 * 26);
  for (const auto& i : log) CHECK(i.rank == -1);

  for (size_t cut : {size_t(0), size_t(17), size_t(40 * 7 + 13), size_t(40 * 26 - 1), size_t(40 * 26)}) {
    INFO("cut after " << cut << " evaluations");
    std::vector<Individual> part(log.begin(), log.begin() + long(cut));
    std::vector<Individual> added;
    Nsga2Callbacks cb2;
    cb2.on_evaluated = [&](const Individual& i) { added.push_back(i); };
    size_t progress_calls = 0;
    cb2.on_generation = [&](const Nsga2Progress& pr) {
      CHECK(pr.generation == progress_calls);
      CHECK(pr.evaluations == 40 * (pr.generation + 1));
      ++progress_calls;
    };
    auto resumed = run_nsga2(*p, s, 2, cb2, part);
    require_same_population(full.population, resumed.population);
    CHECK(progress_calls == 26);
    CHECK(resumed.reused == cut);
    CHECK(resumed.new_evaluations == 40 * 26 - cut);
    // No evaluation lost or repeated: the log and the new evaluations partition the ids.
    std::set<std::uint64_t> ids;
    for (const auto& i : part) ids.insert(i.id);
    for (const auto& i : added) REQUIRE(ids.insert(i.id).second);
    CHECK(ids.size() == 40 * 26);
    CHECK(*ids.rbegin() == 40 * 26 - 1);
  }

  SECTION("a shuffled log that kept only the violation") {
    std::vector<Individual> part(log.begin(), log.begin() + 300);
    Rng rng(1);
    for (size_t i = part.size() - 1; i > 0; --i) std::swap(part[i], part[rng.below(i + 1)]);
    for (auto& i : part) i.g.clear();
    auto resumed = run_nsga2(*p, s, 1, {}, part);
    require_same_population(full.population, resumed.population);
  }
  SECTION("a log from another seed is refused") {
    Nsga2Settings other = s;
    other.seed = 6;
    std::string msg;
    CHECK(error_code([&] { run_nsga2(*p, other, 1, {}, log); }, &msg) == 65);
    CHECK(msg.find("resume") != std::string::npos);
  }
}

namespace {

/// ZDT1 on 6 variables that crashes, returns NaN or throws in parts of the box.
class FlakyZdt1 : public Problem {
 public:
  FlakyZdt1() : Problem("flaky", std::vector<double>(6, 0.0), std::vector<double>(6, 1.0), 2, 0), zdt_(make_problem("ZDT1", 6)) {}
  Evaluation evaluate(const std::vector<double>& x) const override {
    if (x[1] > 0.9) {
      Evaluation e;
      e.ok = false;
      e.reason = "simulated crash";
      return e;
    }
    if (x[2] > 0.9) throw std::runtime_error("boom");
    Evaluation e = zdt_->evaluate(x);
    if (x[3] > 0.9) e.f[1] = std::nan("");
    return e;
  }

 private:
  std::unique_ptr<Problem> zdt_;
};

}  // namespace

TEST_CASE("NSGA-II: failed evaluations become infeasible with their reason, the run goes on", "[nsga2]") {
  FlakyZdt1 p;
  Nsga2Settings s;
  s.population = 60;
  s.generations = 40;
  s.seed = 3;
  std::map<std::string, int> reasons;
  Nsga2Callbacks cb;
  size_t first_gen_feasible = 0;
  cb.on_evaluated = [&](const Individual& i) {
    if (!i.ok) {
      ++reasons[i.reason];
      CHECK(i.violation == kInf);
      CHECK(i.f.size() == 2);
    }
  };
  cb.on_generation = [&](const Nsga2Progress& pr) {
    if (pr.generation == 0) first_gen_feasible = pr.feasible;
  };
  auto r = run_nsga2(p, s, 2, cb);
  CHECK(reasons["simulated crash"] > 0);
  CHECK(reasons["boom"] > 0);
  CHECK(reasons["objective 1 is NaN"] > 0);
  CHECK(reasons.size() == 3);
  CHECK(first_gen_feasible < 60);
  CHECK(r.evaluations == 60 * 41);
  // Selection pushed the failures out: the survivors are the feasible ones, on ZDT1's front.
  for (const auto& i : r.population) CHECK(i.ok);
  CHECK(front_hypervolume(r.population, {1.1, 1.1}) > 0.6);

  SECTION("a population that is all failures still runs") {
    ThreadPoolEvaluator fail([](const std::vector<double>&) -> Evaluation { throw std::runtime_error("down"); }, 2);
    Nsga2Settings t = s;
    t.generations = 2;
    auto rf = run_nsga2(p, t, fail);
    for (const auto& i : rf.population) {
      CHECK_FALSE(i.ok);
      CHECK(i.reason == "down");
    }
    CHECK(pareto_front(rf.population).empty());
    CHECK(front_hypervolume(rf.population, {1.1, 1.1}) == 0);
  }
  SECTION("wrong sizes from an evaluator are failures") {
    Individual i;
    apply_evaluation(i, Evaluation{{1.0}, {}, true, ""}, 2, 0);
    CHECK_FALSE(i.ok);
    CHECK(i.reason.find("1 objectives, expected 2") != std::string::npos);
    apply_evaluation(i, Evaluation{{1.0, 2.0}, {0.5, -1}, true, ""}, 2, 2);
    CHECK(i.ok);
    CHECK(i.violation == 0.5);
    apply_evaluation(i, Evaluation{{1.0, kInf}, {}, true, ""}, 2, 0);
    CHECK(i.reason == "objective 1 is infinite");
  }
}

TEST_CASE("NSGA-II: progress reports and the final front", "[nsga2]") {
  auto p = make_problem("ZDT1", 10);
  Nsga2Settings s;
  s.population = 40;
  s.generations = 20;
  s.reference = {1.1, 1.1};
  std::vector<Nsga2Progress> seen;
  std::vector<double> last_sums;
  Nsga2Callbacks cb;
  cb.on_generation = [&](const Nsga2Progress& pr) {
    seen.push_back(pr);
    double best = kInf;
    for (const auto& i : *pr.population) best = std::min(best, i.f[0] + i.f[1]);
    last_sums.push_back(best);
  };
  auto r = run_nsga2(*p, s, 2, cb);
  REQUIRE(seen.size() == 21);
  for (size_t t = 0; t < seen.size(); ++t) {
    CHECK(seen[t].generation == t);
    CHECK(seen[t].evaluations == 40 * (t + 1));
    CHECK(seen[t].new_evaluations == 40 * (t + 1));
    CHECK(seen[t].feasible == 40);
    CHECK(seen[t].best_sum == last_sums[t]);
  }
  CHECK(seen.back().hypervolume == front_hypervolume(r.population, s.reference));
  CHECK(seen.back().hypervolume > seen.front().hypervolume);
  auto front = pareto_front(r.population);
  REQUIRE(!front.empty());
  for (size_t i = 1; i < front.size(); ++i) CHECK(front[i - 1].f <= front[i].f);
  for (const auto& a : front)
    for (const auto& b : r.population) CHECK_FALSE(constrained_dominates(b, a));
  // Ids: generation * population + index, unique.
  std::set<std::uint64_t> ids;
  for (const auto& i : r.population) {
    CHECK(i.id / 40 == i.generation);
    CHECK(ids.insert(i.id).second);
  }
  CHECK(error_code([&] {
          Nsga2Settings bad = s;
          bad.population = 1;
          run_nsga2(*p, bad, 1);
        }) == 64);
  CHECK(error_code([&] {
          Nsga2Settings bad = s;
          bad.reference = {1, 1, 1};
          run_nsga2(*p, bad, 1);
        }) == 64);
}

TEST_CASE("NSGA-II with an odd population and a 3-objective problem", "[nsga2]") {
  auto p = make_problem("DTLZ2");
  Nsga2Settings s;
  s.population = 51;
  s.generations = 60;
  auto r = run_nsga2(*p, s, 2);
  REQUIRE(r.population.size() == 51);
  CHECK(r.evaluations == 51 * 61);
  std::vector<std::vector<double>> f;
  for (auto& i : pareto_front(r.population)) f.push_back(i.f);
  CHECK(generational_distance(f, p->true_front(2000)) < 0.05);
}
