// Unit tests of the machine file: validation messages, path resolution, design variables.
#include <catch2/catch.hpp>
#include <cmath>
#include <limits>
#include <map>
#include <set>

#include "../support.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/machine/machine.hpp"

using nlohmann::json;
using turnfit::Error;
using turnfit::ExitCode;
using turnfit::Machine;
using turnfit::test::test_file;

namespace {

// Values parsed from the JSON files or made by one or two decimal operations on them (0.847 + 0.25
// * 0.1, 0.847 * 0.95, 72.2 / 1000): exact up to a few ulps of double rounding. 1e-12 relative is
// ~4500 ulps, and a millionth of the smallest digit these files carry (1e-6 relative): a wrong
// scale, sum or bound shows.
constexpr double kArith = 1e-12;

// Runs f, requires a turnfit::Error with the given exit code, and returns its message.
template <class F>
std::string error_of(F&& f, ExitCode code) {
  try {
    f();
  } catch (const Error& e) {
    INFO("message: " << e.what());
    CHECK(static_cast<int>(e.code()) == static_cast<int>(code));
    return e.what();
  } catch (const std::exception& e) {
    FAIL("not a turnfit::Error: " << e.what());
  }
  FAIL("no error thrown");
  return {};
}

std::string machine_dir() { return test_file("machine"); }

json psi_doc() { return turnfit::read_json(test_file("machine/psi.json")); }

Machine from(const json& doc) { return turnfit::machine_from_json(doc, "psi.json", machine_dir()); }

Machine psi() { return turnfit::load_machine(test_file("machine/psi.json")); }

const turnfit::Cavity& cavity(const Machine& m, const std::string& name) {
  for (const auto& c : m.cavities)
    if (c.name == name) return c;
  throw std::runtime_error("no cavity " + name);
}

double doc_number(const Machine& m, const std::string& pointer) {
  return m.doc.at(json::json_pointer(pointer)).get<double>();
}

}  // namespace

TEST_CASE("machine: minimal file is valid and gets the defaults") {
  Machine m = turnfit::load_machine(test_file("machine/minimal.json"));
  CHECK(m.path == test_file("machine/minimal.json"));
  CHECK(m.dir == machine_dir());
  CHECK(m.field.map == machine_dir() + "/maps/ring.dat");
  CHECK(m.field.format == "psi-ring");
  CHECK(m.field.symmetry == 0);
  CHECK(m.field.scale == 1.0);
  CHECK(m.particle.species == "proton");
  CHECK(m.particle.mass_MeV == 938.27208816);
  CHECK(m.particle.charge_e == 1.0);
  CHECK(m.rf.frequency_MHz == 0.0);
  CHECK(m.rf.harmonic == 1);
  CHECK(m.cavities.empty());
  CHECK(m.trimcoils.empty());
  CHECK(m.probes.empty());
  CHECK_FALSE(m.injection.has_value());
  CHECK(m.effects.is_array());
  CHECK(m.dvars.empty());
  // The document keeps the path as written.
  CHECK(m.doc["field"]["map"] == "maps/ring.dat");
}

TEST_CASE("machine: PSI-like machine reads every section") {
  Machine m = psi();
  CHECK(m.name == "psi-ring-like");
  CHECK(m.field.symmetry == 8);
  CHECK(m.field.trimcoil_threshold_T == 0.5);
  CHECK(m.rf.harmonic == 6);
  CHECK(m.rf.frequency_MHz == 50.65);
  REQUIRE(m.cavities.size() == 5);
  const auto& ft = cavity(m, "ft");
  CHECK(ft.harmonic_factor == 3);
  CHECK(ft.type == "single-gap");
  CHECK(ft.gap_width_mm == 250);
  CHECK(ft.rshift_mm == 0);
  CHECK(ft.profile == machine_dir() + "/rffield2.dat");
  REQUIRE(m.trimcoils.size() == 17);
  CHECK(m.trimcoils[5].sectors == std::vector<int>{1, 3, 5, 7});
  CHECK(m.trimcoils[0].sectors.empty());
  CHECK(m.trimcoils[0].coefdenom.size() == 5);
  CHECK(m.trimcoils[0].phimax_deg == 360);
  CHECK(m.trimcoils[16].type == "psi-bfield-mirrored");
  CHECK(m.trimcoils[16].slope_per_mm == 0.6);
  REQUIRE(m.probes.size() == 2);
  CHECK(m.probes[0].step_mm == 0.05);
  REQUIRE(m.injection.has_value());
  CHECK(m.injection->energy_MeV == 72);
  CHECK(m.injection->pr_betagamma == -0.0154);
  CHECK(m.injection->z_mm == 0);
  CHECK(m.tracking.integrator == "rk4");
  CHECK(m.tracking.steps_per_turn == 2880);
  CHECK(m.effects.size() == 1);
  CHECK(m.effects[0]["type"] == "harmonic-error");
  // Defaults become explicit in the normalized document, so design variables can point there.
  CHECK(m.doc["cavities"][2]["rshift_mm"] == 0);
  CHECK(m.doc["injection"]["t_ns"] == 0);
}

