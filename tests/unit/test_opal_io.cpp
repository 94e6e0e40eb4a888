// OPAL input language, turnfit-import-opal and turnfit-export-opal: expressions against values
// worked by hand, the shipped OPAL inputs, and exports that import back to the same machine.
#include <catch2/catch.hpp>
#include <cmath>
#include <filesystem>
#include <fstream>

#include "../support.hpp"
#include "turnfit/field/map_io.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/opal/annotation.hpp"
#include "turnfit/opal/opal_input.hpp"
#include "turnfit/opal/opal_io.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

using namespace turnfit;
using nlohmann::json;

namespace {

// The value of attribute X of the first command of `text` ("C, X = <expr>;" appended).
double eval(const std::string& defs, const std::string& expr, double version = kDefaultOpalVersion) {
  opal::Input in(defs + "\nC, X = " + expr + ";", "t.in", version);
  const auto& c = in.commands().back();
  return in.number(*c.find("X"));
}

std::string eval_error(const std::string& defs, const std::string& expr) {
  std::string msg;
  const int code = test::error_code([&] { eval(defs, expr); }, &msg);
  CHECK(code == 65);
  return msg;
}

std::string ring8(const std::string& f) { return std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/" + f; }
std::string aeo() { return std::string(TURNFIT_TEST_DIR) + "/../examples/psi-ring/aeo.json"; }

// A machine document with every path made absolute, to compare machines read from different folders.
json absolute_paths(json doc, const std::string& dir) {
  rebase_paths(doc, dir, "/");
  json out = doc;
  std::function<void(json&)> prefix;
  auto fix = [](json& p) {
    if (p.is_string() && !p.get<std::string>().empty() && p.get<std::string>()[0] != '/') p = "/" + p.get<std::string>();
  };
  if (out.contains("field") && out["field"].contains("map")) fix(out["field"]["map"]);
  for (const char* l : {"cavities", "trimcoils"})
    if (out.contains(l))
      for (auto& e : out[l])
        for (const char* k : {"profile", "table"})
          if (e.contains(k)) fix(e[k]);
  if (out.contains("bunch") && out["bunch"].contains("file")) fix(out["bunch"]["file"]);
  return out;
}

// The text without the turnfit annotation: what OPAL's commands alone say.
std::string commands_only(const std::string& text) {
  std::string out;
  for (std::string_view l : split_lines(text))
    if (l.rfind("//turnfit|", 0) != 0) out += std::string(l) + "\n";
  return out;
}

// Every line the import read and did not use has its reason (nothing "not understood").
void check_explained(const OpalImport& r) {
  for (const auto& n : r.notes) {
    INFO(n.line << ": " << n.text);
    CHECK(n.explained);
  }
}

struct Exported {
  test::TempDir dir;
  std::string text;
  std::vector<std::string> warnings;
};

// Exports a machine into a fresh folder (the map in OPAL's format there when asked).
void export_into(Exported& e, const Machine& m, bool map_out) {
  std::string map;
  if (map_out) {
    map = "map.dat";
    std::ofstream os(e.dir.path + "/" + map);
    write_psi_ring(os, read_field_map(m.field.map, parse_map_format(m.field.format), m.field.symmetry));
  }
  e.text = export_opal(m, e.dir.path, map, "dist1.dat", e.warnings);
  std::ofstream(e.dir.path + "/dist1.dat") << "1\n0 0 0 0 0 0\n";
}

}  // namespace

TEST_CASE("opal input: arithmetic, precedence, functions and constants as OPAL has them", "[opal]") {
  CHECK(eval("", "1 + 2 * 3") == 7);
  CHECK(eval("", "(1 + 2) * 3") == 9);
  CHECK(eval("", "2 ^ 3 ^ 1") == 8);
  CHECK(eval("", "-2 ^ 2") == -4);  // OPAL: -a^2 is -(a^2)
  CHECK(eval("", "10 / 4") == 2.5);
  CHECK(eval("", "SQRT(16) + ABS(-2) + MAX(1, 3) + MIN(1, 3)") == 10);
  CHECK(eval("", "sin(pi / 2)") == Approx(1).epsilon(1e-15));
  CHECK(eval("", "ATAN2(1, 1) * RADDEG") == Approx(45).epsilon(1e-15));
  CHECK(eval("", "LOG(E)") == Approx(1).epsilon(1e-15));
  CHECK(eval("", "TRUNC(-2.5) + ROUND(2.5) + FLOOR(-0.5) + CEIL(0.5) + SIGN(-3)") == -2 + 3 - 1 + 1 - 1);
  CHECK(eval("", "MOD(7, 3) + POW(2, 10)") == 1 + 1024);
  CHECK(eval("", "PMASS") == 0.93827208816);  // GeV, as OPAL's inputs use it
  CHECK(eval("", "1.0E-6 * 2") == 2e-6);
  CHECK(eval("", "OPALVERSION") == 20220100);
  CHECK(eval("", "(1 < 2) && (2 >= 2) || (3 == 4)") == 1);
  // cyclotron2.in's own arithmetic: the flat-top voltage and the beam momentum.
  CHECK(eval("REAL volt1st = 0.847; REAL ptg = 1.465;", "volt1st*4.0*0.112*ptg") == 0.847 * 4.0 * 0.112 * 1.465);
  const double g = (0.072 + 0.93827208816) / 0.93827208816;
  CHECK(eval("REAL Edes = 0.072; REAL gamma=(Edes+PMASS)/PMASS; REAL beta=sqrt(1-(1/gamma^2));",
             "gamma*beta*PMASS") == g * std::sqrt(1 - 1 / std::pow(g, 2)) * 0.93827208816);
  CHECK(opal::parse_opal_version("2022.1") == 20220100);
  CHECK(opal::parse_opal_version("2.0") == 20000);
  CHECK(opal::parse_opal_version("20100") == 20100);
  CHECK(test::error_code([] { opal::parse_opal_version("new"); }) == 64);
}

TEST_CASE("opal input: '=' is evaluated where it stands, ':=' where it is used", "[opal]") {
  // OPAL (and MAD): b = a + 1 takes a's value then; c := a + 1 its last.
  const std::string defs = "REAL a = 1; REAL b = a + 1; REAL c := a + 1; a = 10;";
  CHECK(eval(defs, "b") == 2);
  CHECK(eval(defs, "c") == 11);
  CHECK(eval("REAL a = 1; C, Y = a; a = 5;", "a") == 5);
}

TEST_CASE("opal input: errors name the line and the token", "[opal]") {
  std::string m = eval_error("REAL a = 1;", "a + bogus");
  CHECK(m.find("t.in:2:") != std::string::npos);
  CHECK(m.find("undefined variable 'bogus'") != std::string::npos);
  m = eval_error("", "1 / (2 - 2)");
  CHECK(m.find("division by zero at '/'") != std::string::npos);
  m = eval_error("REAL a := b + 1;\nREAL b := a * 2;", "a");
  CHECK(m.find("circular definition") != std::string::npos);
  CHECK(m.find("a -> b -> a") != std::string::npos);
  m = eval_error("REAL a = b + 1;\nREAL b = 2;", "a");  // '=' evaluates at once, as OPAL does
  CHECK(m.find("t.in:1: undefined variable 'b'") != std::string::npos);
  std::string late;
  CHECK(test::error_code([&] {
          opal::Input in("C, X = b;\nREAL b = 2;", "t.in", 1);
          in.number(*in.commands().front().find("X"));
        }, &late) == 65);
  CHECK(late.find("t.in:1: variable 'b' is used before its definition (line 2") != std::string::npos);
  m = eval_error("REAL CONST k = 1;\nk = 2;", "k");
  CHECK(m.find("t.in:2:") != std::string::npos);
  CHECK(m.find("cannot be redefined") != std::string::npos);
  m = eval_error("", "LOG10(100)");  // OPAL has no LOG10
  CHECK(m.find("unknown function 'LOG10'") != std::string::npos);
  m = eval_error("", "SQRT(-1)");
  CHECK(m.find("'SQRT': argument out of its domain") != std::string::npos);
  m = eval_error("", "1 +");
  CHECK(m.find("expression ends early") != std::string::npos);
  std::string msg;
  CHECK(test::error_code([&] { opal::Input("X: CYCLOTRON, FMAPFN = \"a.dat;\nY: PROBE;", "t.in", 1); }, &msg) == 65);
  CHECK(msg.find("t.in:1: string") != std::string::npos);
  CHECK(test::error_code([&] { opal::Input("/* never closed\nA: LINE = (B);", "t.in", 1); }, &msg) == 65);
  CHECK(msg.find("never closed") != std::string::npos);
  CHECK(test::error_code([&] { opal::Input("X = 3;", "t.in", 1); }, &msg) == 65);
  CHECK(msg.find("needs REAL") != std::string::npos);
  CHECK(test::error_code([&] { opal::Input("IF (1 > 0) { REAL a = 1;", "t.in", 1); }, &msg) == 65);
  CHECK(msg.find("closing the IF block") != std::string::npos);
}

TEST_CASE("opal input: strings quoted, from STRING variables, or bare words upper-cased as OPAL reads them", "[opal]") {
  opal::Input in("STRING f = \"map.dat\";\nC, A = \"x.dat\", B = f, D = bfield.dat, E = 'y';", "t.in", 1);
  const auto& c = in.commands().back();
  CHECK(in.string(*c.find("A")) == "x.dat");
  CHECK(in.string(*c.find("B")) == "map.dat");
  CHECK(in.string(*c.find("D")) == "BFIELD.DAT");
  CHECK(in.string(*c.find("E")) == "y");
}

TEST_CASE("opal input: IF blocks take the branch of the OPAL version asked for", "[opal]") {
  const std::string text =
      "IF (OPALVERSION >= 20100) {\n  REAL x = 1;\n} ELSE {\n  REAL x = 2;\n}\nC, Y = x;";
  for (auto [version, want] : {std::pair<double, double>{20220100, 1}, {20000, 2}}) {
    opal::Input in(text, "t.in", version);
    CHECK(in.number(*in.commands().back().find("Y")) == want);
  }
}

TEST_CASE("opal import: cyclotron2.in as OPAL 2022.1 reads it, every line explained", "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/cyclotron2.in");
  const std::string dir = std::filesystem::path(path).parent_path().string();
  const OpalImport r = import_opal(read_input(path).text, path, dir, dir);
  check_explained(r);
  const Machine m = machine_from_json(r.machine, "imported", dir);
  REQUIRE(m.cavities.size() == 5);
  CHECK(m.cavities[2].name == "Rf2");
  CHECK(m.cavities[2].voltage_MV == 0.847 * 4.0 * 0.112 * 1.465);
  CHECK(m.cavities[2].harmonic_factor == 3);
  CHECK(m.cavities[2].phase_deg == 111.40 + 36 + 2);
  CHECK(m.cavities[1].phase_deg == 192.0 + 12 + 180.0);
  CHECK(m.rf.harmonic == 6);
  CHECK(m.rf.frequency_MHz == 50.65);
  REQUIRE(m.injection);
  CHECK(m.injection->energy_MeV == 72.0);
  CHECK(m.injection->r_mm == 2045);
  CHECK(m.injection->pr_betagamma == -0.0154);
  CHECK(m.injection->phi_deg == 110);
  CHECK(m.tracking.turns == 190);
  CHECK(m.tracking.steps_per_turn == 1800);
  // 2022.1 reads the unset PHIMIN/PHIMAX as 0: the coil acts nowhere, and the description says so.
  REQUIRE(m.trimcoils.size() == 1);
  CHECK(m.trimcoils[0].type == "psi-bfield-mirrored");
  CHECK(m.trimcoils[0].bmax_T == 0);
  CHECK(m.trimcoils[0].slope_per_mm == 0.6);
  CHECK(r.machine["description"].get<std::string>().find("acts nowhere") != std::string::npos);
  // Read as OPAL 2.0: the ELSE branch's PSI-RING-OLD, which neither OPAL 2022.1 nor turnfit has.
  const OpalImport old = import_opal(read_input(path).text, path, dir, dir, 20000);
  bool flagged = false;
  for (const auto& n : old.notes) flagged = flagged || (!n.explained && n.text.find("PSI-RING-OLD") != std::string::npos);
  CHECK(flagged);
}

