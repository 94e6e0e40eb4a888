// bench_evaluation: what one design of a turn-pattern problem costs (issues 15 and 17), and where
// the time goes: ring8 with its 18 trim coils excited (truth-dvars.json's design), 182 turns,
// on one thread. Model build and track separately, with the coils summed into one table
// (TrimCoilSum, the default) and one by one (the reference, same process), and the turns of the
// two compared. Then the whole in-process evaluation (TurnPatternProblem::simulate: model,
// track, match, objectives) against the shipped measurement.
//
// Usage: bench_evaluation [--repeat 20]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <thread>
#include <unistd.h>
#include <string>
#include <vector>

#include "turnfit/io/parallel.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/optimize/problem_file.hpp"
#include "turnfit/optimize/turn_problem.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

namespace {

std::string share(const std::string& f) { return std::string(TURNFIT_SOURCE_SHARE) + "/ring8/" + f; }

double seconds(Clock::time_point a) { return std::chrono::duration<double>(Clock::now() - a).count(); }

struct Timing {
  double build_ms = 0, track_ms = 0;
  std::vector<TurnRecord> turns;
};

Timing time_track(const Machine& m, const ModelFiles& files, bool sum, int repeat, bool reference = false) {
  ModelOptions opt;
  opt.sum_coils = sum;
  Timing t;
  const ParticleState s0 = injection_state(effective_injection(m), m.particle.mass_MeV);
  TrackSettings st = machine_track_settings(m);
  st.reference_stepper = reference;
  std::vector<double> build, track;
  for (int k = 0; k < repeat; ++k) {
    auto a = Clock::now();
    const TrackModel model = make_track_model(m, opt, &files);
    build.push_back(seconds(a) * 1e3);
    a = Clock::now();
    t.turns.clear();
    track_particle(model, s0, st, t.turns);
    track.push_back(seconds(a) * 1e3);
  }
  // Medians: robust against another process taking a core for a moment.
  std::sort(build.begin(), build.end());
  std::sort(track.begin(), track.end());
  t.build_ms = build[build.size() / 2];
  t.track_ms = track[track.size() / 2];
  return t;
}

}  // namespace

