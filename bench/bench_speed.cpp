// bench_speed (issue 17): tracking speed against the reference stepper in the same process.
//  1. One 182-turn single-particle track of ring8 (nominal), ring8's truth (18 trim coils and
//     its field effects) and the PSI Ring example: the reference stepper (TrackSettings::
//     reference_stepper, the code before issue 17) against the default, median of repeats, and
//     the largest difference of any recorded crossing.
//  2. Bunches of each machine on one thread: a loop of reference single tracks against
//     track_particles (groups stepped together), in particle-turns per second, with the
//     largest difference of a crossing against the single-particle default path.
//  3. Designs of the truth, a model each (as an optimizer's or the diagnosis's finite-difference
//     columns: each design moves one coil or one effect's parameter): tracked one at a time
//     against together as one group of lanes with a model per lane (track_particles(models,
//     ...)), and the group's records against each design's alone (bit for bit).
//  With --breakdown, between 1 and 2: what each of the truth's field effects costs a single
//  track (the truth without it, the variants interleaved run by run).
//
// Usage: bench_speed [--repeat N] [--particles N] [--breakdown] [--designs-only]
// (--designs-only: section 3 alone.)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <sys/stat.h>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point a) { return std::chrono::duration<double>(Clock::now() - a).count(); }

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/// Largest |dr| between two record lists of the same crossings (inf if they differ in count).
double worst_dr(const std::vector<TurnRecord>& a, const std::vector<TurnRecord>& b) {
  if (a.size() != b.size()) return INFINITY;
  double w = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    if (a[i].probe != b[i].probe || a[i].turn != b[i].turn) return INFINITY;
    w = std::max(w, std::fabs(a[i].r_mm - b[i].r_mm));
  }
  return w;
}

struct Case {
  std::string name, path;
};

}  // namespace