TEST_CASE("machine: PSI-like machine exposes the paper's 48 built-in design variables") {
  Machine m = psi();
  std::set<std::string> expected = {
      "benergy", "prinit",   "rinit", "phiinit", "vchange",   "vftcav", "phift",  "phirfft",
      "pdisft",  "rftshift", "rri2a", "rri2phi", "rri2shift", "rrla",   "rrlphi", "rrlshift"};
  for (int k = 1; k <= 4; ++k) {
    std::string n = std::to_string(k);
    for (const char* p : {"vmaincav", "phimain", "pdismain", "rmainshift"}) expected.insert(p + n);
  }
  for (int n = 1; n <= 16; ++n) {
    char buf[16];
    std::snprintf(buf, sizeof buf, "tc%02dmb", n);
    expected.insert(buf);
  }
  REQUIRE(expected.size() == 48);
  auto builtins = turnfit::builtin_dvars(m);
  std::set<std::string> names;
  for (const auto& [name, dv] : builtins) names.insert(name);
  CHECK(names == expected);
  CHECK(builtins.size() == 48);
  // The union also holds the file-defined tc17mb.
  CHECK(m.dvars.size() == 49);
  CHECK(m.dvars.count("tc17mb") == 1);
  for (const auto& [name, dv] : m.dvars) {
    INFO(name);
    CHECK(dv.name == name);
    CHECK_FALSE(dv.unit.empty());
    CHECK_FALSE(dv.description.empty());
    CHECK(dv.lower < dv.upper);
    double v = turnfit::dvar_value(m, name);
    CHECK(v >= dv.lower);
    CHECK(v <= dv.upper);
  }
}

TEST_CASE("machine: built-in design variables have the documented targets and bounds") {
  Machine m = psi();
  const auto& v1 = m.dvars.at("vmaincav1");
  REQUIRE(v1.targets.size() == 1);
  CHECK(v1.targets[0].pointer == "/cavities/0/voltage_MV");
  CHECK(v1.lower == Approx(0.847 * 0.95).epsilon(kArith));
  CHECK(v1.upper == Approx(0.847 * 1.05).epsilon(kArith));
  const auto& vft = m.dvars.at("vftcav");
  CHECK(vft.targets[0].pointer == "/cavities/2/voltage_MV");
  const auto& be = m.dvars.at("benergy");
  CHECK(be.unit == "GeV");
  CHECK(be.targets[0].scale == 1000);
  CHECK(be.lower == Approx(0.0715).epsilon(kArith));
  CHECK(be.upper == Approx(0.0725).epsilon(kArith));
  CHECK(turnfit::dvar_value(m, "benergy") == Approx(0.072).epsilon(kArith));
  const auto& vc = m.dvars.at("vchange");
  REQUIRE(vc.targets.size() == 4);
  for (const auto& t : vc.targets) {
    CHECK(t.add);
    CHECK(t.scale == 0.25);
  }
  CHECK(vc.lower == -0.2);
  CHECK(vc.upper == 0.2);
  CHECK(m.dvars.at("phimain2").lower == 124);
  CHECK(m.dvars.at("phirfft").upper == Approx(154.4).epsilon(kArith));
  CHECK(m.dvars.at("pdisft").lower == 447);
  CHECK(m.dvars.at("rmainshift3").upper == 5);
  CHECK(m.dvars.at("rrlphi").lower == 169);
  CHECK(m.dvars.at("rrlshift").targets[0].pointer == "/probes/1/shift_mm");
  CHECK(m.dvars.at("rinit").upper == 2050);
  CHECK(m.dvars.at("prinit").lower == Approx(-0.0204).epsilon(kArith));
  // TC1 has bmax -1e-3 T: bounds are symmetric, |v| + 2 mT.
  CHECK(m.dvars.at("tc01mb").lower == Approx(-3e-3).epsilon(kArith));
  CHECK(m.dvars.at("tc01mb").upper == Approx(3e-3).epsilon(kArith));
  CHECK(m.dvars.at("tc02mb").upper == Approx(2e-3).epsilon(kArith));
  // rri2phi bounds are overridden by the file, its target is not.
  CHECK(m.dvars.at("rri2phi").lower == 183);
  CHECK(m.dvars.at("rri2phi").upper == 187);
  CHECK(m.dvars.at("rri2phi").targets[0].pointer == "/probes/0/phi_deg");
  CHECK(m.dvars.at("tc17mb").targets[0].pointer == "/trimcoils/16/bmax_T");
}

