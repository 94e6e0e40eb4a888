// Benchmark of the NSGA-II engine (issue 7): hypervolume on ZDT/DTLZ2 over seeds, constrained
// fronts (feasibility, IGD, GD), and the engine's own time per generation at population 8000,
// each side by side with pagmo's nsga2 in the same process when built with pagmo.
//
//   bench_nsga [--seeds S] [--constrained-seeds S] [--overhead-population N]
//              [--overhead-generations G] [--only zdt|constrained|overhead|check]
//
// Prints markdown tables (bench/RESULTS.md). Both tools run turnfit's own problem code (pagmo
// through a user-defined problem that calls turnfit::Problem::evaluate), on one thread, with
// the same budget (population 100, 250 generations: 25100 evaluations) and the same operators
// (crossover probability 0.9, eta_c 20, per-variable mutation probability 1/n, eta_m 20); both
// fronts are scored by turnfit::hypervolume (one front is cross-checked against
// pagmo::hypervolume). pagmo is optional: without it (TURNFIT_HAVE_PAGMO undefined) the pagmo
// columns read "-".
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <memory>
#include <numeric>
#include <string>
#include <vector>

#include "turnfit/optimize/hypervolume.hpp"
#include "turnfit/optimize/nsga2.hpp"
#include "turnfit/optimize/problems.hpp"

#ifdef TURNFIT_HAVE_PAGMO
#include <pagmo/algorithm.hpp>
#include <pagmo/algorithms/nsga2.hpp>
#include <pagmo/population.hpp>
#include <pagmo/problem.hpp>
#include <pagmo/problems/dtlz.hpp>
#include <pagmo/problems/zdt.hpp>
#include <pagmo/utils/hypervolume.hpp>
#endif

using namespace turnfit;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

/// CPU seconds of the whole process (every thread): unlike wall time, barely inflated when
/// other work shares the cores.
double cpu_now() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

struct Stats {
  double mean = NAN, min = NAN, max = NAN, std = NAN;
};

Stats stats(const std::vector<double>& v) {
  Stats s;
  if (v.empty()) return s;
  s.mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
  s.min = *std::min_element(v.begin(), v.end());
  s.max = *std::max_element(v.begin(), v.end());
  double ss = 0;
  for (double x : v) ss += (x - s.mean) * (x - s.mean);
  s.std = v.size() > 1 ? std::sqrt(ss / double(v.size() - 1)) : 0;  // sample std
  return s;
}

double median(std::vector<double> v) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/// The objective vectors of the feasible individuals.
std::vector<std::vector<double>> feasible_objectives(const std::vector<Individual>& pop) {
  std::vector<std::vector<double>> out;
  for (const auto& ind : pop)
    if (ind.feasible()) out.push_back(ind.f);
  return out;
}

/// Counts the time spent in problem evaluations, so that the engine's own time is the rest.
class TimedEvaluator : public Evaluator {
 public:
  explicit TimedEvaluator(const Problem& p) : inner_(p, 1) {}
  void evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) override {
    const auto t0 = Clock::now();
    const double c0 = cpu_now();
    inner_.evaluate(batch, done);
    cpu_seconds_ += cpu_now() - c0;
    seconds_ += seconds_since(t0);
  }
  double seconds_ = 0, cpu_seconds_ = 0;

 private:
  ThreadPoolEvaluator inner_;
};

struct RunResult {
  std::vector<std::vector<double>> f;  // final population's objectives (feasible only)
  size_t population = 0, feasible = 0;
  double seconds = 0, cpu_seconds = 0;
};

Nsga2Settings settings(size_t pop, size_t gens, std::uint64_t seed) {
  Nsga2Settings s;
  s.population = pop;
  s.generations = gens;
  s.seed = seed;
  s.crossover_probability = 0.9;
  s.eta_c = 20;
  s.mutation_probability = -1;  // 1/n
  s.eta_m = 20;
  return s;
}

RunResult run_turnfit(const Problem& p, size_t pop, size_t gens, std::uint64_t seed) {
  RunResult r;
  const auto t0 = Clock::now();
  const double c0 = cpu_now();
  auto res = run_nsga2(p, settings(pop, gens, seed), 1);
  r.cpu_seconds = cpu_now() - c0;
  r.seconds = seconds_since(t0);
  r.f = feasible_objectives(res.population);
  r.population = res.population.size();
  r.feasible = r.f.size();
  return r;
}