TEST_CASE("opal import: cyclotronTune-2-1.in, every line explained", "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/cyclotronTune-2-1.in");
  const std::string dir = std::filesystem::path(path).parent_path().string();
  const OpalImport r = import_opal(read_input(path).text, path, dir, dir);
  check_explained(r);
  const Machine m = machine_from_json(r.machine, "imported", dir);
  CHECK(m.cavities.empty());
  CHECK(m.injection->r_mm == 2037);
  CHECK(m.injection->pr_betagamma == -0.0164);
  CHECK(m.tracking.turns == 1);
  CHECK(m.tracking.steps_per_turn == 720);
}

TEST_CASE("opal export: ring8 and the PSI example import back to the same machine", "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  for (const std::string& file : {aeo(), ring8("machine.json")}) {
    INFO(file);
    const Machine m = load_machine(file);
    Exported e;
    const bool turnfit_map = m.field.format != "psi-ring";
    export_into(e, m, turnfit_map);
    const OpalImport back = import_opal(e.text, e.dir.path + "/x.in", e.dir.path, e.dir.path);
    CHECK(back.from_annotation);
    check_explained(back);
    const Machine m2 = machine_from_json(back.machine, "back", e.dir.path);
    // Exactly the same document, paths aside (they are relative to another folder).
    CHECK(absolute_paths(m2.doc, e.dir.path) == absolute_paths(m.doc, m.dir));
    CHECK(m2.field.map == (std::filesystem::path(e.dir.path) / back.machine["field"]["map"].get<std::string>()).string());

    // The commands alone (the annotation removed): the same numbers to the digits the
    // conversions keep, and the differences turnfit-export-opal(1) names.
    const OpalImport bare = import_opal(commands_only(e.text), e.dir.path + "/x.in", e.dir.path, e.dir.path);
    CHECK_FALSE(bare.from_annotation);
    const Machine b = machine_from_json(bare.machine, "bare", e.dir.path);
    CHECK(b.particle.species == m.particle.species);
    CHECK(b.rf.harmonic == m.rf.harmonic);
    CHECK(b.rf.frequency_MHz == m.rf.frequency_MHz);
    CHECK(b.injection->energy_MeV == Approx(m.injection->energy_MeV).epsilon(1e-14));
    CHECK(b.injection->r_mm == m.injection->r_mm);
    CHECK(b.injection->pr_betagamma == m.injection->pr_betagamma);
    CHECK(b.injection->phi_deg == m.injection->phi_deg);
    CHECK(b.field.symmetry == m.field.symmetry);
    CHECK(b.field.trimcoil_threshold_T == m.field.trimcoil_threshold_T);
    REQUIRE(b.cavities.size() == m.cavities.size());
    for (size_t i = 0; i < m.cavities.size(); ++i) {
      const Cavity &x = m.cavities[i], &y = b.cavities[i];
      CHECK(y.name == x.name);
      CHECK(y.voltage_MV == x.voltage_MV);
      CHECK(y.harmonic_factor == x.harmonic_factor);
      CHECK(y.phase_deg == x.phase_deg);
      CHECK(y.angle_deg == x.angle_deg);
      CHECK(y.pdis_mm == x.pdis_mm);
      CHECK(y.rmin_mm == x.rmin_mm + x.rshift_mm);
      CHECK(y.rmax_mm == x.rmax_mm + x.rshift_mm);
      CHECK(y.gap_width_mm == x.gap_width_mm);
      CHECK(std::filesystem::weakly_canonical(y.profile) == std::filesystem::weakly_canonical(x.profile));
    }
    REQUIRE(b.trimcoils.size() == m.trimcoils.size());
    for (size_t i = 0; i < m.trimcoils.size(); ++i) {
      const TrimCoil &x = m.trimcoils[i], &y = b.trimcoils[i];
      CHECK(y.name == x.name);
      CHECK(y.type == x.type);
      CHECK(y.bmax_T == x.bmax_T);
      CHECK(y.rmin_mm == x.rmin_mm);
      CHECK(y.rmax_mm == x.rmax_mm);
      CHECK(y.coefnum == x.coefnum);
      CHECK(y.coefdenom == x.coefdenom);
      CHECK(y.slope_per_mm == x.slope_per_mm);
      CHECK(y.phimin_deg == x.phimin_deg);
      CHECK(y.phimax_deg == x.phimax_deg);
    }
    REQUIRE(b.probes.size() == m.probes.size());
    for (size_t i = 0; i < m.probes.size(); ++i) {
      const Probe &x = m.probes[i], &y = b.probes[i];
      CHECK(y.name == x.name);
      CHECK(y.step_mm == x.step_mm);
      CHECK(y.phi_deg == Approx(x.phi_deg).margin(1e-12));
      CHECK(y.a_mm == Approx(x.a_mm).margin(1e-9));
      CHECK(y.s_min_mm == Approx(x.s_min_mm + x.shift_mm).margin(1e-9));
      CHECK(y.s_max_mm == Approx(x.s_max_mm + x.shift_mm).margin(1e-9));
    }
    // Named in the man page: name and description, the bunch, and the integrator settings
    // OPAL has no word for come back only with the annotation.
    CHECK(b.name == "x");
    CHECK_FALSE(b.bunch);
  }
}

