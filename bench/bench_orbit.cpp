// Benchmark: the PSI Ring orbit table (519 energies, 1 MeV steps) - time per table and
// per energy, against the single-energy cold start as in-process reference, and the
// accuracy against PSI's FIXPO reference rows (physics.md) at each step density.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <sys/stat.h>

#include "turnfit/field/map_io.hpp"
#include "turnfit/orbit/closed_orbit.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

static double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

int main(int argc, char** argv) {
  std::string path = std::string(TURNFIT_SHARED_DIR) + "/data/psi-ring/bfield.dat";
  if (argc > 1) path = argv[1];
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) {
    std::printf("bench_orbit: skipped: %s not found\n", path.c_str());
    return 0;
  }
  auto t0 = Clock::now();
  PolarFieldMap map = read_field_map(path, MapFormat::psi_ring);
  const double t_read = seconds_since(t0);
  std::printf("map read + spline setup: %.3f s\n", t_read);

  struct Ref { double e, r, nur, nuz; };
  const Ref refs[] = {{72.0, 2131.4, 1.1565, 0.9001}, {369.995, 3938.6, 1.4519, 0.8841}};
  std::vector<double> energies;
  for (int e = 72; e <= 590; ++e) energies.push_back(e);

  OrbitSettings fine;
  fine.steps_per_cell = 32;
  auto rf = orbit_table(map, fine, energies, 2);
  std::printf("\nsteps/cell  table[s]  per-energy[us]  max|dr| FIXPO[mm]  max|dnu_r|  max|dnu_z|  vs 32 steps/cell: "
              "max|dr|[mm] max|dnu|\n");
  for (int spc : {1, 2, 4, 8}) {
    OrbitSettings s;
    s.steps_per_cell = spc;
    s.harmonic = 6;
    s.rf_MHz = 50.65;
    auto t1 = Clock::now();
    auto rows = orbit_table(map, s, energies, 1);
    const double t = seconds_since(t1);
    double dr = 0, dnr = 0, dnz = 0;
    for (const auto& ref : refs) {
      OrbitRow row = closed_orbit(map, s, ref.e);
      dr = std::max(dr, std::fabs(row.r_mm - ref.r));
      dnr = std::max(dnr, std::fabs(row.nu_r - ref.nur));
      dnz = std::max(dnz, std::fabs(row.nu_z - ref.nuz));
    }
    int bad = 0;
    double cr = 0, cn = 0;
    for (size_t i = 0; i < rows.size(); ++i) {
      bad += !rows[i].ok();
      cr = std::max(cr, std::fabs(rows[i].r_mm - rf[i].r_mm));
      cn = std::max({cn, std::fabs(rows[i].nu_r - rf[i].nu_r), std::fabs(rows[i].nu_z - rf[i].nu_z)});
    }
    std::printf("%10d  %8.4f  %14.1f  %17.3f  %10.5f  %10.5f  %11.1e %9.1e%s\n", spc, t, t / energies.size() * 1e6,
                dr, dnr, dnz, cr, cn, bad ? "  (some rows failed)" : "");
  }
  OrbitSettings dflt;

  // Threads and the cold-start reference.
  auto t2 = Clock::now();
  auto r2 = orbit_table(map, dflt, energies, 2);
  const double t_threads = seconds_since(t2);
  auto t3 = Clock::now();
  for (double e : energies) closed_orbit(map, dflt, e);
  const double t_cold = seconds_since(t3);
  auto t4 = Clock::now();
  auto r1 = orbit_table(map, dflt, energies, 1);
  const double t_one = seconds_since(t4);
  std::printf("519 energies, default: 1 thread %.4f s, 2 threads %.4f s (x%.2f), cold start each %.4f s (warm start "
              "x%.2f)\n", t_one, t_threads, t_one / t_threads, t_cold, t_cold / t_one);
  std::printf("whole job incl. map read, 2 threads: %.3f s; OPAL 2022.1 closed-orbit finder: 0.71 s (0.2 s after "
              "start-up) -> ratio %.1fx / %.1fx\n", t_read + t_threads, 0.71 / (t_read + t_threads), 0.2 / t_threads);
  return 0;
}