#ifdef TURNFIT_HAVE_PAGMO
/// pagmo's view of a turnfit problem (same code evaluates both tools' designs). Times its
/// fitness calls so that pagmo's engine time can be separated from evaluation.
struct PagmoUdp {
  std::shared_ptr<const Problem> p;
  std::shared_ptr<double> eval_seconds = std::make_shared<double>(0);
  bool timed = false;
  pagmo::vector_double fitness(const pagmo::vector_double& x) const {
    const auto t0 = timed ? Clock::now() : Clock::time_point{};
    Evaluation e = p->evaluate(x);
    pagmo::vector_double out(e.f);
    out.insert(out.end(), e.g.begin(), e.g.end());
    if (timed) *eval_seconds += seconds_since(t0);
    return out;
  }
  std::pair<pagmo::vector_double, pagmo::vector_double> get_bounds() const { return {p->lower(), p->upper()}; }
  pagmo::vector_double::size_type get_nobj() const { return p->n_objectives(); }
  pagmo::vector_double::size_type get_nic() const { return p->n_constraints(); }
  std::string get_name() const { return "turnfit " + p->name(); }
};

pagmo::algorithm pagmo_nsga2(size_t gens, size_t n_variables, unsigned seed) {
  return pagmo::algorithm(pagmo::nsga2(unsigned(gens), 0.9, 20.0, 1.0 / double(n_variables), 20.0, seed));
}

RunResult run_pagmo(std::shared_ptr<const Problem> p, size_t pop, size_t gens, unsigned seed) {
  RunResult r;
  const auto t0 = Clock::now();
  const double c0 = cpu_now();
  pagmo::problem prob{PagmoUdp{p}};
  pagmo::population popu{prob, pop, seed};
  auto algo = pagmo_nsga2(gens, p->n_variables(), seed);
  popu = algo.evolve(popu);
  r.cpu_seconds = cpu_now() - c0;
  r.seconds = seconds_since(t0);
  for (const auto& f : popu.get_f()) r.f.emplace_back(f.begin(), f.begin() + long(p->n_objectives()));
  r.population = r.feasible = r.f.size();
  return r;
}

/// pagmo::hypervolume wants every point strictly better than the reference.
double pagmo_hv(const std::vector<std::vector<double>>& f, const std::vector<double>& ref) {
  std::vector<pagmo::vector_double> pts;
  for (const auto& x : f) {
    bool in = true;
    for (size_t i = 0; i < x.size(); ++i) in = in && x[i] < ref[i];
    if (in) pts.push_back(x);
  }
  if (pts.empty()) return 0;
  return pagmo::hypervolume(pts, true).compute(ref);
}
#endif

