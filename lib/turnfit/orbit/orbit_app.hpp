// turnfit-orbit as a library function: options struct, run, table output.
#pragma once

#include <CLI/CLI.hpp>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/field/sector_field.hpp"
#include "turnfit/orbit/closed_orbit.hpp"
#include "turnfit/orbit/isochronize.hpp"

namespace turnfit {

/// Everything turnfit-orbit is asked to do.
struct OrbitOptions {
  cli::CommonOptions common;
  std::string machine;                 ///< machine file (optional)
  std::vector<std::string> sets;       ///< --set NAME=VALUE
  std::string dvars;                   ///< --dvars FILE
  std::string field_map;               ///< --field-map (overrides the machine's)
  std::string field_format = "psi-ring";
  int symmetry = 0;
  double field_scale = 1.0;
  std::string particle;                ///< empty: proton (without a machine file)
  std::string energies;                ///< --energies spec
  int harmonic = 0;                    ///< 0: machine's or none
  double rf_MHz = 0;                   ///< 0: machine's or none
  double azimuth_deg = 0;
  int steps_per_cell = 2;
  bool strict = false;                 ///< exit 65 if any energy has no closed orbit
  std::string write_map;               ///< --write-map: also write the loaded (scaled) map here
  std::string write_map_format = "turnfit";
  std::string sector_field;            ///< --sector-field: analytic field spec (turnfit-sector-field/1)
  bool isochronize = false;            ///< --isochronize: adjust the spec's hill field first
  std::string write_spec;              ///< --write-spec: the (isochronized) spec goes here
};

/// The field and settings an orbit run resolved from its options and machine file.
struct OrbitJob {
  PolarFieldMap map;
  std::optional<SectorFieldSpec> spec;  ///< the analytic field, when --sector-field gave one
  IsochronizeSettings iso;              ///< from the spec's "isochronize" block and the options
  OrbitSettings settings;
  std::vector<double> energies;  ///< empty when only a map is written
};

/// Registers turnfit-orbit's options on app.
void add_orbit_options(CLI::App& app, OrbitOptions& o);

/// Resolves options into a job: reads the machine and the map, applies --set/--dvars,
/// checks option combinations (EX_USAGE) and parses the energies.
OrbitJob prepare_orbit(const OrbitOptions& o);

/// Runs turnfit-orbit: prepare, compute, write. Returns the exit code.
int run_orbit(const OrbitOptions& o);

/// Writes rows in a format: "csv" (the orbit table of architecture.md plus r_avg_mm and
/// status), "json" ({"provenance", "orbits": [...]}) or "text" (aligned, for people).
void write_orbit_table(std::ostream& os, const std::vector<OrbitRow>& rows, const std::string& format,
                       bool provenance);

}  // namespace turnfit
