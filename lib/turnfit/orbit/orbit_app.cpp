// turnfit-orbit: equilibrium orbit tables from a field map or a machine file.
#include "turnfit/orbit/orbit_app.hpp"

#include <cmath>
#include <iostream>

#include "turnfit/field/load.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/machine/machine.hpp"

namespace turnfit {
namespace {

std::string cell(double v, int digits) { return std::isfinite(v) ? cli::fmt(v, digits) : std::string(); }

Particle particle_named(const std::string& name) {
  if (auto p = named_particle(name)) return *p;
  throw usage_error("--particle '" + name + "': expected proton, deuteron, alpha or h2+ (or a machine file)");
}

void progress_bar(size_t done, size_t total) {
  if (done == total || done % 16 == 0)
    std::fprintf(stderr, "\rturnfit-orbit: %zu/%zu energies%s", done, total, done == total ? "\n" : "");
}

}  // namespace

void add_orbit_options(CLI::App& app, OrbitOptions& o) {
  app.description(
      "Static equilibrium orbits (closed orbits without RF) of a cyclotron field map: radius and\n"
      "radial momentum at an azimuth, tunes from the one-sector transfer matrices, revolution\n"
      "frequency and RF phase slip per turn. One CSV row per energy.");
  app.add_option("machine", o.machine, "Machine file (field, particle and RF taken from it)");
  app.add_option("--field-map", o.field_map, "Field map file ('-' for stdin); overrides the machine's");
  app.add_option("--field-format", o.field_format, "Field map format")
      ->check(CLI::IsMember({"psi-ring", "turnfit"}))
      ->capture_default_str();
  app.add_option("--symmetry", o.symmetry, "Sector count --field-map must have (0: whatever it has; a mismatch is an error)")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--field-scale", o.field_scale, "Multiply the map by this factor (-1 flips polarity)")
      ->capture_default_str();
  app.add_option("--particle", o.particle, "proton (default), deuteron, alpha or h2+; a machine file names its own");
  app.add_option("--energies", o.energies, "Kinetic energies [MeV]: FIRST:LAST:STEP or E1,E2,...");
  app.add_option("--harmonic", o.harmonic, "RF harmonic number h (for the phase slip)")->check(CLI::PositiveNumber);
  app.add_option("--rf-MHz", o.rf_MHz, "RF frequency [MHz] (for the phase slip)")->check(CLI::PositiveNumber);
  app.add_option("--azimuth-deg", o.azimuth_deg, "Azimuth where r and pr are reported [deg]")->capture_default_str();
  app.add_option("--steps-per-cell", o.steps_per_cell, "RK4 steps per azimuthal map cell")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--set", o.sets, "Set a design variable or JSON pointer of the machine: NAME=VALUE (repeatable)")
      ->allow_extra_args(false);
  app.add_option("--dvars", o.dvars, "JSON file of design-variable values");
  app.add_option("--write-map", o.write_map, "Also write the loaded (scaled) map to this file");
  app.add_option("--write-map-format", o.write_map_format, "Format for --write-map")
      ->check(CLI::IsMember({"psi-ring", "turnfit"}))
      ->capture_default_str();
  app.add_flag("--strict", o.strict, "Exit 65 if any energy has no closed orbit or unstable motion");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kFormat | cli::kThreads, {"csv", "json", "text"});
}

namespace {
void write_orbit_csv(std::ostream& os, const std::vector<OrbitRow>& rows) {
  os << "energy_MeV,r_mm,pr_mrad,nu_r,nu_z,f_rev_MHz,phase_slip_deg_per_turn,r_avg_mm,status\n";
  for (const auto& r : rows) {
    std::string status = r.status;
    for (auto& c : status)
      if (c == ',') c = ';';
    os << cli::fmt(r.energy_MeV, 10) << ',' << cell(r.r_mm, 10) << ',' << cell(r.pr_mrad, 8) << ','
       << cell(r.nu_r, 8) << ',' << cell(r.nu_z, 8) << ',' << cell(r.f_rev_MHz, 10) << ','
       << cell(r.phase_slip_deg, 6) << ',' << cell(r.r_avg_mm, 10) << ',' << status << '\n';
  }
}

void write_orbit_json(std::ostream& os, const std::vector<OrbitRow>& rows, bool provenance) {
  nlohmann::json doc;
  if (provenance) doc["provenance"] = cli::provenance();
  nlohmann::json arr = nlohmann::json::array();
  auto num = [](double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); };
  for (const auto& r : rows)
    arr.push_back({{"energy_MeV", r.energy_MeV}, {"r_mm", num(r.r_mm)}, {"pr_mrad", num(r.pr_mrad)},
                   {"nu_r", num(r.nu_r)}, {"nu_z", num(r.nu_z)}, {"f_rev_MHz", num(r.f_rev_MHz)},
                   {"phase_slip_deg_per_turn", num(r.phase_slip_deg)}, {"r_avg_mm", num(r.r_avg_mm)},
                   {"status", r.status}});
  doc["orbits"] = arr;
  os << doc.dump(1) << "\n";
}

