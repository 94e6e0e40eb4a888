// turnfit-orbit: equilibrium orbit tables from a field map or a machine file.
#include "turnfit/orbit/orbit_app.hpp"

#include <algorithm>
#include <cmath>
#include <iostream>

#include "turnfit/field/load.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
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
  app.add_option("--sector-field", o.sector_field,
                 "Analytic separated-sector field (turnfit-sector-field/1 JSON, '-' for stdin) instead of a map");
  app.add_flag("--isochronize", o.isochronize,
               "Adjust the --sector-field's hill field until f_rev = f_rf / h at every energy (settings from\n"
               "the spec's \"isochronize\" block; --energies overrides its energies); then write the table");
  app.add_option("--write-spec", o.write_spec, "Write the (isochronized) --sector-field spec to this file");
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
  os << json_text(doc, 1) << "\n";
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

namespace {
// The spec's "isochronize" block: the particle and RF the field is made for (they also give the
// table its phase-slip column), and the isochronizer's settings. Options given on the command
// line win.
void read_isochronize_block(const SectorFieldSpec& spec, const OrbitOptions& o, OrbitJob& job) {
  const nlohmann::json& b = spec.isochronize;
  if (b.is_null()) return;
  const std::string at = o.sector_field + ": /isochronize/";
  const std::vector<std::string> known{"particle",  "harmonic", "rf_MHz",          "energies_MeV",
                                       "tolerance", "max_iterations", "node_spacing_mm", "start",
                                       "smoothing"};
  for (const auto& item : b.items())
    if (std::find(known.begin(), known.end(), item.key()) == known.end())
      throw Error(ExitCode::data, at + item.key() + ": unknown key");
  auto number = [&](const char* k, double def) {
    if (!b.contains(k)) return def;
    if (!b.at(k).is_number() || !std::isfinite(b.at(k).get<double>()))
      throw Error(ExitCode::data, at + k + ": expected a finite number");
    return b.at(k).get<double>();
  };
  auto text = [&](const char* k, const std::string& def) {
    if (!b.contains(k)) return def;
    if (!b.at(k).is_string()) throw Error(ExitCode::data, at + k + ": expected a string");
    return b.at(k).get<std::string>();
  };
  OrbitSettings& s = job.settings;
  if (o.particle.empty()) {
    const std::string name = text("particle", "proton");
    auto p = named_particle(name);
    if (!p) throw Error(ExitCode::data, at + "particle: expected proton, deuteron, alpha or h2+, got '" + name + "'");
    s.mass_MeV = p->mass_MeV;
    s.charge_e = p->charge_e;
  }
  const double h = number("harmonic", 0), f = number("rf_MHz", 0);
  if (h != std::floor(h) || h < 0 || f < 0) throw Error(ExitCode::data, at + "harmonic/rf_MHz: expected h >= 1 and f > 0");
  if (o.harmonic == 0 && h > 0) s.harmonic = static_cast<int>(h);
  if (o.rf_MHz == 0 && f > 0) s.rf_MHz = f;
  IsochronizeSettings& iso = job.iso;
  iso.tolerance = number("tolerance", iso.tolerance);
  iso.max_iterations = static_cast<int>(number("max_iterations", iso.max_iterations));
  iso.node_spacing_mm = number("node_spacing_mm", 0);
  iso.smoothing = number("smoothing", iso.smoothing);
  const std::string start = text("start", "spec");
  if (start != "spec" && start != "mean-field")
    throw Error(ExitCode::data, at + "start: expected \"spec\" or \"mean-field\", got '" + start + "'");
  iso.start_from_mean_field = start == "mean-field";
  if (!(iso.tolerance > 0) || iso.max_iterations < 1 || iso.node_spacing_mm < 0 || iso.smoothing < 0)
    throw Error(ExitCode::data, at + ": tolerance > 0, max_iterations >= 1, node_spacing_mm >= 0, smoothing >= 0");
  if (job.energies.empty() && b.contains("energies_MeV")) {
    try {
      job.energies = parse_energies(text("energies_MeV", ""));
    } catch (const Error& e) {
      throw Error(ExitCode::data, at + "energies_MeV: " + e.what());
    }
  }
}
}  // namespace

