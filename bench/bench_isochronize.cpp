// Benchmark: isochronizing ring8's design field (turnfit-orbit --isochronize) - iterations,
// errors and time, against one closed-orbit table of the same energies as in-process reference
// (a Levenberg-Marquardt iteration costs one table per hill node plus its trial steps).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>

#include "turnfit/field/sector_field.hpp"
#include "turnfit/orbit/isochronize.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

static double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

int main(int argc, char** argv) {
  std::string path = std::string(TURNFIT_SOURCE_SHARE) + "/ring8/field-design.json";
  if (argc > 1) path = argv[1];
  const SectorFieldSpec design = read_sector_spec(path);
  OrbitSettings s;
  s.harmonic = 6;
  s.rf_MHz = 50.65;
  IsochronizeSettings iso;
  for (double e = 72; e <= 600; e += 4) iso.energies_MeV.push_back(e);
  iso.node_spacing_mm = 100;
  iso.start_from_mean_field = true;
  iso.tolerance = 2e-6;

  std::printf("ring8 design field: %zu energies 72-600 MeV, hill nodes every 100 mm\n", iso.energies_MeV.size());
  for (unsigned threads : {1u, 2u}) {
    auto t0 = Clock::now();
    const PolarFieldMap map = make_sector_field(design);
    const double t_map = seconds_since(t0);
    auto t1 = Clock::now();
    orbit_table(map, s, iso.energies_MeV, threads);
    const double t_table = seconds_since(t1);
    auto t2 = Clock::now();
    const IsochronizeResult r = isochronize(design, s, iso, threads);
    const double t_iso = seconds_since(t2);
    std::printf("\n%u thread(s): sampling the field %.4f s, one orbit table %.4f s (reference)\n", threads, t_map,
                t_table);
    std::printf("  iter  max|df/f|   rms|df/f|   max slip [deg/turn]\n");
    for (const auto& h : r.history)
      std::printf("  %4d  %9.3e  %9.3e  %9.5f\n", h.iteration, h.max_rel, h.rms_rel, h.max_slip_deg);
    std::printf("  isochronized in %.3f s = %.0f orbit tables (%zu hill nodes, %zu iterations)%s\n", t_iso,
                t_iso / (t_map + t_table), r.spec.hill_T.r_mm.size(), r.history.size() - 1,
                r.converged ? "" : "  NOT CONVERGED");
  }
  return 0;
}