TEST_CASE("machine: built-ins exist only for the elements present, TC01 naming works") {
  json doc = psi_doc();
  doc["cavities"].erase(4);  // main4 gone: no vmaincav4 and no vchange
  doc.erase("injection");
  doc["trimcoils"][2]["name"] = "TC03";
  doc["probes"].erase(1);
  Machine m = from(doc);
  CHECK(m.dvars.count("vmaincav4") == 0);
  CHECK(m.dvars.count("vchange") == 0);
  CHECK(m.dvars.count("vmaincav3") == 1);
  CHECK(m.dvars.count("benergy") == 0);
  CHECK(m.dvars.count("rrla") == 0);
  CHECK(m.dvars.count("rri2a") == 1);
  REQUIRE(m.dvars.count("tc03mb") == 1);
  CHECK(m.dvars.at("tc03mb").targets[0].pointer == "/trimcoils/2/bmax_T");

  json both = psi_doc();
  both["trimcoils"][16]["name"] = "TC03";
  std::string msg = error_of([&] { from(both); }, ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("'TC3' and 'TC03'"));
}

TEST_CASE("machine: unknown key names the file and the JSON path") {
  std::string file = test_file("machine/bad_unknown.json");
  std::string msg = error_of([&] { turnfit::load_machine(file); }, ExitCode::data);
  CHECK(msg == file + ": /probes/0/colour: unknown key");

  json doc = psi_doc();
  doc["tracking"]["turn"] = 3;
  msg = error_of([&] { from(doc); }, ExitCode::data);
  CHECK(msg == "psi.json: /tracking/turn: unknown key (did you mean 'turns'?)");

  json top = psi_doc();
  top["comment"] = "x";
  msg = error_of([&] { from(top); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /comment: unknown key"));
}

TEST_CASE("machine: a key with the wrong unit suffix says which unit is expected") {
  std::string file = test_file("machine/bad_unit.json");
  std::string msg = error_of([&] { turnfit::load_machine(file); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith(file + ": /cavities/2/voltage_kV: unknown key"));
  CHECK_THAT(msg, Catch::Contains("wrong unit: expected 'voltage_MV'"));

  json doc = psi_doc();
  doc["injection"].erase("r_mm");
  doc["injection"]["r_m"] = 2.045;
  msg = error_of([&] { from(doc); }, ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("/injection/r_m: unknown key (wrong unit: expected 'r_mm')"));

  json nounit = psi_doc();
  nounit["probes"][1]["shift"] = 1;
  msg = error_of([&] { from(nounit); }, ExitCode::data);
  CHECK_THAT(msg,
             Catch::Contains("/probes/1/shift: unknown key (missing unit: expected 'shift_mm')"));

  // An unknown key is reported even when it also leaves a required key missing.
  json missing = psi_doc();
  missing["probes"][1].erase("s_max_mm");
  missing["probes"][1]["s_max_m"] = 4.5;
  msg = error_of([&] { from(missing); }, ExitCode::data);
  CHECK_THAT(msg,
             Catch::Contains("/probes/1/s_max_m: unknown key (wrong unit: expected 's_max_mm')"));
}

TEST_CASE("machine: wrong JSON types name the path") {
  json doc = psi_doc();
  doc["cavities"][0]["voltage_MV"] = "0.847";
  std::string msg = error_of([&] { from(doc); }, ExitCode::data);
  CHECK(msg == "psi.json: /cavities/0/voltage_MV: expected a number, got a string");

  json nan = psi_doc();
  nan["injection"]["phi_deg"] = std::numeric_limits<double>::quiet_NaN();
  msg = error_of([&] { from(nan); }, ExitCode::data);
  CHECK(msg == "psi.json: /injection/phi_deg: not a finite number");

  json frac = psi_doc();
  frac["field"]["symmetry"] = 8.5;
  msg = error_of([&] { from(frac); }, ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("/field/symmetry: expected an integer"));

  json integral = psi_doc();
  integral["field"]["symmetry"] = 8.0;  // JSON has one number type: 8.0 is fine
  CHECK(from(integral).field.symmetry == 8);

  json arr = psi_doc();
  arr["trimcoils"][3]["coefnum"][1] = true;
  msg = error_of([&] { from(arr); }, ExitCode::data);
  CHECK(msg == "psi.json: /trimcoils/3/coefnum/1: expected a number, got a boolean");

  json name = psi_doc();
  name["probes"][0]["name"] = 2;
  msg = error_of([&] { from(name); }, ExitCode::data);
  CHECK(msg == "psi.json: /probes/0/name: expected a string, got a number");

  json sec = psi_doc();
  sec["cavities"] = json::object();
  msg = error_of([&] { from(sec); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /cavities: expected a JSON array"));

  json root = json::array();
  msg = error_of([&] { from(root); }, ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("expected a JSON object"));
}

TEST_CASE("machine: ranges are checked (rmin < rmax and friends)") {
  json cav = psi_doc();
  cav["cavities"][1]["rmax_mm"] = 900;
  std::string msg = error_of([&] { from(cav); }, ExitCode::data);
  CHECK(msg == "psi.json: /cavities/1/rmax_mm: must be > rmin_mm (1003.38), got 900");

  json tc = psi_doc();
  tc["trimcoils"][4]["rmax_mm"] = tc["trimcoils"][4]["rmin_mm"];
  msg = error_of([&] { from(tc); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /trimcoils/4/rmax_mm: must be > rmin_mm"));

  json pr = psi_doc();
  pr["probes"][0]["s_min_mm"] = 3000;
  msg = error_of([&] { from(pr); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /probes/0/s_max_mm: must be > s_min_mm"));

  struct Case {
    const char* pointer;
    json value;
    const char* text;
  };
  for (const Case& c : {Case{"/cavities/0/harmonic_factor", 0, "must be > 0"},
                        Case{"/cavities/0/gap_width_mm", -1, "must be >= 0"},
                        Case{"/probes/1/step_mm", 0, "must be > 0"},
                        Case{"/injection/energy_MeV", 0, "must be > 0"},
                        Case{"/injection/r_mm", -5, "must be > 0"},
                        Case{"/rf/harmonic", 0, "must be >= 1"},
                        Case{"/rf/frequency_MHz", -1, "must be >= 0"},
                        Case{"/field/scale", 0, "must not be 0"},
                        Case{"/field/symmetry", -8, "must be >= 1"},
                        Case{"/field/trimcoil_threshold_T", -0.1, "must be >= 0"},
                        Case{"/tracking/turns", -1, "must be >= 0"},
                        Case{"/trimcoils/16/slope_per_mm", 0, "must be > 0"},
                        Case{"/trimcoils/6/sectors/1", 9, "sector 9 out of range (1..8)"},
                        Case{"/trimcoils/6/sectors/1", 1, "listed twice"},
                        Case{"/trimcoils/0/phimax_deg", -1, "must be > phimin_deg"},
                        Case{"/cavities/0/type", "double-gap", "unknown value 'double-gap'"},
                        Case{"/trimcoils/0/type", "psi", "unknown value 'psi'"},
                        Case{"/field/format", "opal", "unknown value 'opal'"},
                        Case{"/particle/species", "muon", "unknown value 'muon'"},
                        Case{"/format", "turnfit-machine/2", "expected 'turnfit-machine/1'"},
                        Case{"/effects/0/type", 3, "expected a non-empty string"}}) {
    json doc = psi_doc();
    doc[json::json_pointer(c.pointer)] = c.value;
    INFO(c.pointer << " = " << c.value.dump());
    msg = error_of([&] { from(doc); }, ExitCode::data);
    CHECK_THAT(msg, Catch::StartsWith(std::string("psi.json: ") + c.pointer + ": "));
    CHECK_THAT(msg, Catch::Contains(c.text));
  }
}

TEST_CASE("machine: required keys") {
  const std::map<std::string, std::string> expected = {
      {"/format", "missing required key"},
      {"/field", "missing required key"},
      {"/field/map", "missing required key"},
      {"/cavities/3/rmax_mm", "missing required key"},
      {"/cavities/3/name", "missing required key"},
      {"/trimcoils/0/coefnum", "a psi-bfield coil needs at least one numerator coefficient"},
      {"/trimcoils/16/slope_per_mm", "missing required key (type psi-bfield-mirrored)"},
      {"/probes/0/s_max_mm", "missing required key"},
      {"/injection/energy_MeV", "missing required key"},
      {"/injection/r_mm", "missing required key"},
      {"/effects/0/type", "missing required key"}};
  for (const auto& [pointer, text] : expected) {
    json doc = psi_doc();
    json::json_pointer p(pointer);
    doc[p.parent_pointer()].erase(p.back());
    INFO(pointer);
    std::string msg = error_of([&] { from(doc); }, ExitCode::data);
    CHECK(msg == "psi.json: " + pointer + ": " + text);
  }
  json table = psi_doc();
  table["trimcoils"][0]["type"] = "table";
  std::string msg = error_of([&] { from(table); }, ExitCode::data);
  CHECK(msg == "psi.json: /trimcoils/0/table: missing required key (type table)");
}

TEST_CASE("machine: particle species and masses") {
  auto with = [](json particle) {
    json doc = {{"format", "turnfit-machine/1"}, {"field", {{"map", "x"}}}, {"particle", particle}};
    return turnfit::machine_from_json(doc, "p.json", "");
  };
  CHECK(with({{"species", "deuteron"}}).particle.mass_MeV == 1875.61294257);
  CHECK(with({{"species", "alpha"}}).particle.charge_e == 2);
  CHECK(with({{"species", "alpha"}}).particle.mass_MeV == 3727.3794066);
  CHECK(with({{"species", "h2+"}}).particle.mass_MeV ==
        Approx(2 * 938.27208816 + 0.51099895 - 16.25e-6).epsilon(kArith));
  auto custom = with({{"species", "custom"}, {"mass_MeV", 139.57039}, {"charge_e", -1}});
  CHECK(custom.particle.mass_MeV == 139.57039);
  CHECK(custom.particle.charge_e == -1);
  std::string msg = error_of(
      [&] {
        with({{"species", "custom"}, {"charge_e", 1}});
      },
      ExitCode::data);
  CHECK(msg == "p.json: /particle/mass_MeV: missing required key");
  msg = error_of([&] { with({{"species", "proton"}, {"mass_MeV", 938}}); }, ExitCode::data);
  CHECK(msg == "p.json: /particle/mass_MeV: only allowed with species 'custom'");
  msg = error_of(
      [&] {
        with({{"species", "custom"}, {"mass_MeV", 1}, {"charge_e", 0}});
      },
      ExitCode::data);
  CHECK(msg == "p.json: /particle/charge_e: must not be 0");
}

TEST_CASE("machine: names must be unique within each list") {
  json doc = psi_doc();
  doc["cavities"][3]["name"] = "main1";
  std::string msg = error_of([&] { from(doc); }, ExitCode::data);
  CHECK(msg == "psi.json: /cavities/3/name: duplicate name 'main1' (also /cavities/0/name)");

  json tc = psi_doc();
  tc["trimcoils"][9]["name"] = "TC2";
  msg = error_of([&] { from(tc); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /trimcoils/9/name: duplicate name 'TC2'"));

  json pr = psi_doc();
  pr["probes"][1]["name"] = "RRI2";
  msg = error_of([&] { from(pr); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith("psi.json: /probes/1/name: duplicate name 'RRI2'"));

  // The same name in different lists is fine (a probe may share a trim coil's name).
  json mixed = psi_doc();
  mixed["probes"][1]["name"] = "TC2";
  CHECK_NOTHROW(from(mixed));
}

TEST_CASE("machine: relative paths are resolved against the machine file's folder") {
  std::string file = test_file("machine/sub/relative.json");
  Machine m = turnfit::load_machine(file);
  std::string dir = test_file("machine/sub");
  CHECK(m.dir == dir);
  CHECK(m.field.map == dir + "/../maps/ring.dat");
  REQUIRE(m.cavities.size() == 1);
  CHECK(m.cavities[0].profile == dir + "/profiles/main.dat");
  REQUIRE(m.trimcoils.size() == 2);
  CHECK(m.trimcoils[0].table == "/opt/turnfit/tc1.csv");  // absolute: kept
  CHECK(m.trimcoils[1].table == dir + "/tc2.csv");
  // The document keeps them as written (so it can be written out and read from elsewhere).
  CHECK(m.doc["field"]["map"] == "../maps/ring.dat");
  CHECK(m.doc["cavities"][0]["profile"] == "profiles/main.dat");
  CHECK(m.doc["trimcoils"][1]["table"] == "tc2.csv");
  // Built in memory without a folder: paths stay relative to the working directory.
  Machine mem = turnfit::machine_from_json(m.doc, "mem", "");
  CHECK(mem.field.map == "../maps/ring.dat");
  CHECK(mem.path.empty());
}

TEST_CASE("machine: files that cannot be read or parsed") {
  std::string msg = error_of(
      [] { turnfit::load_machine(test_file("machine/does-not-exist.json")); }, ExitCode::no_input);
  CHECK_THAT(msg, Catch::Contains("does-not-exist.json: cannot open"));
  msg =
      error_of([] { turnfit::load_machine(test_file("machine/bad_syntax.json")); }, ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("bad_syntax.json:4: invalid JSON"));
}

TEST_CASE("machine: --set by design-variable name and by JSON pointer") {
  Machine m = psi();
  turnfit::apply_sets(m, {"vmaincav2=0.86", "benergy=0.0722", "/rf/frequency_MHz=50.6",
                          "/trimcoils/0/coefnum/2=0.07", "tc17mb=0.002", "rri2phi=186.5"});
  CHECK(cavity(m, "main2").voltage_MV == 0.86);
  CHECK(turnfit::dvar_value(m, "vmaincav2") == 0.86);
  CHECK(m.injection->energy_MeV == Approx(72.2).epsilon(kArith));
  CHECK(turnfit::dvar_value(m, "benergy") == Approx(0.0722).epsilon(kArith));
  CHECK(m.rf.frequency_MHz == 50.6);
  CHECK(m.trimcoils[0].coefnum[2] == 0.07);
  CHECK(m.trimcoils[16].bmax_T == 0.002);
  CHECK(m.probes[0].phi_deg == 186.5);
  // Other cavities untouched; path, dir and the design variables survive the rebuild.
  CHECK(cavity(m, "main1").voltage_MV == 0.847);
  CHECK(m.path == test_file("machine/psi.json"));
  CHECK(m.dvars.size() == 49);
  CHECK(m.field.map == machine_dir() + "/bfield.dat");

  // Bounds stay those of the loaded machine, not re-centred on the new value.
  Machine n = psi();
  double upper = n.dvars.at("rinit").upper;
  turnfit::set_dvar(n, "rinit", upper);
  CHECK(n.injection->r_mm == upper);
  CHECK(n.dvars.at("rinit").upper == upper);
  CHECK_THROWS(turnfit::set_dvar(n, "rinit", upper + 1));
}

TEST_CASE("machine: out-of-bounds values are usage errors naming variable, value and bounds") {
  Machine m = psi();
  std::string msg = error_of([&] { turnfit::set_dvar(m, "vchange", 0.5); }, ExitCode::usage);
  CHECK(msg == "design variable vchange = 0.5 is outside its bounds [-0.2, 0.2] MV");
  msg = error_of([&] { turnfit::apply_sets(m, {"tc01mb=0.004"}); }, ExitCode::usage);
  CHECK(msg == "--set 'tc01mb=0.004': tc01mb = 0.004 is outside its bounds [-0.003, 0.003] T");
  msg = error_of([&] { turnfit::set_dvar(m, "nope", 1); }, ExitCode::usage);
  CHECK_THAT(msg, Catch::Contains("unknown design variable 'nope'"));
  msg = error_of([&] { turnfit::apply_sets(m, {"vmaincav5=0.8"}); }, ExitCode::usage);
  CHECK_THAT(msg, Catch::Contains("unknown design variable 'vmaincav5' (did you mean 'vmaincav"));
  // A failed --set list leaves the machine as it was, even the assignments before the bad one.
  msg = error_of(
      [&] {
        turnfit::apply_sets(m, {"vmaincav1=0.85", "vchange=0.3"});
      },
      ExitCode::usage);
  CHECK(cavity(m, "main1").voltage_MV == 0.847);
  CHECK(turnfit::dvar_value(m, "vchange") == 0);
}

TEST_CASE("machine: --set syntax and pointer errors") {
  Machine m = psi();
  for (const char* bad : {"vchange", "=0.1", "vchange=", ""}) {
    INFO(bad);
    std::string msg = error_of([&] { turnfit::apply_sets(m, {bad}); }, ExitCode::usage);
    CHECK(msg == std::string("--set '") + bad + "': expected NAME=VALUE");
  }
  for (const char* bad : {"vchange=abc", "vchange=0.1x", "vchange=1e999", "vchange=nan",
                          "vchange=inf", "vchange= 0.1", "vchange=0x1p-3"}) {
    INFO(bad);
    std::string msg = error_of([&] { turnfit::apply_sets(m, {bad}); }, ExitCode::usage);
    CHECK_THAT(msg, Catch::Contains("is not a finite number"));
  }
  std::string msg = error_of([&] { turnfit::apply_sets(m, {"/rf/harmonics=6"}); }, ExitCode::usage);
  CHECK(msg == "--set '/rf/harmonics=6': '/rf/harmonics' does not exist in the machine");
  msg = error_of([&] { turnfit::apply_sets(m, {"/field/map=3"}); }, ExitCode::usage);
  CHECK(msg == "--set '/field/map=3': '/field/map' is not a number");
  msg = error_of([&] { turnfit::apply_sets(m, {"/dvars/tc17mb/upper=1"}); }, ExitCode::usage);
  CHECK_THAT(msg, Catch::Contains("cannot be set"));
  // A pointer set that breaks the machine: usage error, machine unchanged.
  msg = error_of([&] { turnfit::apply_sets(m, {"/cavities/0/rmax_mm=10"}); }, ExitCode::usage);
  CHECK_THAT(msg, Catch::Contains("/cavities/0/rmax_mm: must be > rmin_mm"));
  CHECK(m.cavities[0].rmax_mm == 6203.38);
  msg = error_of([&] { turnfit::apply_sets(m, {"/rf/harmonic=6.5"}); }, ExitCode::usage);
  CHECK_THAT(msg, Catch::Contains("/rf/harmonic: expected an integer"));
  turnfit::apply_sets(m, {"/rf/harmonic=3"});
  CHECK(m.rf.harmonic == 3);
}

TEST_CASE("machine: vchange adds a quarter to each main cavity and does not accumulate") {
  Machine m = psi();
  turnfit::set_dvar(m, "vchange", 0.1);
  for (int k = 1; k <= 4; ++k)
    CHECK(cavity(m, "main" + std::to_string(k)).voltage_MV == Approx(0.872).epsilon(kArith));
  CHECK(cavity(m, "ft").voltage_MV == 0.555903);
  CHECK(turnfit::dvar_value(m, "vchange") == Approx(0.1).epsilon(kArith));
  // vmaincavK reads back the base voltage, without vchange's share.
  CHECK(turnfit::dvar_value(m, "vmaincav1") == Approx(0.847).epsilon(kArith));

  turnfit::set_dvar(m, "vchange", 0.1);  // the same value again: no change
  CHECK(cavity(m, "main3").voltage_MV == Approx(0.872).epsilon(kArith));
  turnfit::apply_sets(m, {"vchange=-0.04"});
  CHECK(cavity(m, "main3").voltage_MV == Approx(0.837).epsilon(kArith));
  turnfit::set_dvar(m, "vchange", 0);
  CHECK(cavity(m, "main3").voltage_MV == Approx(0.847).epsilon(kArith));

  // Order does not matter when a replacing and an adding variable hit the same voltage.
  Machine a = psi(), b = psi();
  turnfit::apply_sets(a, {"vchange=0.2", "vmaincav1=0.86"});
  turnfit::apply_sets(b, {"vmaincav1=0.86", "vchange=0.2"});
  CHECK(cavity(a, "main1").voltage_MV == Approx(0.91).epsilon(kArith));
  CHECK(cavity(b, "main1").voltage_MV == Approx(0.91).epsilon(kArith));
  CHECK(cavity(a, "main2").voltage_MV == Approx(0.897).epsilon(kArith));
  CHECK(turnfit::dvar_value(a, "vmaincav1") == Approx(0.86).epsilon(kArith));
  // A pointer write sets the base too.
  turnfit::apply_sets(a, {"/cavities/0/voltage_MV=0.85"});
  CHECK(cavity(a, "main1").voltage_MV == Approx(0.9).epsilon(kArith));
  CHECK(doc_number(a, "/cavities/0/voltage_MV") == Approx(0.9).epsilon(kArith));
}

TEST_CASE("machine: design variables from a file") {
  Machine m = psi();
  turnfit::apply_dvars_file(m, test_file("machine/dvars_ok.json"));
  CHECK(cavity(m, "main4").voltage_MV == Approx(0.872).epsilon(kArith));
  CHECK(m.injection->energy_MeV == Approx(72.2).epsilon(kArith));
  CHECK(m.trimcoils[2].bmax_T == 0.0025);
  CHECK(m.rf.frequency_MHz == 50.6);
  // Applying the same file twice gives the same machine.
  turnfit::apply_dvars_file(m, test_file("machine/dvars_ok.json"));
  CHECK(cavity(m, "main4").voltage_MV == Approx(0.872).epsilon(kArith));

  Machine fresh = psi();
  std::string file = test_file("machine/dvars_unknown.json");
  std::string msg = error_of([&] { turnfit::apply_dvars_file(fresh, file); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith(file + ": /vmaincav5: unknown design variable 'vmaincav5'"));
  CHECK(cavity(fresh, "main1").voltage_MV == 0.847);  // the valid vmaincav1 was not kept

  file = test_file("machine/dvars_bounds.json");
  msg = error_of([&] { turnfit::apply_dvars_file(fresh, file); }, ExitCode::data);
  CHECK(msg == file + ": /vchange: vchange = 0.5 is outside its bounds [-0.2, 0.2] MV");

  file = test_file("machine/dvars_notnum.json");
  msg = error_of([&] { turnfit::apply_dvars_file(fresh, file); }, ExitCode::data);
  CHECK(msg == file + ": /rinit: expected a number");

  file = test_file("machine/dvars_array.json");
  msg = error_of([&] { turnfit::apply_dvars_file(fresh, file); }, ExitCode::data);
  CHECK_THAT(msg, Catch::StartsWith(file + ": expected a JSON object"));

  msg = error_of([&] { turnfit::apply_dvars_file(fresh, test_file("machine/none.json")); },
                 ExitCode::no_input);
  CHECK_THAT(msg, Catch::Contains("none.json: cannot open"));
  msg = error_of([&] { turnfit::apply_dvars_file(fresh, test_file("machine/bad_syntax.json")); },
                 ExitCode::data);
  CHECK_THAT(msg, Catch::Contains("bad_syntax.json:4:"));
}

TEST_CASE("machine: the dvars section of a machine file is validated") {
  auto dvars_error = [](json entry, const std::string& name = "x") {
    json doc = psi_doc();
    doc["dvars"][name] = entry;
    return error_of([&] { from(doc); }, ExitCode::data);
  };
  CHECK(dvars_error({{"pointer", "/rf/frequency_MHz"}, {"lower", 50}}) ==
        "psi.json: /dvars/x/upper: missing required key");
  CHECK(dvars_error({{"pointer", "/rf/frequency"}, {"lower", 50}, {"upper", 51}}) ==
        "psi.json: /dvars/x/pointer: '/rf/frequency' does not exist in the machine");
  CHECK(dvars_error({{"pointer", "/name"}, {"lower", 50}, {"upper", 51}}) ==
        "psi.json: /dvars/x/pointer: '/name' is not a number");
  CHECK(dvars_error({{"pointer", "rf/frequency_MHz"}, {"lower", 50}, {"upper", 51}}) ==
        "psi.json: /dvars/x/pointer: JSON pointer must start with '/', got 'rf/frequency_MHz'");
  CHECK(dvars_error({{"pointer", "/rf/frequency_MHz"}, {"lower", 51}, {"upper", 50}}) ==
        "psi.json: /dvars/x: lower (51) must be < upper (50)");
  // Nominal 50.65 MHz against kHz-sized bounds: a unit slip.
  CHECK(dvars_error({{"pointer", "/rf/frequency_MHz"}, {"lower", 50000}, {"upper", 51000}}) ==
        "psi.json: /dvars/x: nominal value 50.65 is outside [50000, 51000]");
  CHECK(dvars_error({{"lower", 1}, {"upper", 2}}, "vmaincav7") ==
        "psi.json: /dvars/vmaincav7: needs 'pointer' or 'targets' ('vmaincav7' is not a built-in "
        "design "
        "variable of this machine)");
  CHECK(dvars_error({{"lower", 0.8}, {"upper", 0.9}, {"unit", "kV"}}, "vmaincav1") ==
        "psi.json: /dvars/vmaincav1/unit: a built-in design variable takes only lower, upper and "
        "description");
  CHECK(dvars_error(
            {{"pointer", "/rf/frequency_MHz"}, {"lower", 50}, {"upper", 51}, {"units", "MHz"}}) ==
        "psi.json: /dvars/x/units: unknown key (did you mean 'unit'?)");
  CHECK(dvars_error({{"targets", json::array({{{"pointer", "/cavities/0/pdis_mm"}, {"add", true}},
                                              {{"pointer", "/cavities/1/pdis_mm"}}})},
                     {"lower", -1},
                     {"upper", 1}}) ==
        "psi.json: /dvars/x/targets/1/add: all targets of a design variable must agree on 'add'");
  CHECK(dvars_error({{"pointer", "/rf/frequency_MHz"}, {"lower", 50}, {"upper", 51}}, "bad name") ==
        "psi.json: /dvars/bad name: design-variable names start with a letter and use letters, "
        "digits, '_', '.', '-'");

  // A multi-target, scaled, additive variable defined in the file.
  json doc = psi_doc();
  doc["dvars"]["pdisall"] = {
      {"targets",
       json::array({{{"pointer", "/cavities/0/pdis_mm"}, {"add", true}},
                    {{"pointer", "/cavities/1/pdis_mm"}, {"add", true}, {"scale", -1}}})},
      {"lower", -2},
      {"upper", 2},
      {"unit", "mm"}};
  Machine m = from(doc);
  CHECK(m.dvars.size() == 50);
  turnfit::set_dvar(m, "pdisall", 1.5);
  turnfit::set_dvar(m, "pdismain1", 420);
  CHECK(m.cavities[0].pdis_mm == Approx(421.5).epsilon(kArith));
  CHECK(m.cavities[1].pdis_mm == Approx(414.5).epsilon(kArith));
  CHECK(turnfit::dvar_value(m, "pdismain1") == Approx(420).epsilon(kArith));
  CHECK(turnfit::dvar_value(m, "pdisall") == Approx(1.5).epsilon(kArith));
}
