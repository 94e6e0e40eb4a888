// turnfit-orbit's library entry points, driven in-process with string streams.
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <unistd.h>

#include "../support.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/orbit/orbit_app.hpp"
#include "turnfit/physics/particle.hpp"

using namespace turnfit;
using Catch::Matchers::Contains;

namespace {
/// A small analytic 4-sector map written to a temporary turnfit-format file.
std::string write_test_map() {
  PolarGrid g;
  g.r_min_mm = 300;
  g.dr_mm = 10;
  g.nr = 151;
  g.ntheta = 45;
  g.symmetry = 4;
  PolarFieldMap map = make_field_map(
      g, [](double r, double th) { return 1.2 * (1 + 0.01 * r) * (1 + 0.35 * std::cos(4 * th)); }, "test flutter");
  char tmpl[] = "/tmp/turnfit-app-XXXXXX";
  int fd = ::mkstemp(tmpl);
  ::close(fd);
  std::ostringstream os;
  write_turnfit_map(os, map);
  write_output(tmpl, os.str());
  return tmpl;
}

}  // namespace

TEST_CASE("app: orbit table from a map file as CSV", "[app]") {
  const std::string map = write_test_map();
  OrbitOptions o;
  o.field_map = map;
  o.field_format = "turnfit";
  o.energies = "20:60:10";
  o.harmonic = 2;
  o.rf_MHz = 40;
  OrbitJob job = prepare_orbit(o);
  REQUIRE(job.energies.size() == 5);
  auto rows = orbit_table(job.map, job.settings, job.energies, 1);
  std::ostringstream os;
  write_orbit_table(os, rows, "csv", false);
  CsvTable t = CsvTable::parse(os.str(), "out");
  t.require_columns({"energy_MeV", "r_mm", "pr_mrad", "nu_r", "nu_z", "f_rev_MHz", "phase_slip_deg_per_turn", "status"});
  REQUIRE(t.rows() == 5);
  for (size_t i = 0; i < t.rows(); ++i) {
    CHECK(t.cell(i, t.column("status")) == "ok");
    CHECK(t.number(i, t.column("nu_r")) > 1.0);  // rising field: nu_r above 1
    CHECK(t.number(i, t.column("r_mm")) == Approx(rows[i].r_mm).epsilon(1e-9));
  }
  CHECK(t.comments().empty());
  std::remove(map.c_str());
}

TEST_CASE("app: JSON and text formats carry the same rows", "[app]") {
  const std::string map = write_test_map();
  OrbitOptions o;
  o.field_map = map;
  o.field_format = "turnfit";
  o.energies = "30,5000";  // the second cannot close
  OrbitJob job = prepare_orbit(o);
  auto rows = orbit_table(job.map, job.settings, job.energies, 1);
  std::ostringstream js, tx;
  write_orbit_table(js, rows, "json", true);
  write_orbit_table(tx, rows, "text", false);
  auto doc = nlohmann::json::parse(js.str());
  REQUIRE(doc["orbits"].size() == 2);
  CHECK(doc["orbits"][0]["r_mm"].get<double>() == Approx(rows[0].r_mm));
  CHECK(doc["orbits"][1]["r_mm"].is_null());
  CHECK_THAT(doc["orbits"][1]["status"].get<std::string>(), Contains("no closed orbit"));
  CHECK(doc["orbits"][0]["phase_slip_deg_per_turn"].is_null());  // no RF given
  CHECK_THAT(tx.str(), Contains("nu_r") && Contains("no closed orbit"));
  std::remove(map.c_str());
}

TEST_CASE("app: option errors are usage errors", "[app]") {
  OrbitOptions o;
  std::string msg;
  CHECK(turnfit::test::error_code([&] { prepare_orbit(o); }, &msg) == 64);
  CHECK_THAT(msg, Contains("machine file") && Contains("--field-map") && Contains("--sector-field"));
  o.field_map = "/no/such/map.dat";
  CHECK(turnfit::test::error_code([&] { prepare_orbit(o); }, &msg) == 64);  // energies missing
  o.energies = "72";
  CHECK(turnfit::test::error_code([&] { prepare_orbit(o); }, &msg) == 66);
  CHECK_THAT(msg, Contains("/no/such/map.dat"));
  o.sets = {"vmaincav1=0.8"};
  CHECK(turnfit::test::error_code([&] { prepare_orbit(o); }, &msg) == 64);
  CHECK_THAT(msg, Contains("machine file"));
  o.sets.clear();
  o.harmonic = 6;  // without --rf-MHz
  const std::string map = write_test_map();
  o.field_map = map;
  o.field_format = "turnfit";
  CHECK(turnfit::test::error_code([&] { prepare_orbit(o); }, &msg) == 64);
  std::remove(map.c_str());
}

TEST_CASE("app: the PSI Ring machine example reproduces the reference rows", "[app][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  OrbitOptions o;
  o.machine = std::string(TURNFIT_TEST_DIR) + "/../examples/psi-ring/ring.json";
  o.energies = "72,369.995";
  OrbitJob job = prepare_orbit(o);
  CHECK(job.settings.harmonic == 6);
  CHECK(job.settings.rf_MHz == 50.65);
  auto rows = orbit_table(job.map, job.settings, job.energies, 1);
  // FIXPO's reference rows (physics.md) within the accuracy the README and turnfit-orbit(1)
  // promise: r within 0.05 mm (FIXPO gives 0.1 mm), nu_r within 0.0012, nu_z within 0.0016.
  CHECK(rows[0].r_mm == Approx(2131.4).epsilon(0).margin(0.05));
  CHECK(rows[0].nu_r == Approx(1.1565).epsilon(0).margin(0.0012));
  CHECK(rows[0].nu_z == Approx(0.9001).epsilon(0).margin(0.0016));
  CHECK(rows[1].r_mm == Approx(3938.6).epsilon(0).margin(0.05));
  CHECK(rows[1].nu_r == Approx(1.4519).epsilon(0).margin(0.0012));
  CHECK(rows[1].nu_z == Approx(0.8841).epsilon(0).margin(0.0016));
  // The same through --set on the machine. Scaling the field by s is scaling the rigidity by
  // 1/s: the 72 MeV orbit in the 1.001 field is the unscaled map's orbit at p/1.001 (72 - 0.139
  // MeV), 1.64 mm further in. Exact up to the orbit finder's convergence (step count: 2e-6 mm,
  // turnfit-orbit(1)); 1e-4 mm, where a scale not applied, or applied twice, is 1.6 mm off.
  o.sets = {"/field/scale=1.001"};
  OrbitJob scaled_job = prepare_orbit(o);
  auto srows = orbit_table(scaled_job.map, scaled_job.settings, scaled_job.energies, 1);
  const double m = job.settings.mass_MeV;
  const double bg = kinematics(m, 1, 72.0).betagamma / 1.001;
  const double e_equiv = m * (std::sqrt(1 + bg * bg) - 1);
  const OrbitRow equiv = closed_orbit(job.map, job.settings, e_equiv);
  REQUIRE(equiv.ok());
  CHECK(srows[0].r_mm == Approx(equiv.r_mm).epsilon(0).margin(1e-4));
  CHECK(srows[0].nu_r == Approx(equiv.nu_r).epsilon(0).margin(1e-6));  // same orbit: same tunes (step count: 1e-6)
  CHECK(srows[0].r_mm < rows[0].r_mm - 1.0);
}