std::string fmt(double v, const char* f = "%.4f") {
  if (std::isnan(v)) return "-";
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

// ---- (0) the problems' code against pagmo's own ZDT/DTLZ ---------------------------------------

void check_problems() {
#ifdef TURNFIT_HAVE_PAGMO
  std::printf("### Problem check: turnfit's ZDT/DTLZ2 against pagmo's own zdt/dtlz\n\n");
  std::printf("| problem | n | points | max abs difference of objectives |\n| --- | --- | --- | --- |\n");
  struct C { const char* name; unsigned id; size_t n; bool dtlz; };
  const C cases[] = {{"ZDT1", 1, 30, false}, {"ZDT2", 2, 30, false}, {"ZDT3", 3, 30, false},
                     {"ZDT4", 4, 10, false}, {"ZDT6", 6, 10, false}, {"DTLZ2", 2, 12, true}};
  Rng rng(12345);
  for (const auto& c : cases) {
    auto tp = make_problem(c.name, c.n);
    pagmo::problem pp = c.dtlz ? pagmo::problem(pagmo::dtlz(2, c.n, 3)) : pagmo::problem(pagmo::zdt(c.id, unsigned(c.n)));
    double worst = 0;
    const size_t npts = 1000;
    for (size_t k = 0; k < npts; ++k) {
      std::vector<double> x(c.n);
      for (size_t i = 0; i < c.n; ++i) x[i] = tp->lower()[i] + rng.uniform() * (tp->upper()[i] - tp->lower()[i]);
      auto a = tp->evaluate(x).f;
      auto b = pp.fitness(x);
      for (size_t i = 0; i < a.size(); ++i) worst = std::max(worst, std::abs(a[i] - b[i]));
    }
    std::printf("| %s | %zu | %zu | %.3g |\n", c.name, c.n, npts, worst);
  }
  std::printf("\n");
#endif
}

// ---- (a) hypervolume over seeds ---------------------------------------------------------------

struct HvCase {
  const char* name;
  size_t n;
  double target, deap;  // NaN: none
};

void bench_hypervolume(size_t nseeds) {
  const size_t pop = 100, gens = 250;
  std::printf("### (a) Hypervolume, population %zu x %zu generations, %zu seeds\n\n", pop, gens, nseeds);
  std::printf("Reference point 1.1 in every objective; scored by turnfit::hypervolume on the final population's\n"
              "objectives (the dominated ones add nothing). Time per run (one thread), median over seeds: wall and\n"
              "process CPU seconds; the ratio is of CPU times (wall ratio in brackets), both tools run alternately.\n\n");
  std::printf("| problem | n | tool | HV mean | min | max | std | target | DEAP | wall s/run | CPU s/run | time turnfit/pagmo |\n");
  std::printf("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
  const HvCase cases[] = {{"ZDT1", 30, 0.865, 0.8692}, {"ZDT2", 30, 0.532, 0.5359}, {"ZDT3", 30, 1.323, 1.3276},
                          {"ZDT4", 10, NAN, NAN},      {"ZDT6", 10, NAN, NAN},      {"DTLZ2", 12, NAN, NAN}};
  bool crosschecked = false;
  std::string xcheck;
  for (const auto& c : cases) {
    std::shared_ptr<const Problem> p(make_problem(c.name, c.n));
    const std::vector<double> ref(p->n_objectives(), 1.1);
    std::vector<double> hv_t, hv_p, t_t, t_p, c_t, c_p;
    for (size_t s = 1; s <= nseeds; ++s) {
      auto rt = run_turnfit(*p, pop, gens, s);
      hv_t.push_back(hypervolume(rt.f, ref));
      t_t.push_back(rt.seconds);
      c_t.push_back(rt.cpu_seconds);
#ifdef TURNFIT_HAVE_PAGMO
      auto rp = run_pagmo(p, pop, gens, unsigned(s));
      hv_p.push_back(hypervolume(rp.f, ref));
      t_p.push_back(rp.seconds);
      c_p.push_back(rp.cpu_seconds);
      if (!crosschecked) {
        crosschecked = true;
        xcheck = std::string("Cross-check of the scoring (") + c.name + ", seed " + std::to_string(s) +
                 "): pagmo's front " + fmt(hv_p.back(), "%.12f") + " by turnfit::hypervolume, " +
                 fmt(pagmo_hv(rp.f, ref), "%.12f") + " by pagmo::hypervolume; turnfit's front " +
                 fmt(hv_t.back(), "%.12f") + " and " + fmt(pagmo_hv(rt.f, ref), "%.12f") + ".\n\n";
      }
#endif
    }
    const Stats st = stats(hv_t), sp = stats(hv_p);
    const double mt = median(t_t), mp = median(t_p), ct = median(c_t), cp = median(c_p);
    std::string verdict = std::isnan(c.target) ? "-" : fmt(c.target, "%.3f") + (st.mean >= c.target ? " met" : " **missed**");
    const std::string ratio = std::isnan(mp) ? "-" : fmt(ct / cp, "%.2f") + " (" + fmt(mt / mp, "%.2f") + ")";
    std::printf("| %s | %zu | turnfit | %.4f | %.4f | %.4f | %.4f | %s | %s | %.3f | %.3f | %s |\n", c.name, c.n,
                st.mean, st.min, st.max, st.std, verdict.c_str(), fmt(c.deap).c_str(), mt, ct, ratio.c_str());
#ifdef TURNFIT_HAVE_PAGMO
    std::printf("| %s | %zu | pagmo nsga2 | %.4f | %.4f | %.4f | %.4f | | | %.3f | %.3f | |\n", c.name, c.n, sp.mean,
                sp.min, sp.max, sp.std, mp, cp);
#else
    (void)sp;
    (void)crosschecked;
#endif
    std::fflush(stdout);
  }
  std::printf("\nThe best possible 100-point set on ZDT1 reaches 0.8720; the whole ZDT1 front 1.1^2 - 1/3 = 0.8767;\n"
              "ZDT2 1.21 - 2/3 = 0.5433; DTLZ2 1.331 - pi/6 = %.4f.\n\n", 1.331 - M_PI / 6);
  std::printf("%s", xcheck.c_str());
}

// ---- (b) constrained problems -----------------------------------------------------------------

void bench_constrained(size_t nseeds) {
  const size_t pop = 100, gens = 250;
  std::printf("### (b) Constrained problems, population %zu x %zu generations, seeds 1-%zu (turnfit only)\n\n", pop,
              gens, nseeds);
  std::printf("feasible: of the final population, over all seeds. IGD and GD against true_front(1000), mean over\n"
              "seeds (worst seed in brackets); GD over the final feasible non-dominated set. IGD floor: the IGD of\n"
              "true_front(100) itself (what about 100 points on the front give). gap: the largest distance from a\n"
              "true-front point to the nearest point found, worst seed (a missed part of the front shows here). range:\n"
              "the true front's largest objective range, for scale.\n\n");
  std::printf("| problem | n | m | constraints | feasible | front size (mean) | IGD | IGD floor | GD | gap | range | s/run |\n");
  std::printf("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
  for (const char* name : {"BNH", "TNK", "OSY", "SRN", "C2-DTLZ2"}) {
    std::shared_ptr<const Problem> p(make_problem(name));
    const auto tf = p->true_front(1000);
    double range = 0;
    for (size_t j = 0; j < p->n_objectives(); ++j) {
      double lo = INFINITY, hi = -INFINITY;
      for (const auto& q : tf) lo = std::min(lo, q[j]), hi = std::max(hi, q[j]);
      range = std::max(range, hi - lo);
    }
    const double floor = inverted_generational_distance(p->true_front(100), tf);
    size_t feas = 0, total = 0;
    double gap = 0;
    std::vector<double> igd, gd, fs, secs;
    for (size_t s = 1; s <= nseeds; ++s) {
      auto r = run_turnfit(*p, pop, gens, s);
      feas += r.feasible;
      total += r.population;
      auto nd = nondominated_points(r.f);
      fs.push_back(double(nd.size()));
      igd.push_back(inverted_generational_distance(nd, tf));
      gd.push_back(generational_distance(nd, tf));
      for (const auto& q : tf) {
        double best = INFINITY;
        for (const auto& y : nd) {
          double d2 = 0;
          for (size_t j = 0; j < q.size(); ++j) d2 += (q[j] - y[j]) * (q[j] - y[j]);
          best = std::min(best, d2);
        }
        gap = std::max(gap, std::sqrt(best));
      }
      secs.push_back(r.seconds);
    }
    const Stats si = stats(igd), sg = stats(gd);
    std::printf("| %s | %zu | %zu | %zu | %zu/%zu | %.1f | %.3g (%.3g) | %.3g | %.3g (%.3g) | %.3g | %.3g | %.3f |\n",
                name, p->n_variables(), p->n_objectives(), p->n_constraints(), feas, total, stats(fs).mean, si.mean,
                si.max, floor, sg.mean, sg.max, gap, range, median(secs));
    std::fflush(stdout);
  }
#ifdef TURNFIT_HAVE_PAGMO
  try {
    std::shared_ptr<const Problem> p(make_problem("BNH"));
    run_pagmo(p, 100, 1, 1);
    std::printf("\npagmo's nsga2 accepted BNH (constrained).\n\n");
  } catch (const std::exception& e) {
    std::string msg = e.what();
    // pagmo's messages carry a source location first; keep the last line.
    while (!msg.empty() && msg.back() == '\n') msg.pop_back();
    const auto nl = msg.find_last_of('\n');
    if (nl != std::string::npos) msg = msg.substr(nl + 1);
    std::printf("\npagmo's nsga2 on BNH throws: \"%s\"\n\n", msg.c_str());
  }
#endif
}

// ---- (c) engine overhead ----------------------------------------------------------------------

void bench_overhead(size_t pop, size_t gens) {
  std::printf("### (c) Engine time per generation, population %zu, one thread\n\n", pop);
  std::printf("engine: time of a generation minus the time in problem evaluations (sorting, crowding,\n"
              "tournament, SBX, mutation, selection, bookkeeping), as process CPU seconds (wall in brackets); median\n"
              "over generations 1-%zu (generation 0 excluded: it is only sampling and one sort). eval: wall time in\n"
              "the problem's code per generation (%zu evaluations). pagmo: one evolve() call per generation, its\n"
              "fitness calls timed (wall) inside the problem and subtracted from both its CPU and wall times.\n"
              "Ratio of CPU times.\n\n",
              gens, pop);
  std::printf("| problem | m | turnfit engine s/gen | turnfit eval s/gen | pagmo engine s/gen | pagmo eval s/gen | engine turnfit/pagmo |\n");
  std::printf("| --- | --- | --- | --- | --- | --- | --- |\n");
  struct C { const char* name; size_t m; };
  for (const C c : {C{"ZDT1", 2}, C{"DTLZ2", 6}}) {
    std::shared_ptr<const Problem> p(make_problem(c.name, 0, c.name[0] == 'D' ? c.m : 0));
    // turnfit
    TimedEvaluator ev(*p);
    std::vector<double> eng, engc, evs;
    auto last = Clock::now();
    double last_cpu = cpu_now(), last_eval = 0, last_eval_cpu = 0;
    Nsga2Callbacks cb;
    cb.on_generation = [&](const Nsga2Progress& pr) {
      const auto now = Clock::now();
      const double cpu = cpu_now();
      const double wall = std::chrono::duration<double>(now - last).count();
      const double e = ev.seconds_ - last_eval, ec = ev.cpu_seconds_ - last_eval_cpu;
      if (pr.generation > 0) {
        eng.push_back(wall - e);
        engc.push_back(cpu - last_cpu - ec);
        evs.push_back(e);
      }
      last = now;
      last_cpu = cpu;
      last_eval = ev.seconds_;
      last_eval_cpu = ev.cpu_seconds_;
    };
    last = Clock::now();
    last_cpu = cpu_now();
    run_nsga2(*p, settings(pop, gens, 1), ev, cb);
    const double te = median(eng), tec = median(engc), tv = median(evs);
    double pe = NAN, pec = NAN, pv = NAN;
#ifdef TURNFIT_HAVE_PAGMO
    {
      // One generation per evolve call, so each generation is timed alone (pagmo's nsga2 keeps
      // no state between generations but its random engine, reseeded per call here).
      PagmoUdp udp{p};
      udp.timed = true;
      auto evals = udp.eval_seconds;
      pagmo::problem prob{udp};
      pagmo::population popu{prob, pop, 1u};
      std::vector<double> peng, pengc, pev;
      for (size_t g = 1; g <= gens; ++g) {
        auto algo = pagmo_nsga2(1, p->n_variables(), unsigned(g));
        const double e0 = *evals;
        const auto t0 = Clock::now();
        const double c0 = cpu_now();
        popu = algo.evolve(popu);
        const double cpu = cpu_now() - c0;
        const double wall = seconds_since(t0);
        const double e = *evals - e0;  // shared by every copy of the problem
        peng.push_back(wall - e);
        pengc.push_back(cpu - e);
        pev.push_back(e);
      }
      pe = median(peng);
      pec = median(pengc);
      pv = median(pev);
    }
#endif
    std::printf("| %s | %zu | %.4f (%.4f) | %.4f | %s | %s | %s |\n", c.name, c.m, tec, te, tv,
                std::isnan(pe) ? "-" : (fmt(pec) + " (" + fmt(pe) + ")").c_str(), fmt(pv).c_str(),
                std::isnan(pe) ? "-" : fmt(tec / pec, "%.3f").c_str());
    std::fflush(stdout);
  }
  std::printf("\n");
}

}  // namespace

int main(int argc, char** argv) {
  size_t seeds = 10, cseeds = 5, opop = 8000, ogens = 5;
  std::string only;
  for (int i = 1; i < argc; ++i) {
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "bench_nsga: %s needs a value\n", argv[i]);
        std::exit(64);
      }
      return argv[++i];
    };
    if (!std::strcmp(argv[i], "--seeds")) seeds = std::strtoul(next(), nullptr, 10);
    else if (!std::strcmp(argv[i], "--constrained-seeds")) cseeds = std::strtoul(next(), nullptr, 10);
    else if (!std::strcmp(argv[i], "--overhead-population")) opop = std::strtoul(next(), nullptr, 10);
    else if (!std::strcmp(argv[i], "--overhead-generations")) ogens = std::strtoul(next(), nullptr, 10);
    else if (!std::strcmp(argv[i], "--only")) only = next();
    else {
      std::fprintf(stderr,
                   "usage: bench_nsga [--seeds S] [--constrained-seeds S] [--overhead-population N]\n"
                   "                  [--overhead-generations G] [--only zdt|constrained|overhead|check]\n");
      return 64;
    }
  }
#ifdef TURNFIT_HAVE_PAGMO
  std::printf("pagmo: linked (nsga2 cr 0.9, eta_c 20, m 1/n, eta_m 20)\n\n");
#else
  std::printf("pagmo: not built in (configure with libpagmo-dev installed for its columns)\n\n");
#endif
  if (only.empty() || only == "check") check_problems();
  if (only.empty() || only == "zdt") bench_hypervolume(seeds);
  if (only.empty() || only == "constrained") bench_constrained(cseeds);
  if (only.empty() || only == "overhead") bench_overhead(opop, ogens);
  return 0;
}
