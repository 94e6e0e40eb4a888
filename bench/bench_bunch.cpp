// Benchmark: bunch throughput on the PSI Ring example (aeo.json, 190 turns) in particle-turns
// per second per core, against a plain loop of single-particle tracks in the same process (the
// reference: what the bunch machinery and the threads add or cost).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <sys/stat.h>
#include <thread>

#include "turnfit/track/bunch.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

int main(int argc, char** argv) {
  std::string machine = std::string(TURNFIT_SOURCE_SHARE) + "/../../examples/psi-ring/aeo.json";
  if (argc > 1) machine = argv[1];
  const size_t n = argc > 2 ? std::stoul(argv[2]) : 64;
  struct stat st {};
  if (::stat((std::string(TURNFIT_SHARED_DIR) + "/data/psi-ring/bfield.dat").c_str(), &st) != 0) {
    std::printf("bench_bunch: skipped: shared PSI Ring data not found\n");
    return 0;
  }
  Machine m = load_machine(machine);
  TrackModel model = make_track_model(m);
  // A bunch of the size the paper's multi-particle check implies (its emittances are not
  // published: these are round numbers; throughput hardly depends on them).
  Bunch b;
  b.emittance_r_mm_mrad = 1;
  b.beta_r_m = 2;
  b.sigma_E_MeV = 0.05;
  b.sigma_phase_deg = 1;
  std::vector<ParticleState> starts;
  for (const auto& o : gaussian_bunch(b, n, 1))
    starts.push_back(offset_state(*m.injection, m.particle.mass_MeV, model.rf_MHz, o));
  const unsigned cores = std::max(1u, std::thread::hardware_concurrency());
  std::printf("PSI Ring bunch, %zu particles, %d turns, %u hardware threads\n\n", n, m.tracking.turns, cores);
  std::printf("%-28s %9s %10s %22s %9s\n", "run", "step", "time [s]", "particle-turns/s/core", "lost");
  for (double step : {1.0, 4.0 / 3.0}) {
    TrackSettings s;
    s.turns = m.tracking.turns;
    s.step_deg = step;
    // Reference: the same particles one after another, no bunch machinery.
    auto t0 = Clock::now();
    double pt = 0;
    std::vector<TurnRecord> turns;
    for (const auto& p : starts) {
      turns.clear();
      pt += track_particle(model, p, s, turns).turns;
    }
    const double t_ref = std::chrono::duration<double>(Clock::now() - t0).count();
    std::printf("%-28s %9.3f %10.3f %22.0f %9s\n", "loop of single tracks", step, t_ref, pt / t_ref, "-");
    for (unsigned th : {1u, cores}) {
      t0 = Clock::now();
      BunchResult r = track_bunch(model, starts, s, th);
      const double t = std::chrono::duration<double>(Clock::now() - t0).count();
      char name[64];
      std::snprintf(name, sizeof name, "track_bunch, %u thread%s", th, th > 1 ? "s" : "");
      std::printf("%-28s %9.3f %10.3f %22.0f %9zu   (x%.2f vs loop)\n", name, step, t, r.particle_turns / t / th,
                  r.lost.size(), t_ref / t);
      if (cores == 1) break;
    }
  }
  std::printf("\nGoal (issue 3): >= 1e5 particle-turns/s/core.\n");
  return 0;
}