TEST_CASE("opal export: an edited export takes the edited sections from its commands, the rest from the annotation",
          "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  Machine m = load_machine(ring8("machine.json"));
  Exported e;
  export_into(e, m, true);
  std::string text = e.text;
  const std::string volt = "VOLT = 0.85672104,";
  size_t at = text.find(volt);
  REQUIRE(at != std::string::npos);
  text.replace(at, volt.size(), "VOLT = 0.9,");
  const OpalImport r = import_opal(text, e.dir.path + "/x.in", e.dir.path, e.dir.path);
  CHECK_FALSE(r.from_annotation);
  CHECK(r.machine["cavities"][0]["voltage_MV"] == 0.9);
  // What OPAL cannot say survives the edit: the name, the bunch, the exact probe geometry.
  CHECK(r.machine["name"] == "ring8");
  CHECK(r.machine["bunch"]["sigma_E_MeV"] == 0.03);
  CHECK(r.machine["probes"] == m.doc["probes"]);
  CHECK(r.machine["description"].get<std::string>().find("Edited in OPAL after turnfit-export-opal: cavities") !=
        std::string::npos);
  bool said = false;
  for (const auto& n : r.notes) said = said || n.text.find("cavities changed since") != std::string::npos;
  CHECK(said);

  // An edit the annotation's machine no longer fits (an effect names a cavity that was
  // renamed in OPAL): the machine comes from the commands alone, with a warning.
  m.doc["effects"] = json::array({{{"type", "voltage-tilt"}, {"cavity", "main1"}, {"slope", 0.01}}});
  revalidate(m);
  Exported f;
  export_into(f, m, true);
  text = f.text;
  at = text.find("main1: RFCAVITY");
  REQUIRE(at != std::string::npos);
  text.replace(at, 5, "gapA1");
  for (size_t k = text.find("main1,"); k != std::string::npos; k = text.find("main1,")) text.replace(k, 5, "gapA1");
  const OpalImport s = import_opal(text, f.dir.path + "/x.in", f.dir.path, f.dir.path);
  CHECK(s.machine["cavities"][0]["name"] == "gapA1");
  CHECK_FALSE(s.machine.contains("effects"));
  CHECK(s.machine["name"] == "x");
  bool warned = false;
  for (const auto& n : s.notes) warned = warned || (!n.explained && n.text.find("no longer fit") != std::string::npos);
  CHECK(warned);
}