int main(int argc, char** argv) {
  int repeat = 15;
  size_t particles = 64;
  bool breakdown = false, only_designs = false;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--repeat") && i + 1 < argc) repeat = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--particles") && i + 1 < argc) particles = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--breakdown")) breakdown = true;
    else if (!std::strcmp(argv[i], "--designs-only")) only_designs = true;
    else {
      std::fprintf(stderr, "usage: bench_speed [--repeat N] [--particles N] [--breakdown] [--designs-only]\n");
      return 64;
    }
  }
  const std::string share = std::string(TURNFIT_SOURCE_SHARE) + "/ring8/";
  std::vector<Case> cases = {{"ring8 nominal", share + "machine.json"}, {"ring8 truth", share + "truth-machine.json"}};
  struct stat st {};
  if (::stat((std::string(TURNFIT_SHARED_DIR) + "/data/psi-ring/bfield.dat").c_str(), &st) == 0)
    cases.push_back({"PSI Ring aeo", std::string(TURNFIT_SOURCE_SHARE) + "/../../examples/psi-ring/aeo.json"});
  else
    std::printf("(PSI Ring example skipped: shared data not found at %s)\n", TURNFIT_SHARED_DIR);

  struct Loaded {
    Machine m;
    TrackModel model;
    ParticleState s0;
    TrackSettings ts;
  };
  std::vector<Loaded> loaded;
  for (const auto& c : cases) {
    Loaded L;
    L.m = load_machine(c.path);
    // ring8's truth as synth runs it: with the trim coils of truth-dvars.json.
    if (c.name == "ring8 truth") apply_dvars_file(L.m, share + "truth-dvars.json");
    L.model = make_track_model(L.m);
    L.s0 = injection_state(effective_injection(L.m), L.m.particle.mass_MeV);
    L.ts = machine_track_settings(L.m);
    L.ts.turns = 182;
    loaded.push_back(std::move(L));
  }

  if (!only_designs) {  // sections 1 and 2 (and the breakdown)
    std::printf("== Single-particle tracks, 182 turns, one thread, median of %d\n", repeat);
    std::printf("%-14s %14s %12s %8s %16s\n", "machine", "reference [ms]", "default [ms]", "ratio", "max |dr| [mm]");
    for (size_t c = 0; c < loaded.size(); ++c) {
      const Loaded& L = loaded[c];
      TrackSettings ref = L.ts;
      ref.reference_stepper = true;
      std::vector<double> t_ref, t_fast;
      std::vector<TurnRecord> a, b;
      for (int k = 0; k < repeat; ++k) {
        a.clear();
        auto t0 = Clock::now();
        track_particle(L.model, L.s0, ref, a);
        t_ref.push_back(seconds_since(t0) * 1e3);
        b.clear();
        t0 = Clock::now();
        track_particle(L.model, L.s0, L.ts, b);
        t_fast.push_back(seconds_since(t0) * 1e3);
      }
      std::printf("%-14s %14.2f %12.2f %7.2fx %16.2e\n", cases[c].name.c_str(), median(t_ref), median(t_fast),
                  median(t_ref) / median(t_fast), worst_dr(a, b));
    }
    if (breakdown) {
      // What each field effect of the truth costs a single track: the truth without it, and the
      // nominal machine with it alone (the same coils as the truth), interleaved run by run.
      std::printf("\n== The truth's field effects, one at a time (single track, default stepper, median of %d)\n", repeat);
      const Loaded& T = loaded[1];
      struct Variant {
        std::string name;
        Machine m;
      };
      std::vector<Variant> vs;
      const auto without = [&](const std::string& name, auto clear) {
        Machine m = T.m;
        clear(m.effect_set);
        vs.push_back({name, m});
      };
      using Fx = Effects;
      without("truth", [](Fx&) {});
      without("- field-harmonic", [](Fx& e) { e.field_harmonics.clear(); });
      without("- sector-strength", [](Fx& e) { e.sector_strengths.clear(); });
      without("- trimcoil-sectors", [](Fx& e) { e.trimcoil_sectors.clear(); });
      without("no field effect", [](Fx& e) {
        e.field_harmonics.clear();
        e.sector_strengths.clear();
        e.trimcoil_sectors.clear();
      });
      without("nothing (coils 0)", [](Fx& e) { e = Fx{}; });
      for (auto& t : vs.back().m.trimcoils) t.bmax_T = 0;
      std::vector<TrackModel> models;
      for (const auto& v : vs) models.push_back(make_track_model(v.m));
      std::vector<std::vector<double>> times(vs.size());
      for (int k = 0; k < repeat; ++k)
        for (size_t v = 0; v < vs.size(); ++v) {
          std::vector<TurnRecord> a;
          const auto t0 = Clock::now();
          track_particle(models[v], T.s0, T.ts, a);
          times[v].push_back(seconds_since(t0) * 1e3);
        }
      for (size_t v = 0; v < vs.size(); ++v)
        std::printf("%-22s %8.2f ms  %5.2fx of nothing\n", vs[v].name.c_str(), median(times[v]),
                    median(times[v]) / median(times.back()));
    }

    std::printf("\n== Bunches of %zu particles, 182 turns, one thread (ring8's bunch block; PSI: "
                "1 mm mrad, 0.05 MeV, 1 deg)\n", particles);
    std::printf("%-14s %22s %22s %8s %24s\n", "machine", "reference [pt/s]", "default [pt/s]", "ratio",
                "max |dr| vs single [mm]");
    for (size_t c = 0; c < loaded.size(); ++c) {
      Loaded& L = loaded[c];
      Bunch b = L.m.bunch ? *L.m.bunch : Bunch{};
      if (!L.m.bunch) {
        b.emittance_r_mm_mrad = 1;
        b.beta_r_m = 2;
        b.sigma_E_MeV = 0.05;
        b.sigma_phase_deg = 1;
      }
      const Injection inj = effective_injection(L.m);
      std::vector<ParticleState> starts;
      for (const auto& o : gaussian_bunch(b, particles, 1))
        starts.push_back(offset_state(inj, L.m.particle.mass_MeV, L.model.rf_MHz, o));
      TrackSettings ref = L.ts;
      ref.reference_stepper = true;
      std::vector<std::vector<TurnRecord>> tr(particles), tf(particles), ts(particles);
      std::vector<TrackEnd> er(particles), ef(particles);
      auto t0 = Clock::now();
      double pt = 0;
      for (size_t i = 0; i < particles; ++i) pt += (er[i] = track_particle(L.model, starts[i], ref, tr[i])).turns;
      const double t_ref = seconds_since(t0);
      t0 = Clock::now();
      track_particles(L.model, starts.data(), particles, L.ts, tf.data(), ef.data());
      const double t_fast = seconds_since(t0);
      double pf = 0, worst = 0;
      for (size_t i = 0; i < particles; ++i) {
        pf += ef[i].turns;
        track_particle(L.model, starts[i], L.ts, ts[i]);
        worst = std::max(worst, worst_dr(tf[i], ts[i]));
      }
      std::printf("%-14s %22.0f %22.0f %7.2fx %24.2e\n", cases[c].name.c_str(), pt / t_ref, pf / t_fast,
                  (pf / t_fast) / (pt / t_ref), worst);
    }
  }

  {
    // 16 designs of the truth: each moves one number (a coil's bmax, the harmonic's amplitude,
    // radius or phase, the sector strength) by a small step, as a Jacobian's columns do.
    const Loaded& T = loaded[1];
    std::vector<Machine> ms;
    for (int d = 0; d < 16; ++d) {
      Machine m = T.m;
      const double e = 1e-4 * (d + 1);
      switch (d % 4) {
        case 0: m.trimcoils[static_cast<size_t>(d) % m.trimcoils.size()].bmax_T *= 1 + e; break;
        case 1: m.effect_set.field_harmonics[0].amplitude_T *= 1 + e; break;
        case 2: m.effect_set.field_harmonics[0].r_mm += e * 100; break;
        default: m.effect_set.sector_strengths[0].relative *= 1 + e; break;
      }
      ms.push_back(m);
    }
    // Built as an optimizer builds them: from one read of the files, so that they share the
    // map (lanes go through grid steps together only on one map).
    const ModelFiles files = read_model_files(T.m);
    std::vector<TrackModel> models;
    for (const auto& m : ms) models.push_back(make_track_model(m, {}, &files));
    std::vector<const TrackModel*> mp;
    for (const auto& m : models) mp.push_back(&m);
    const size_t n = models.size();
    std::vector<ParticleState> starts(n, T.s0);
    std::vector<std::vector<TurnRecord>> alone(n), together(n);
    std::vector<TrackEnd> ends(n);
    std::vector<double> t_alone, t_together;
    double turns = 0;
    for (int k = 0; k < repeat; ++k) {
      auto t0 = Clock::now();
      turns = 0;
      for (size_t i = 0; i < n; ++i) {
        alone[i].clear();
        turns += track_particle(models[i], starts[i], T.ts, alone[i]).turns;
      }
      t_alone.push_back(seconds_since(t0));
      for (auto& t : together) t.clear();
      t0 = Clock::now();
      track_particles(mp.data(), starts.data(), n, T.ts, together.data(), ends.data());
      t_together.push_back(seconds_since(t0));
    }
    double worst = 0;
    for (size_t i = 0; i < n; ++i) worst = std::max(worst, worst_dr(alone[i], together[i]));
    std::printf("\n== %zu designs of ring8's truth, a model each, 182 turns, one thread, median of %d\n", n, repeat);
    std::printf("%-22s %12s %16s\n", "", "ms per design", "particle-turns/s");
    std::printf("%-22s %12.2f %16.0f\n", "one at a time", median(t_alone) * 1e3 / n, turns / median(t_alone));
    std::printf("%-22s %12.2f %16.0f\n", "one group, lane models", median(t_together) * 1e3 / n,
                turns / median(t_together));
    std::printf("ratio %.2fx; the group's records against each design alone: max |dr| %.2e mm\n",
                median(t_alone) / median(t_together), worst);
  }
  return 0;
}