OrbitJob prepare_orbit(const OrbitOptions& o) {
  if (o.machine.empty() && o.field_map.empty() && o.sector_field.empty())
    throw usage_error("give a machine file, --field-map FILE or --sector-field FILE");
  if (!o.sector_field.empty() && (!o.machine.empty() || !o.field_map.empty()))
    throw usage_error("--sector-field is a field of its own: it goes without a machine file or --field-map");
  if ((o.isochronize || !o.write_spec.empty()) && o.sector_field.empty())
    throw usage_error(std::string(o.isochronize ? "--isochronize" : "--write-spec") + " needs --sector-field");
  if (!o.write_spec.empty() && o.write_spec == o.write_map)
    throw usage_error("--write-spec and --write-map name the same file");
  if ((!o.sets.empty() || !o.dvars.empty()) && o.machine.empty())
    throw usage_error("--set and --dvars need a machine file");
  if (o.machine == "-" && (o.field_map == "-" || o.dvars == "-")) throw usage_error("only one input can be stdin");
  if (!(o.field_scale != 0) || !std::isfinite(o.field_scale)) throw usage_error("--field-scale must be non-zero");
  if (o.energies.empty() && o.write_map.empty() && o.write_spec.empty() && !o.isochronize)
    throw usage_error("--energies is required (unless only --write-map or --write-spec)");
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
  if (!o.sector_field.empty()) {
    if (o.field_scale != 1.0) throw usage_error("--field-scale applies to maps; scale a --sector-field's hill table");
    job.spec = read_sector_spec(o.sector_field);
    read_isochronize_block(*job.spec, o, job);
    if (o.isochronize && job.energies.empty())
      throw usage_error(o.sector_field + ": --isochronize needs energies (--energies or isochronize.energies_MeV)");
    if (!o.isochronize) job.map = make_sector_field(*job.spec);
  }
  if ((o.harmonic > 0) != (o.rf_MHz > 0) && !(s.harmonic > 0 && s.rf_MHz > 0))
    throw usage_error("--harmonic and --rf-MHz go together (or come from the machine file)");
  if (o.harmonic > 0) s.harmonic = o.harmonic;
  if (o.rf_MHz > 0) s.rf_MHz = o.rf_MHz;
  return job;
}

int run_orbit(const OrbitOptions& o) {
  OrbitJob job = prepare_orbit(o);
  std::vector<OrbitRow> iso_rows;
  if (o.isochronize) {
    job.iso.energies_MeV = job.energies;
    auto log = [&](const std::string& line) {
      if (!o.common.quiet) std::fprintf(stderr, "turnfit-orbit: %s\n", line.c_str());
    };
    IsochronizeResult r = isochronize(*job.spec, job.settings, job.iso, cli::resolve_threads(o.common.threads), log);
    if (!r.converged)
      cli::warn(o.common, "isochronize: stopped at max |df/f| = " + cli::fmt(r.history.back().max_rel, 3) +
                              " (goal " + cli::fmt(job.iso.tolerance, 3) + ")");
    job.spec = r.spec;
    job.map = make_sector_field(*job.spec);
    iso_rows = std::move(r.rows);
  }
  // Every output is written to its temporary first and all are renamed together at the end,
  // so a failure leaves none of them behind.
  std::optional<OutputFile> specout, mapout, out;
  if (!o.write_spec.empty()) {
    nlohmann::json doc = sector_spec_to_json(*job.spec);
    if (!o.common.no_provenance) doc["provenance"] = cli::provenance();
    specout.emplace(o.write_spec);
    specout->stream() << json_text(doc, 1) << "\n";
  }
  if (!o.write_map.empty()) {
    mapout.emplace(o.write_map);
    if (parse_map_format(o.write_map_format) == MapFormat::turnfit) write_turnfit_map(mapout->stream(), job.map);
    else write_psi_ring(mapout->stream(), job.map);
  }
  std::vector<OrbitRow> rows;
  if (!job.energies.empty()) {
    const bool show_progress = !o.common.quiet && cli::stderr_is_tty() && job.energies.size() > 64;
    // After --isochronize the final orbits at the same energies are already known.
    rows = !iso_rows.empty() ? std::move(iso_rows)
                             : orbit_table(job.map, job.settings, job.energies, cli::resolve_threads(o.common.threads),
                                           show_progress ? progress_bar : nullptr);
    out.emplace(o.common.output);
    write_orbit_table(out->stream(), rows, o.common.format, !o.common.no_provenance);
  }
  for (auto* f : {&specout, &mapout, &out})
    if (*f) (*f)->commit();

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