TEST_CASE("opal export: a fit exports with its values, and OPAL's sign and window conventions", "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  Machine m = load_machine(ring8("machine.json"));
  set_dvar(m, "tc03mb", 1.5e-4);
  Exported e;
  export_into(e, m, true);
  // PSI-BFIELD: OPAL's BMAX is -bmax_T (physics.md); 2022.1 needs the window written out.
  CHECK(e.text.find("TC3: TRIMCOIL, TYPE = \"PSI-BFIELD\", RMIN = 1965, RMAX = 2715, BMAX = -0.00015,") != std::string::npos);
  CHECK(e.text.find("PHIMIN = 0, PHIMAX = 360;") != std::string::npos);
  const OpalImport bare = import_opal(commands_only(e.text), e.dir.path + "/x.in", e.dir.path, e.dir.path);
  CHECK(bare.machine["trimcoils"][2]["bmax_T"] == 1.5e-4);
}

TEST_CASE("opal export: coils about an origin, phase coils and windows through azimuth 0 come back as the same fields",
          "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  Machine m = load_machine(aeo());
  // A psi-phase coil as turnfit-tc-fit writes it (about its window centre, r in m from 4.4 m),
  // on sectors 1 and 3, in a window from 300 to 420 deg.
  m.doc["trimcoils"].push_back({{"name", "TCx"}, {"type", "psi-phase"}, {"rmin_mm", 4300.0}, {"rmax_mm", 4500.0},
                                {"bmax_T", 2e-4}, {"coef_origin_mm", 4400.0}, {"coefnum", {0.1, 3.0, -20.0}},
                                {"coefdenom", {1.0, 0.5, 40.0}}, {"sectors", {1, 3}}, {"phimin_deg", 300.0},
                                {"phimax_deg", 420.0}});
  revalidate(m);
  Exported e;
  export_into(e, m, false);
  bool warned = false;
  for (const auto& w : e.warnings) warned = warned || w.find("'TCx' sits on sectors") != std::string::npos;
  CHECK(warned);
  CHECK(e.text.find("TCx: TRIMCOIL, TYPE = \"PSI-PHASE\", RMIN = 4300, RMAX = 4500, BMAX = -0.0002,") != std::string::npos);
  CHECK(e.text.find("PHIMIN = 300, PHIMAX = 60;") != std::string::npos);
  const OpalImport bare = import_opal(commands_only(e.text), e.dir.path + "/x.in", e.dir.path, e.dir.path);
  const Machine b = machine_from_json(bare.machine, "bare", e.dir.path);
  REQUIRE(b.trimcoils.size() == 2);
  const TrimCoil &x = m.trimcoils[1], &y = b.trimcoils[1];
  CHECK(y.type == "psi-phase");
  CHECK(y.coef_origin_mm == 0);
  CHECK(y.phimin_deg == 300);
  CHECK(y.phimax_deg == 420);
  CHECK(y.sectors.empty());  // OPAL spreads a coil over every sector (warned above)
  // The expanded polynomials give the same shape on the coil's window, to rounding.
  TrimCoil xs = x, ys = y;
  xs.bmax_T = ys.bmax_T = 1;
  xs.sectors.clear();
  TrimCoilField fx(xs, 1), fy(ys, 1);
  double worst = 0, peak = 0;
  for (int i = 0; i <= 200; ++i) {
    const double r = 4.3 + 0.2 * i / 200;
    double a, da, c, dc;
    fx.shape_exact(r, a, da);
    fy.shape_exact(r, c, dc);
    worst = std::max(worst, std::fabs(a - c));
    peak = std::max(peak, std::fabs(a));
  }
  CHECK(peak > 0);
  CHECK(worst <= 1e-9 * peak);
}