void write_orbit_text(std::ostream& os, const std::vector<OrbitRow>& rows) {
  auto col = [](double v, int width, int prec) {
    char b[48];
    if (std::isfinite(v)) std::snprintf(b, sizeof b, "%*.*f", width, prec, v);
    else std::snprintf(b, sizeof b, "%*s", width, "-");
    return std::string(b);
  };
  os << "  E [MeV]     r [mm]  pr [mrad]     nu_r     nu_z  f_rev [MHz]  slip [deg/turn]  status\n";
  for (const auto& r : rows)
    os << col(r.energy_MeV, 9, 3) << ' ' << col(r.r_mm, 10, 3) << ' ' << col(r.pr_mrad, 10, 4) << ' '
       << col(r.nu_r, 8, 5) << ' ' << col(r.nu_z, 8, 5) << ' ' << col(r.f_rev_MHz, 12, 6) << ' '
       << col(r.phase_slip_deg, 16, 4) << "  " << r.status << '\n';
}
}  // namespace

void write_orbit_table(std::ostream& os, const std::vector<OrbitRow>& rows, const std::string& format,
                       bool provenance) {
  if (format == "json") {
    write_orbit_json(os, rows, provenance);
  } else if (format == "text") {
    write_orbit_text(os, rows);
  } else if (format == "csv" || format.empty()) {
    if (provenance) os << cli::provenance_comment();
    write_orbit_csv(os, rows);
  } else {
    throw usage_error("unknown --format '" + format + "'");
  }
}

OrbitJob prepare_orbit(const OrbitOptions& o) {
  if (o.machine.empty() && o.field_map.empty())
    throw usage_error("give a machine file or --field-map FILE");
  if ((!o.sets.empty() || !o.dvars.empty()) && o.machine.empty())
    throw usage_error("--set and --dvars need a machine file");
  if (o.machine == "-" && (o.field_map == "-" || o.dvars == "-")) throw usage_error("only one input can be stdin");
  if (!(o.field_scale != 0) || !std::isfinite(o.field_scale)) throw usage_error("--field-scale must be non-zero");
  if (o.energies.empty() && o.write_map.empty()) throw usage_error("--energies is required (unless only --write-map)");
  if (!o.machine.empty() && !o.particle.empty())
    throw usage_error("--particle conflicts with a machine file: the machine names its particle");
  if (o.symmetry > 0 && o.field_map.empty())
    throw usage_error("--symmetry checks --field-map; a machine file sets field.symmetry");
  if (!o.energies.empty() && (o.write_map == "-" || o.write_map == "/dev/stdout") &&
      (o.common.output == "-" || o.common.output.empty()))
    throw usage_error("--write-map - and the orbit table cannot both go to stdout (use -o)");
  OrbitJob job;
  if (!o.energies.empty()) job.energies = parse_energies(o.energies);

  OrbitSettings& s = job.settings;
  s.azimuth_deg = o.azimuth_deg;
  s.steps_per_cell = o.steps_per_cell;
  if (!o.machine.empty()) {
    Machine m = load_machine(o.machine);
    apply_sets(m, o.sets);
    if (!o.dvars.empty()) apply_dvars_file(m, o.dvars);
    s.mass_MeV = m.particle.mass_MeV;
    s.charge_e = m.particle.charge_e;
    s.harmonic = m.rf.harmonic;
    s.rf_MHz = m.rf.frequency_MHz;
    if (o.field_map.empty()) job.map = scaled(load_main_field(m), o.field_scale);
  } else {
    Particle p = particle_named(o.particle.empty() ? "proton" : o.particle);
    s.mass_MeV = p.mass_MeV;
    s.charge_e = p.charge_e;
  }
  if (!o.field_map.empty())
    job.map = scaled(read_field_map(o.field_map, parse_map_format(o.field_format), o.symmetry), o.field_scale);
  if ((o.harmonic > 0) != (o.rf_MHz > 0) && !(s.harmonic > 0 && s.rf_MHz > 0))
    throw usage_error("--harmonic and --rf-MHz go together (or come from the machine file)");
  if (o.harmonic > 0) s.harmonic = o.harmonic;
  if (o.rf_MHz > 0) s.rf_MHz = o.rf_MHz;
  return job;
}

int run_orbit(const OrbitOptions& o) {
  OrbitJob job = prepare_orbit(o);
  if (!o.write_map.empty()) {
    OutputFile mapout(o.write_map);
    if (parse_map_format(o.write_map_format) == MapFormat::turnfit) write_turnfit_map(mapout.stream(), job.map);
    else write_psi_ring(mapout.stream(), job.map);
    mapout.commit();
    if (job.energies.empty()) return 0;
  }
  const bool show_progress = !o.common.quiet && cli::stderr_is_tty() && job.energies.size() > 64;
  std::vector<OrbitRow> rows = orbit_table(job.map, job.settings, job.energies,
                                           cli::resolve_threads(o.common.threads),
                                           show_progress ? progress_bar : nullptr);
  OutputFile out(o.common.output);
  write_orbit_table(out.stream(), rows, o.common.format, !o.common.no_provenance);
  out.commit();

  size_t bad = 0;
  for (const auto& r : rows)
    if (!r.ok()) {
      if (bad < 5) cli::warn(o.common, cli::fmt(r.energy_MeV) + " MeV: " + r.status);
      ++bad;
    }
  if (bad > 5) cli::warn(o.common, std::to_string(bad - 5) + " more energies without a stable closed orbit");
  if (bad > 0 && o.strict) return static_cast<int>(ExitCode::data);
  return 0;
}

}  // namespace turnfit
