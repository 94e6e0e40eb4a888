// Static equilibrium (closed) orbits, their tunes and isochronism, like PSI's FIXPO.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "turnfit/field/field_map.hpp"

namespace turnfit {

/// How closed orbits are found.
struct OrbitSettings {
  double mass_MeV = 938.27208816;  ///< particle rest energy [MeV]
  double charge_e = 1.0;           ///< particle charge [e]; its sign selects the bending direction
  double azimuth_deg = 0;          ///< where r and pr are reported
  int steps_per_cell = 2;          ///< RK4 steps per azimuthal map cell (steps align with the grid)
  int max_iterations = 40;         ///< Newton iterations before giving up
  double tolerance_mm = 1e-9;      ///< Newton convergence: |dr| below this and |dpr/p| below it / 1 m
  int harmonic = 0;                ///< RF harmonic h (0: no phase slip column)
  double rf_MHz = 0;               ///< RF frequency [MHz]
};

/// One closed orbit.
struct OrbitRow {
  double energy_MeV = 0;
  double r_mm = 0;            ///< radius where the orbit crosses the azimuth [mm]
  double pr_mrad = 0;         ///< p_r / p there [mrad]
  double nu_r = 0, nu_z = 0;  ///< tunes (NaN where the motion is unstable)
  double f_rev_MHz = 0;       ///< revolution frequency [MHz]
  double phase_slip_deg = 0;  ///< RF phase slip per turn [deg] (NaN without RF)
  double r_avg_mm = 0;        ///< mean radius over the sector [mm]
  std::string status = "ok";  ///< "ok", or why the row has no or partial results
  bool ok() const { return status == "ok"; }
};

/// A closed orbit at one energy, with its linear optics.
/// `guess` = (r [m], p_r/p) to start Newton from; none: from the average field.
/// Never throws for physics failures: they are reported in status.
OrbitRow closed_orbit(const PolarFieldMap& map, const OrbitSettings& s, double energy_MeV,
                      std::optional<std::pair<double, double>> guess = std::nullopt);

/// Closed orbits at many energies on `threads` threads. Energies are processed in fixed
/// chunks, each warm-started along the chunk, so the result does not depend on the
/// thread count. `progress` (may be null) is called with the number of rows done.
std::vector<OrbitRow> orbit_table(const PolarFieldMap& map, const OrbitSettings& s,
                                  const std::vector<double>& energies_MeV, unsigned threads,
                                  void (*progress)(size_t done, size_t total) = nullptr);

/// Parses an energy list "A:B:STEP" (inclusive of B when it falls on the grid) or
/// "E1,E2,..." [MeV]. EX_USAGE on bad syntax, non-positive energies or steps.
std::vector<double> parse_energies(const std::string& spec);

}  // namespace turnfit