TEST_CASE("opal input: STOP ends the input, ':=' values are taken at the RUN", "[opal]") {
  // OPAL reads no further than STOP: an undefined name or an unclosed string after it is no error.
  opal::Input in("REAL b = 1;\nREAL a := b * 2;\nC, X := a, Y = a;\nb = 5;\nRUN, METHOD = \"CYCLOTRON-T\";\nb = 7;\n"
                 "STOP;\nREAL y = undefined;\n\"unclosed\n",
                 "t.in", 1);
  const auto& cmds = in.commands();
  REQUIRE(cmds.size() == 3);  // C, RUN, STOP
  const auto& c = cmds[0];
  CHECK(in.number(*c.find("Y")) == 2);   // '=': where it stands (b = 1)
  CHECK(in.number(*c.find("X")) == 14);  // ':=': after the whole input (b = 7) ...
  in.set_evaluation_point(cmds[1].seq);
  CHECK(in.number(*c.find("X")) == 10);  // ... or at the RUN (b = 5), as the importer asks
  bool noted = false;
  for (const auto& n : in.notes()) noted = noted || n.text.find("OPAL reads no further (2 more lines not read)") != std::string::npos;
  CHECK(noted);
}

TEST_CASE("opal import: what the machine cannot hold is refused at its line", "[opal]") {
  const std::string head =
      "R: CYCLOTRON, TYPE = \"RING\", FMAPFN = \"m.dat\", SYMMETRY = 8, CYHARMON = 6, RFFREQ = 50, RINIT = 2000, PHIINIT = 0;\n"
      "C1: RFCAVITY, TYPE = \"SINGLEGAP\", VOLT = 1, FREQ = 50, RMAX = 5000;\n"
      "B: BEAM, PARTICLE = PROTON, PC = 0.4;\n";
  auto refusal = [&](const std::string& tail) {
    std::string msg;
    CHECK(test::error_code([&] { import_opal(head + tail, "t.in", "", "", kDefaultOpalVersion, false); }, &msg) == 65);
    return msg;
  };
  std::string m = refusal("L: LINE = (R, C1, c1);\n");
  CHECK(m.find("t.in:4: LINE L: 'c1' appears twice") != std::string::npos);
  m = refusal("L: LINE = (R, C1);\nTRACK, LINE = L, BEAM = B, MAXSTEPS = 1e13, STEPSPERTURN = 1000;\n");
  CHECK(m.find("t.in:5: TRACK MAXSTEPS: 10000000000000 steps are 10000000000 turns of 1000: turnfit tracks at most 1e6 turns") !=
        std::string::npos);
  std::string coil = head;
  coil.replace(coil.find("PHIINIT = 0;"), 12, "PHIINIT = 0, TRIMCOIL = T;");
  std::string msg;
  CHECK(test::error_code([&] {
          import_opal("T: TRIMCOIL, TYPE = \"PSI-BFIELD\", RMIN = 1000, RMAX = 2000, COEFDENOM = {-1.5, 1};\n" + coil +
                          "L: LINE = (R, C1);\n",
                      "t.in", "", "", kDefaultOpalVersion, false);
        }, &msg) == 65);
  CHECK(msg.find("t.in:1: T: TRIMCOIL COEFDENOM: the denominator is 0 within RMIN..RMAX (near r = 1500 mm)") !=
        std::string::npos);
}