int main(int argc, char** argv) {
  int repeat = 20;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--repeat") && i + 1 < argc) repeat = std::max(1, std::atoi(argv[++i]));
    else {
      std::fprintf(stderr, "usage: bench_evaluation [--repeat N]\n");
      return 64;
    }
  }
  Machine m = load_machine(share("machine.json"));
  apply_dvars_file(m, share("truth-dvars.json"));
  const ModelFiles files = read_model_files(m);
  size_t excited = 0;
  for (const auto& c : m.trimcoils) excited += c.bmax_T != 0;
  std::printf("ring8, truth-dvars.json's design (%zu of %zu trim coils excited), 182 turns, one thread, medians of %d\n",
              excited, m.trimcoils.size(), repeat);
  const Timing one = time_track(m, files, false, repeat);
  const Timing sum = time_track(m, files, true, repeat);
  const Timing ref = time_track(m, files, true, repeat, true);
  double worst = 0;
  bool same = one.turns.size() == sum.turns.size();
  for (size_t i = 0; same && i < one.turns.size(); ++i) worst = std::max(worst, std::fabs(one.turns[i].r_mm - sum.turns[i].r_mm));
  std::printf("%-26s %10s %10s %10s\n", "coils", "build [ms]", "track [ms]", "total [ms]");
  std::printf("%-26s %10.2f %10.2f %10.2f\n", "one by one (reference)", one.build_ms, one.track_ms, one.build_ms + one.track_ms);
  std::printf("%-26s %10.2f %10.2f %10.2f\n", "summed (TrimCoilSum)", sum.build_ms, sum.track_ms, sum.build_ms + sum.track_ms);
  std::printf("%-26s %10.2f %10.2f %10.2f\n", "summed, reference stepper", ref.build_ms, ref.track_ms,
              ref.build_ms + ref.track_ms);
  std::printf("speed-up of the track: %.2fx; turns differ by at most %.2e mm%s\n", one.track_ms / sum.track_ms, worst,
              same ? "" : " (turn counts differ!)");

  // The whole in-process evaluation (model, track, match, six objectives) of the same design
  // against its own turns as the measurement, with the paper's 48 variables.
  const std::string tmp = std::filesystem::temp_directory_path() / ("bench_evaluation_" + std::to_string(::getpid()));
  std::filesystem::create_directories(tmp);
  {
    std::ofstream pk(tmp + "/peaks.csv");
    pk.precision(12);
    pk << "probe,turn,r_mm,height,area,width_mm,flag\n";
    const TrackModel model = make_track_model(m, {}, &files);
    for (const auto& t : sum.turns) pk << model.probes[static_cast<size_t>(t.probe)].name << ',' << t.turn << ',' << t.r_mm << ",1,1,1,ok\n";
    std::ofstream(tmp + "/problem.json") << "{\"format\": \"turnfit-problem/1\", \"machine\": \"" << share("machine.json")
                                         << "\", \"peaks\": \"peaks.csv\", \"bunch\": \"reference\", \"variables\": \"paper\"}\n";
  }
  LoadedProblem lp = load_problem(tmp + "/problem.json", "", -1);
  auto* p = dynamic_cast<TurnPatternProblem*>(lp.problem.get());
  std::vector<double> x;
  for (const auto& v : p->variables()) x.push_back(dvar_value(m, v.name));
  // Median ms of one evaluation, and its worst turn against the measurement.
  auto evaluate = [&](const TurnPatternProblem& q, double& linf) {
    std::vector<double> ev;
    linf = 0;
    for (int k = 0; k < repeat; ++k) {
      const auto a = Clock::now();
      const TurnPatternResult r = q.simulate(x);
      ev.push_back(seconds(a) * 1e3);
      for (size_t i = 0; i < r.delta_mm.size(); ++i)
        if (r.matched[i]) linf = std::max(linf, std::fabs(r.delta_mm[i]));
    }
    std::sort(ev.begin(), ev.end());
    return ev[ev.size() / 2];
  };
  double linf = 0, linf_ref = 0;
  const double t_ev = evaluate(*p, linf);
  p->set_reference_stepper(true);
  const double t_ev_ref = evaluate(*p, linf_ref);
  p->set_reference_stepper(false);
  std::printf("one evaluation of the %zu-variable problem (TurnPatternProblem::simulate), the reference particle: "
              "%.2f ms (reference stepper %.2f ms, %.2fx); worst turn %.1e mm against its own turns\n",
              p->n_variables(), t_ev, t_ev_ref, t_ev_ref / t_ev, linf);
  // A forward-difference Jacobian's 49 designs on 2 threads: one simulate() at a time per
  // thread (as localsearch did before issue 17's second session) against simulate_many in
  // chunks of at most 16 (what localsearch does now), and that the two agree bit for bit.
  {
    std::vector<std::vector<double>> xs = {x};
    for (size_t j = 0; j < x.size(); ++j) {
      std::vector<double> v = x;
      v[j] += 1e-6 * (p->upper()[j] - p->lower()[j]);
      xs.push_back(v);
    }
    const unsigned threads = 2;
    std::vector<TurnPatternResult> one(xs.size()), many(xs.size());
    std::vector<double> t_one, t_many;
    for (int k = 0; k < std::max(3, repeat / 3); ++k) {
      auto a = Clock::now();
      parallel_for(xs.size(), threads, [&](size_t i, unsigned) { one[i] = p->simulate(xs[i]); });
      t_one.push_back(seconds(a) * 1e3);
      a = Clock::now();
      many = p->simulate_many(xs, threads);
      t_many.push_back(seconds(a) * 1e3);
    }
    std::sort(t_one.begin(), t_one.end());
    std::sort(t_many.begin(), t_many.end());
    bool same = true;
    for (size_t i = 0; i < xs.size(); ++i) {
      same = same && one[i].ok == many[i].ok && one[i].delta_mm.size() == many[i].delta_mm.size();
      for (size_t k = 0; same && k < one[i].delta_mm.size(); ++k)
        same = one[i].delta_mm[k] == many[i].delta_mm[k] ||
               (std::isnan(one[i].delta_mm[k]) && std::isnan(many[i].delta_mm[k]));
    }
    std::printf("a Jacobian's %zu designs on %u threads: one at a time %.1f ms, together (simulate_many) %.1f ms, "
                "%.2fx; %s\n", xs.size(), threads, t_one[t_one.size() / 2], t_many[t_many.size() / 2],
                t_one[t_one.size() / 2] / t_many[t_many.size() / 2],
                same ? "the same residuals bit for bit" : "RESIDUALS DIFFER");
  }
  // The bunch's centre (the default when the machine has a bunch: the reference and 13
  // quadrature nodes, on all threads), as the main job's fit evaluates it.
  {
    std::ofstream(tmp + "/problem-centroid.json") << "{\"format\": \"turnfit-problem/1\", \"machine\": \""
                                                  << share("machine.json")
                                                  << "\", \"peaks\": \"peaks.csv\", \"variables\": \"paper\"}\n";
    LoadedProblem lc = load_problem(tmp + "/problem-centroid.json", "", -1);
    auto* c = dynamic_cast<TurnPatternProblem*>(lc.problem.get());
    double lc_inf = 0, lc_ref = 0;
    const double tc = evaluate(*c, lc_inf);
    c->set_reference_stepper(true);
    const double tc_ref = evaluate(*c, lc_ref);
    std::printf("one evaluation, the bunch's centre (reference + 13 quadrature nodes, %u threads): %.2f ms (reference "
                "stepper %.2f ms, %.2fx)\n", std::max(1u, std::thread::hardware_concurrency()), tc, tc_ref, tc_ref / tc);
  }
  // Smoothness: second differences of every residual along each variable at steps h (fractions
  // of its bound range). A smooth function gives h^2 scaling; a floor is noise, which limits the
  // finite-difference Jacobian (error ~ noise / h).
  std::printf("second differences max_i |r(x+h) - 2 r(x) + r(x-h)| [mm] per variable and step h (fraction of range)\n");
  std::printf("%-12s", "variable");
  const std::vector<double> hs = {1e-8, 1e-7, 1e-6, 1e-5, 1e-4};
  for (double h : hs) std::printf(" %10.0e", h);
  std::printf("\n");
  const TurnPatternResult r0 = p->simulate(x);
  for (size_t j = 0; j < x.size(); j += 3) {
    std::printf("%-12s", p->variables()[j].name.c_str());
    for (double h : hs) {
      std::vector<double> xp = x, xm = x;
      const double d = h * (p->upper()[j] - p->lower()[j]);
      xp[j] = std::min(x[j] + d, p->upper()[j]);
      xm[j] = std::max(x[j] - d, p->lower()[j]);
      const TurnPatternResult a = p->simulate(xp), b = p->simulate(xm);
      double worst = 0;
      for (size_t i = 0; i < r0.delta_mm.size(); ++i)
        if (r0.matched[i] && a.matched[i] && b.matched[i])
          worst = std::max(worst, std::fabs(a.delta_mm[i] - 2 * r0.delta_mm[i] + b.delta_mm[i]));
      std::printf(" %10.2e", worst);
    }
    std::printf("\n");
  }
  std::filesystem::remove_all(tmp);
  return same ? 0 : 1;
}