TEST_CASE("opal export: names cannot break the input (control characters in notes, labels made OPAL names)",
          "[opal][shared]") {
  TURNFIT_REQUIRE_SHARED(path, "data/psi-ring/bfield.dat");
  Machine m = load_machine(aeo());
  // A coil name that would end a comment line and the input, and one OPAL reads as a keyword.
  m.doc["trimcoils"][0]["name"] = "tc\nSTOP;\n//turnfit| {";
  m.doc["trimcoils"][0]["sectors"] = {1};
  m.doc["cavities"][0]["name"] = "real";
  m.doc["cavities"][1]["name"] = "REAL_";
  revalidate(m);
  Exported e;
  export_into(e, m, false);
  CHECK(e.text.find("\nSTOP;\n//turnfit| {") == std::string::npos);
  const OpalImport back = import_opal(e.text, e.dir.path + "/x.in", e.dir.path, e.dir.path);
  CHECK(back.from_annotation);
  CHECK(back.machine["trimcoils"][0]["name"] == "tc\nSTOP;\n//turnfit| {");
  const OpalImport bare = import_opal(commands_only(e.text), e.dir.path + "/x.in", e.dir.path, e.dir.path);
  CHECK(bare.machine["cavities"][0]["name"] == "real_");
  CHECK(bare.machine["cavities"][1]["name"] == "REAL__2");
}

TEST_CASE("opal input: STOP inside a taken IF, labelled, or before a comment ends the input too", "[opal]") {
  for (const std::string& text : {std::string("REAL r = 1;\nIF (TRUE) { STOP; r = 9; }\nREAL z = 1/0;\n"),
                                  std::string("REAL r = 1;\nS: STOP;\nREAL z = 1/0;\n"),
                                  std::string("REAL r = 1;\nSTOP // the end\n;\n$ \"not OPAL at all\n")}) {
    INFO(text);
    std::string msg;
    CHECK(test::error_code([&] { opal::Input in(text, "t.in", 1); CHECK(in.variable("r", 1) == 1); }, &msg) == 0);
    CHECK(msg.empty());
  }
  // A STOP in a branch not taken is not read.
  opal::Input in("REAL r = 1;\nIF (FALSE) { STOP; } ELSE { r = 2; }\nr = r + 1;\n", "t.in", 1);
  CHECK(in.variable("r", 1) == 3);
}

TEST_CASE("opal import: a denominator's double root is refused, a refusal names the line its value came from",
          "[opal]") {
  // g(r) = (r - 2.0005)^2 touches 0 between samples without changing sign.
  const std::string cyc =
      "R: CYCLOTRON, TYPE = \"RING\", FMAPFN = \"m.dat\", SYMMETRY = 8, CYHARMON = 6, RFFREQ = 50, RINIT = 2000,"
      " PHIINIT = 0, TRIMCOIL = T;\nL: LINE = (R);\n";
  std::string msg;
  CHECK(test::error_code([&] {
          import_opal("T: TRIMCOIL, TYPE = \"PSI-BFIELD\", RMIN = 1000, RMAX = 3000, COEFDENOM = {4.00200025, -4.001, 1};\n" +
                          cyc + "B: BEAM, PARTICLE = PROTON, PC = 0.4;\n",
                      "t.in", "", "", kDefaultOpalVersion, false);
        }, &msg) == 65);
  CHECK(msg.find("t.in:1: T: TRIMCOIL COEFDENOM: the denominator is 0 within RMIN..RMAX (near r = 2000.5") !=
        std::string::npos);
  // An energy that rounds to 0 comes from the BEAM (line 4), not the CYCLOTRON.
  const OpalImport r = import_opal("T: TRIMCOIL, TYPE = \"PSI-BFIELD\", RMAX = 3000;\n" + cyc +
                                       "B: BEAM, PARTICLE = PROTON, PC = 1e-12;\n",
                                   "t.in", "", "", kDefaultOpalVersion, false);
  CHECK(test::error_code([&] { validate_import(r, "t.in", ""); }, &msg) == 65);
  CHECK(msg.find("t.in:4: the machine it describes is not valid: /injection/energy_MeV: must be > 0") !=
        std::string::npos);
}
