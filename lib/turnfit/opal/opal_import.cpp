// turnfit-import-opal's reading of OPAL-cycl commands into a turnfit machine document.
#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <optional>
#include <set>

#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/opal/annotation.hpp"
#include "turnfit/opal/opal_io.hpp"

namespace turnfit {
namespace {

using nlohmann::json;
using opal::Attribute;
using opal::Command;
using opal::Input;
using opal::Note;
using opal::upper;

namespace fs = std::filesystem;

constexpr double kPhiWindowSince = 20220000;  // PHIMIN/PHIMAX: absent in 2.0, read as 0/0 in 2022.1

// A value from a unit conversion, rounded to 12 significant digits when that is within a few
// ulps (72.00000000000001 MeV from a GeV momentum reads 72), otherwise as computed.
double tidy(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.12g", v);
  double w = std::strtod(buf, nullptr);
  return std::fabs(w - v) <= 8 * DBL_EPSILON * std::fabs(v) ? w : v;
}

std::string num(double v) { return format_exact(tidy(v)); }

// Where the polynomial c_0 + c_1 x + ... is 0 (or not finite) on [lo, hi], if anywhere: a sign
// change between 2000 samples, or a double root where |g| only touches 0 (a local minimum of
// the samples refined by golden section, at most 1e-12 of the largest |g|).
std::optional<double> root_within(const std::vector<double>& c, double lo, double hi) {
  auto g_at = [&](double x) {
    double g = 0;
    for (size_t j = c.size(); j-- > 0;) g = g * x + c[j];
    return g;
  };
  constexpr int kSamples = 2000;
  auto x_of = [&](int k) { return lo + (hi - lo) * k / kSamples; };
  std::vector<double> g(kSamples + 1);
  double gmax = 0;
  for (int k = 0; k <= kSamples; ++k) {
    g[k] = g_at(x_of(k));
    gmax = std::max(gmax, std::fabs(g[k]));
  }
  for (int k = 0; k <= kSamples; ++k) {
    if (g[k] == 0 || !std::isfinite(g[k]) || (k > 0 && (g[k] > 0) != (g[k - 1] > 0))) return x_of(k);
    if (k > 0 && k < kSamples && std::fabs(g[k]) <= std::fabs(g[k - 1]) && std::fabs(g[k]) <= std::fabs(g[k + 1])) {
      double a = x_of(k - 1), b = x_of(k + 1);
      const double gr = 0.5 * (std::sqrt(5.0) - 1);
      for (int it = 0; it < 100 && b - a > 1e-15; ++it) {
        const double p = b - gr * (b - a), q = a + gr * (b - a);
        if (std::fabs(g_at(p)) < std::fabs(g_at(q))) b = q;
        else a = p;
      }
      if (std::fabs(g_at(0.5 * (a + b))) <= 1e-12 * gmax) return 0.5 * (a + b);
    }
  }
  return std::nullopt;
}

// Reads one command's attributes: every attribute must be taken, explained, or is reported.
class Attrs {
 public:
  Attrs(const Command& c, const Input& in, std::vector<Note>& notes) : c_(c), in_(in), notes_(notes) {}

  const Attribute* take(const std::string& n) {
    const Attribute* a = c_.find(n);
    if (a) used_.insert(n);
    return a;
  }
  std::optional<double> number(const std::string& n) {
    const Attribute* a = take(n);
    if (!a) return std::nullopt;
    return in_.number(*a);
  }
  double number(const std::string& n, double def) {
    auto v = number(n);
    return v ? *v : def;
  }
  double required(const std::string& n) {
    auto v = number(n);
    if (!v) throw data_error(in_.name(), c_.line, what() + ": missing " + n);
    return *v;
  }
  std::optional<std::string> string(const std::string& n) {
    const Attribute* a = take(n);
    if (!a) return std::nullopt;
    return in_.string(*a);
  }
  /// An attribute read and not used, with the reason.
  void explain(const std::string& n, const std::string& why) {
    const Attribute* a = take(n);
    if (a) notes_.push_back({a->line, what() + " " + a->spelled + ": " + why, true});
  }
  /// Whatever was not taken: not understood.
  void finish() {
    for (const auto& a : c_.attrs)
      if (!used_.count(a.name))
        notes_.push_back({a.line, what() + ": attribute " + quote(a.spelled) + " is not understood", false});
  }
  std::string what() const { return (c_.label.empty() ? std::string() : c_.label + ": ") + c_.keyword; }
  Error error(const Attribute& a, const std::string& msg) const {
    return data_error(in_.name(), a.line, what() + " " + a.spelled + ": " + msg);
  }

 private:
  const Command& c_;
  const Input& in_;
  std::vector<Note>& notes_;
  std::set<std::string> used_;
};

// The value tokens of an attribute as written, for messages.
std::string written(const Attribute& a) {
  std::string s;
  for (const auto& t : a.value) s += (s.empty() ? "" : " ") + (t.kind == opal::Token::Kind::string ? "\"" + t.text + "\"" : t.text);
  return s;
}

struct Importer {
  Input& in;
  std::string in_dir;
  double version;
  bool check_files = true;
  std::vector<Note> notes;
  std::vector<std::string> remarks;  // choices stated in the machine's description
  std::map<std::string, long> lines_of;  // JSON pointer of the machine -> the input line it came from
  std::map<std::string, const Command*> by_label;  // upper-case label -> its (last) definition

  Error error(long line, const std::string& msg) const { return data_error(in.name(), line, msg); }
  void note(long line, const std::string& text, bool explained = true) { notes.push_back({line, text, explained}); }

  // An input file name as OPAL would open it (relative to the folder OPAL runs in: the input's).
  fs::path input_path(const std::string& f) const {
    const fs::path p = fs::path(f).is_absolute() ? fs::path(f) : fs::path(in_dir.empty() ? "." : in_dir) / f;
    return fs::absolute(p).lexically_normal();
  }

  // The same, for a file the machine needs: it must be there (unless check_files is off).
  std::string existing_file(Attrs& r, const Attribute& a, const std::string& what) const {
    const std::string f = in.string(a);
    if (f.empty()) throw r.error(a, "empty file name");
    const fs::path p = input_path(f);
    std::error_code ec;
    if (check_files && !fs::is_regular_file(p, ec))
      throw r.error(a, what + " " + quote(f) + " is not there (looked for " + quote(p.string()) + ")" +
                           (a.value.size() == 1 && a.value[0].kind == opal::Token::Kind::name
                                ? "; OPAL upper-cases an unquoted name: quote it"
                                : ""));
    return p.string();
  }

  // The element an attribute names (of type `keyword`); EX_DATAERR at the attribute otherwise.
  const Command& element(const Attrs& r, const Attribute& a, const std::string& n, const std::string& keyword) const {
    auto it = by_label.find(upper(n));
    if (it == by_label.end() || it->second->keyword != keyword)
      throw r.error(a, quote(n) + " is not a " + keyword + " defined in the input");
    return *it->second;
  }

  json run() {
    const auto& cmds = in.commands();
    std::vector<const Command*> tracks, runs, selects, lines;
    std::string title;
    // The run imported is the last RUN: OPAL evaluates deferred (':=') values when it runs, and
    // what comes after it is not part of that run.
    const Command* last_run = nullptr;
    for (const Command& c : cmds)
      if (c.keyword == "RUN") last_run = &c;
    if (last_run) in.set_evaluation_point(last_run->seq);
    bool after_run = false;
    for (const Command& c : cmds) {
      if (after_run && c.keyword != "ENDTRACK" && c.keyword != "STOP" && c.keyword != "QUIT") {
        note(c.line, c.keyword_spelled + " after the RUN that is imported (line " + std::to_string(last_run->line) +
                         "): not part of that run");
        continue;
      }
      if (&c == last_run) after_run = true;
      if (!c.label.empty()) {
        const std::string key = upper(c.label);
        auto it = by_label.find(key);
        if (it != by_label.end())
          note(c.line, "label " + c.label + " defined again (first on line " + std::to_string(it->second->line) +
                           "): the last definition counts");
        by_label[key] = &c;
      }
      const std::string& k = c.keyword;
      if (k == "OPTION") {
        for (const auto& a : c.attrs) {
          if (a.name == "VERSION")
            note(a.line, "OPTION VERSION = " + written(a) + ": the OPAL version the input was written for; IF blocks "
                         "are read for OPALVERSION " + num(version) + " (--opal-version)");
          else
            note(a.line, "OPTION " + a.spelled + ": an OPAL run option (output, echo, dumps): nothing to import");
        }
      } else if (k == "TITLE") {
        Attrs r(c, in, notes);
        if (auto s = r.string("STRING")) title = *s;
        r.finish();
      } else if (k == "VALUE") {
        for (const auto& a : c.attrs) {
          std::string vals;
          for (double v : in.numbers(a)) vals += (vals.empty() ? "" : ", ") + num(v);
          note(a.line, "VALUE " + written(a) + " = " + vals + " (printed by OPAL; nothing to import)");
        }
      } else if (k == "SELECT") {
        selects.push_back(&c);
      } else if (k == "TRACK") {
        tracks.push_back(&c);
      } else if (k == "RUN") {
        runs.push_back(&c);
      } else if (k == "LINE") {
        lines.push_back(&c);
      } else if (k == "ENDTRACK") {
        note(c.line, "ENDTRACK: closes the TRACK block");
      } else if (k == "STOP" || k == "QUIT") {
        note(c.line, c.keyword_spelled + ": the end of OPAL's input");
      } else if (k == "ECHO") {
        note(c.line, "ECHO: OPAL prints its text; nothing to import");
      } else if (k == "CYCLOTRON" || k == "RFCAVITY" || k == "TRIMCOIL" || k == "PROBE" || k == "BEAM" ||
                 k == "DISTRIBUTION" || k == "FIELDSOLVER") {
        if (c.label.empty()) note(c.line, c.keyword_spelled + " without a label is not understood", false);
      } else if (by_label.count(k)) {
        note(c.line, "'" + c.keyword_spelled + "' is a copy of element " + c.keyword_spelled + ": copies are not understood",
             false);
      } else {
        note(c.line, "unknown command or element type '" + c.keyword_spelled + "'", false);
      }
    }

    // The line that is tracked: TRACK's, else SELECT's, else the only one.
    const Command* track = tracks.empty() ? nullptr : tracks.back();
    if (tracks.size() > 1) note(tracks.front()->line, "more than one TRACK: the last one is imported", false);
    if (runs.size() > 1) note(runs.front()->line, "more than one RUN: the last one is imported", false);
    std::string line_name;
    long line_at = 0;
    if (track && track->find("LINE")) {
      line_name = in.string(*track->find("LINE"));
      line_at = track->find("LINE")->line;
    } else if (!selects.empty() && selects.back()->find("LINE")) {
      line_name = in.string(*selects.back()->find("LINE"));
      line_at = selects.back()->line;
    } else if (lines.size() == 1) {
      line_name = lines.front()->label;
      line_at = lines.front()->line;
    } else {
      throw error(lines.empty() ? 0 : lines.back()->line,
                  lines.empty() ? "no LINE: nothing says which elements form the machine"
                                : "several LINEs and no TRACK or SELECT names one");
    }
    for (const Command* s : selects) {
      Attrs r(*s, in, notes);
      r.explain("LINE", "the line OPAL's commands act on");
      r.finish();
    }
    auto lit = by_label.find(upper(line_name));
    if (lit == by_label.end() || lit->second->keyword != "LINE")
      throw error(line_at, "LINE " + quote(line_name) + " is not defined");
    const Command& line = *lit->second;
    std::vector<const Command*> members;
    std::set<const Command*> in_line;
    for (const auto& t : line.line_members) {
      auto m = by_label.find(upper(t.text));
      if (m == by_label.end()) throw error(t.line, "LINE member " + quote(t.text) + " is not defined");
      if (m->second->keyword == "LINE") throw error(t.line, "LINE member " + quote(t.text) + " is a LINE: nested lines are not read");
      if (!in_line.insert(m->second).second)
        throw error(t.line, "LINE " + line.label + ": " + quote(t.text) + " appears twice (turnfit's elements are unique)");
      members.push_back(m->second);
    }
    for (const auto* l : lines)
      if (l != &line) note(l->line, "LINE " + l->label + " is not the tracked line (" + line.label + "): not imported");

    json m = json::object();
    m["format"] = "turnfit-machine/1";
    std::string stem = in.name() == "<stdin>" ? std::string("opal") : fs::path(in.name()).stem().string();
    m["name"] = stem.empty() ? std::string("opal") : stem;
    m["description"] = "";

    // The cyclotron: main field, RF, injection point, trim coil list.
    const Command* cyc = nullptr;
    for (const Command* c : members)
      if (c->keyword == "CYCLOTRON") {
        if (cyc) throw error(c->line, "a second CYCLOTRON in LINE " + line.label + " (the first is " + cyc->label + ")");
        cyc = c;
      }
    if (!cyc) throw error(line.line, "LINE " + line.label + " has no CYCLOTRON");
    json trims = json::array();
    json injection = json::object();
    double rf_MHz = 0;
    {
      Attrs r(*cyc, in, notes);
      const Attribute* type = r.take("TYPE");
      if (!type) throw error(cyc->line, r.what() + ": missing TYPE (turnfit reads TYPE=\"RING\" maps)");
      const std::string t = upper(in.string(*type));
      if (t != "RING")
        throw r.error(*type, "field map type " + quote(in.string(*type)) +
                                 " is not read by turnfit (it reads TYPE=\"RING\", the PSI format)");
      const Attribute* fm = r.take("FMAPFN");
      if (!fm) throw error(cyc->line, r.what() + ": missing FMAPFN");
      json field = json::object();
      field["map"] = existing_file(r, *fm, "field map");
      field["format"] = "psi-ring";
      if (check_files) {
        // OPAL 2022.1 takes a RING map as starting at azimuth 0 whatever its header says
        // (physics.md: theta_map = fmod(theta, 45)); turnfit places it where the header says.
        const double th0 = read_field_map(field["map"].get<std::string>(), MapFormat::psi_ring).grid().theta_min_deg;
        if (th0 != 0)
          note(fm->line, r.what() + " FMAPFN: the map starts at azimuth " + num(th0) + " deg, which OPAL 2022.1 "
                         "ignores (it starts every RING map at 0) and turnfit does not: the two track differently", false);
      }
      if (auto s = r.number("SYMMETRY")) {
        if (!(*s == std::floor(*s) && *s >= 1 && *s <= 360))
          throw r.error(*r.take("SYMMETRY"), "must be a whole number in 1..360, got " + num(*s));
        field["symmetry"] = static_cast<int>(*s);
      } else {
        note(cyc->line, r.what() + ": no SYMMETRY, which OPAL needs (it has no default); turnfit takes the map's "
                                   "sector count", false);
      }
      if (auto s = r.number("BSCALE")) field["scale"] = *s;
      if (auto s = r.number("TRIMCOILTHRESHOLD")) field["trimcoil_threshold_T"] = *s;
      m["field"] = field;
      lines_of["/field"] = lines_of["/rf"] = lines_of["/injection"] = cyc->line;
      json rf = json::object();
      if (auto h = r.number("CYHARMON")) {
        if (!(*h == std::floor(*h) && *h >= 1 && *h <= 1e6))
          throw r.error(*r.take("CYHARMON"), "must be a whole number in 1..1e6, got " + num(*h));
        rf["harmonic"] = static_cast<int>(*h);
      }
      if (const Attribute* a = r.take("RFFREQ")) {
        auto f = in.numbers(*a);
        if (f.empty()) throw r.error(*a, "needs a frequency");
        if (f.size() > 1) note(a->line, r.what() + " RFFREQ: only the first frequency is the machine's RF (" + num(f[0]) + " MHz)", false);
        if (!(f[0] >= 0)) throw r.error(*a, "must be >= 0, got " + num(f[0]));
        rf_MHz = f[0];
        rf["frequency_MHz"] = f[0];
      }
      m["rf"] = rf;
      injection["r_mm"] = r.required("RINIT");
      injection["pr_betagamma"] = r.number("PRINIT", 0.0);
      injection["phi_deg"] = r.required("PHIINIT");
      if (auto z = r.number("ZINIT")) injection["z_mm"] = *z;
      if (auto z = r.number("PZINIT")) injection["pz_betagamma"] = *z;
      if (const Attribute* a = r.take("TRIMCOIL")) {
        std::set<std::string> listed;
        for (const std::string& n : in.names(*a)) {
          if (!listed.insert(upper(n)).second) throw r.error(*a, quote(n) + " is listed twice");
          trimcoil(element(r, *a, n, "TRIMCOIL"), trims);
        }
      }
      r.explain("FMLOWE", "energy range of OPAL's closed-orbit finder (GAUSSMATCHED): turnfit-orbit --energies does this");
      r.explain("FMHIGHE", "energy range of OPAL's closed-orbit finder (GAUSSMATCHED): turnfit-orbit --energies does this");
      for (const char* k : {"MINZ", "MAXZ", "MINR", "MAXR"})
        r.explain(k, "OPAL's loss limits: turnfit loses a particle at the map's edge");
      if (const Attribute* a = r.take("SPIRAL")) {
        if (in.boolean(*a)) note(a->line, r.what() + " SPIRAL = TRUE (a spiral inflector) is not understood", false);
        else note(a->line, r.what() + " SPIRAL = FALSE: no spiral inflector");
      }
      r.finish();
    }
    // Trim coils named nowhere are defined but unused.
    std::set<std::string> coil_names;
    for (const auto& t : trims) coil_names.insert(upper(t["name"].get<std::string>()));
    for (const Command& c : cmds)
      if (c.keyword == "TRIMCOIL" && !c.label.empty() && (!last_run || c.seq < last_run->seq)) {
        const bool used = coil_names.count(upper(c.label)) > 0;
        if (!used && by_label[upper(c.label)] == &c)
          note(c.line, "TRIMCOIL " + c.label + " is in no CYCLOTRON's TRIMCOIL list: not imported");
      }

    // Beam: particle and energy.
    const Command* beam = named_beam(track);
    if (!beam && !runs.empty()) beam = named_beam(runs.back());
    if (!beam) beam = only(cmds, "BEAM");
    if (!beam) throw error(track ? track->line : line.line, "no BEAM: the particle and its energy are unknown");
    double mass_MeV = 0;
    {
      Attrs r(*beam, in, notes);
      json particle = json::object();
      if (auto p = r.string("PARTICLE")) {
        const std::string up = upper(*p);
        static const std::map<std::string, std::string> species = {
            {"PROTON", "proton"}, {"DEUTERON", "deuteron"}, {"ALPHA", "alpha"}, {"H2P", "h2+"}};
        auto s = species.find(up);
        if (s == species.end())
          throw r.error(*beam->find("PARTICLE"), "particle " + quote(*p) + " is not one turnfit tracks (PROTON, DEUTERON, ALPHA, H2P; "
                                                 "or MASS and CHARGE without PARTICLE)");
        particle["species"] = s->second;
        mass_MeV = named_particle(s->second)->mass_MeV;
        if (const Attribute* a = r.take("CHARGE")) {
          const double q = in.number(*a);
          if (q != named_particle(s->second)->charge_e)
            note(a->line, "BEAM CHARGE = " + num(q) + ": PARTICLE sets the charge in OPAL; " + *p + "'s is used", false);
          else
            note(a->line, "BEAM CHARGE = " + num(q) + ": the particle's charge, as PARTICLE gives it");
        }
        r.explain("MASS", "PARTICLE sets the mass in OPAL");
      } else {
        const double mass = r.required("MASS"), q = r.required("CHARGE");
        if (!(mass > 0)) throw error(beam->line, "BEAM MASS must be > 0, got " + num(mass));
        particle["species"] = "custom";
        particle["mass_MeV"] = tidy(mass * 1000);
        particle["charge_e"] = q;
        mass_MeV = mass * 1000;
      }
      m["particle"] = particle;
      lines_of["/particle"] = lines_of["/injection/energy_MeV"] = beam->line;
      double E = 0;
      if (auto g = r.number("GAMMA")) {
        if (!(*g > 1)) throw r.error(*beam->find("GAMMA"), "must be > 1, got " + num(*g));
        E = (*g - 1) * mass_MeV;
        r.explain("ENERGY", "GAMMA takes precedence in OPAL");
        r.explain("PC", "GAMMA takes precedence in OPAL");
      } else if (auto e = r.number("ENERGY")) {
        E = *e * 1000 - mass_MeV;
        if (!(E > 0)) throw r.error(*beam->find("ENERGY"), "the total energy " + num(*e) + " GeV is not above the rest energy");
        r.explain("PC", "ENERGY takes precedence in OPAL");
      } else if (auto pc = r.number("PC")) {
        if (!(*pc > 0)) throw r.error(*beam->find("PC"), "must be > 0, got " + num(*pc));
        const double p = *pc * 1000;
        E = std::sqrt(p * p + mass_MeV * mass_MeV) - mass_MeV;
      } else {
        throw error(beam->line, "BEAM gives no energy (GAMMA, ENERGY or PC)");
      }
      injection["energy_MeV"] = tidy(E);
      if (auto f = r.number("BFREQ")) {
        if (rf_MHz > 0 && *f != rf_MHz)
          note(beam->find("BFREQ")->line, "BEAM BFREQ = " + num(*f) + " MHz differs from the RF (" + num(rf_MHz) +
                                              " MHz): OPAL's time step uses BFREQ, turnfit's rk4 the RF frequency", false);
        else
          note(beam->find("BFREQ")->line, "BEAM BFREQ: sets OPAL's time step with STEPSPERTURN (the RF frequency here)");
      }
      r.explain("NPART", "OPAL's particle count: turnfit-track --particles");
      r.explain("BCURRENT", "beam current: space charge is not imported (turnfit-track --space-charge --current-uA, "
                            "or a space_charge block)");
      r.finish();
    }

    // Elements of the line in order.
    json cavities = json::array(), probes = json::array();
    for (const Command* c : members) {
      if (c->keyword == "RFCAVITY") cavity(*c, rf_MHz, cavities);
      else if (c->keyword == "PROBE") probe(*c, probes);
      else if (c->keyword != "CYCLOTRON")
        note(c->line, c->keyword_spelled + " " + c->label + " in LINE " + line.label + " is not understood", false);
    }
    for (const Command& c : cmds)
      if ((c.keyword == "RFCAVITY" || c.keyword == "PROBE" || c.keyword == "CYCLOTRON") && !c.label.empty() &&
          !in_line.count(&c) && (!last_run || c.seq < last_run->seq))
        note(c.line, c.keyword_spelled + " " + c.label + " is not in the tracked LINE " + line.label + ": not imported");
    if (!cavities.empty()) m["cavities"] = cavities;
    if (!trims.empty()) m["trimcoils"] = trims;
    if (!probes.empty()) m["probes"] = probes;
    m["injection"] = injection;

    // Tracking, run, distribution, field solver.
    json tracking = json::object();
    if (track) {
      Attrs r(*track, in, notes);
      r.take("LINE");
      r.take("BEAM");
      const double spt = r.number("STEPSPERTURN", 720);
      if (!(spt == std::floor(spt) && spt >= 1 && spt <= 1e7))
        throw r.error(*track->find("STEPSPERTURN"), "must be a whole number in 1..1e7, got " + num(spt));
      tracking["steps_per_turn"] = static_cast<int>(spt);
      double maxsteps = 10;
      if (const Attribute* a = r.take("MAXSTEPS")) {
        auto v = in.numbers(*a);
        if (v.empty()) throw r.error(*a, "needs a number");
        if (v.size() > 1) note(a->line, "TRACK MAXSTEPS: only the first value is read", false);
        maxsteps = v[0];
      }
      if (!(maxsteps >= 0)) throw error(track->line, "TRACK MAXSTEPS must be >= 0, got " + num(maxsteps));
      const double turns = std::floor(maxsteps / spt);
      if (turns > 1e6)
        throw r.error(*track->find("MAXSTEPS"), num(maxsteps) + " steps are " + num(turns) +
                                                    " turns of " + num(spt) + ": turnfit tracks at most 1e6 turns");
      if (turns >= 1) tracking["turns"] = static_cast<int>(turns);
      if (turns * spt != maxsteps)
        note(track->line, "TRACK MAXSTEPS = " + num(maxsteps) + " is not a whole number of turns of " + num(spt) +
                              " steps: " + num(turns) + " whole turns are imported");
      if (const Attribute* a = r.take("TIMEINTEGRATOR")) {
        const std::string ti = upper(in.string(*a));
        if (ti == "RK4" || ti == "RK-4")
          note(a->line, "TRACK TIMEINTEGRATOR = RK4: turnfit's rk4 integrator (--integrator rk4; --opal-compat for OPAL's numerics)");
        else
          note(a->line, "TRACK TIMEINTEGRATOR = " + in.string(*a) + " is not one turnfit has (it has RK4)", false);
      }
      r.explain("DT", "OPAL-cycl sets its time step from STEPSPERTURN");
      r.explain("ZSTOP", "not used by OPAL-cycl");
      r.finish();
    }
    if (!tracking.empty()) m["tracking"] = tracking;
    if (track) lines_of["/tracking"] = track->line;
    if (!runs.empty()) {
      const Command& run = *runs.back();
      Attrs r(run, in, notes);
      if (auto meth = r.string("METHOD")) {
        if (upper(*meth) != "CYCLOTRON-T")
          note(run.find("METHOD")->line, "RUN METHOD = " + *meth + " is not OPAL's cyclotron tracker (CYCLOTRON-T)", false);
      }
      r.take("BEAM");
      if (const Attribute* a = r.take("FIELDSOLVER"))
        for (const auto& n : in.names(*a)) fieldsolver(element(r, *a, n, "FIELDSOLVER"));
      if (const Attribute* a = r.take("DISTRIBUTION"))
        for (const auto& n : in.names(*a)) distribution(element(r, *a, n, "DISTRIBUTION"));
      if (const Attribute* a = r.take("TURNS")) {
        const double t = in.number(*a);
        if (t == 1) note(a->line, "RUN TURNS = 1: one bunch (OPAL's multi-bunch count)");
        else note(a->line, "RUN TURNS = " + num(t) + ": OPAL's neighbouring bunches are not modelled", false);
      }
      r.finish();
    }

    // The description: where the machine came from and every choice made for it.
    std::string d = "Imported by turnfit-import-opal from " + fs::path(in.name()).filename().string();
    if (!title.empty()) d += " (TITLE \"" + title + "\")";
    d += ", read as OPAL " + version_text() + " (OPALVERSION " + num(version) + "). Physics: turnfit's defaults "
         "(turnfit-track --opal-compat gives OPAL-cycl 2022.1's numerics); tracking.steps_per_turn is OPAL's "
         "STEPSPERTURN, used by the rk4 integrator.";
    for (const auto& s : remarks) d += " " + s;
    m["description"] = d;
    return m;
  }

  std::string version_text() const {
    const long v = static_cast<long>(version);
    return std::to_string(v / 10000) + "." + std::to_string(v / 100 % 100) + "." + std::to_string(v % 100);
  }

  // The BEAM a TRACK or RUN names, or nullptr when it names none.
  const Command* named_beam(const Command* c) {
    if (!c || !c->find("BEAM")) return nullptr;
    const Attrs r(*c, in, notes);
    return &element(r, *c->find("BEAM"), in.string(*c->find("BEAM")), "BEAM");
  }

  static const Command* only(const std::vector<Command>& cmds, const std::string& keyword) {
    const Command* found = nullptr;
    for (const auto& c : cmds)
      if (c.keyword == keyword) {
        if (found) return nullptr;
        found = &c;
      }
    return found;
  }

  void trimcoil(const Command& c, json& out) {
    Attrs r(c, in, notes);
    json t = json::object();
    t["name"] = c.label;
    const Attribute* type = r.take("TYPE");
    if (!type) throw error(c.line, r.what() + ": missing TYPE");
    const std::string ty = upper(in.string(*type));
    std::string tt;
    if (ty == "PSI-BFIELD") tt = "psi-bfield";
    else if (ty == "PSI-PHASE") tt = "psi-phase";
    else if (ty == "PSI-BFIELD-MIRRORED") tt = "psi-bfield-mirrored";
    else {
      note(type->line, r.what() + " TYPE = " + in.string(*type) + " is not a trim coil type OPAL " + version_text() +
                           " or turnfit has (PSI-BFIELD, PSI-PHASE, PSI-BFIELD-MIRRORED): coil left out", false);
      return;
    }
    t["type"] = tt;
    t["rmin_mm"] = r.number("RMIN", 0.0);
    t["rmax_mm"] = r.required("RMAX");
    lines_of["/trimcoils/" + std::to_string(out.size())] = c.line;
    const double bmax = r.number("BMAX", 0.0);
    // OPAL adds PSI-BFIELD and PSI-PHASE fields to its sign-flipped Bz and subtracts the
    // mirrored shape (physics.md): BMAX is -bmax_T for the first two, +bmax_T for the third.
    t["bmax_T"] = tt == "psi-bfield-mirrored" ? bmax : -bmax;
    if (tt == "psi-bfield-mirrored") {
      t["slope_per_mm"] = r.required("SLPTC");
      for (const char* k : {"COEFNUM", "COEFDENOM", "COEFNUMPHI", "COEFDENOMPHI"})
        r.explain(k, "not used by PSI-BFIELD-MIRRORED");
    } else {
      std::vector<double> num_c{1.0}, den_c;
      if (const Attribute* a = r.take("COEFNUM")) num_c = in.numbers(*a);
      if (const Attribute* a = r.take("COEFDENOM")) den_c = in.numbers(*a);
      if (num_c.empty()) num_c = {1.0};
      t["coefnum"] = num_c;
      if (!den_c.empty()) {
        // f/g must be finite on the coil: a denominator with a root there gives an infinite field.
        const double lo = t["rmin_mm"].get<double>() * 1e-3, hi = t["rmax_mm"].get<double>() * 1e-3;
        if (const auto root = root_within(den_c, lo, hi))
          throw r.error(*c.find("COEFDENOM"), "the denominator is 0 within RMIN..RMAX (near r = " + num(*root * 1e3) +
                                                  " mm): the coil's field would be infinite there");
        t["coefdenom"] = den_c;
      }
      r.explain("SLPTC", "used only by PSI-BFIELD-MIRRORED");
      // An azimuthal factor turnfit can hold only when it is a constant.
      double phi_factor = 1;
      for (const char* k : {"COEFNUMPHI", "COEFDENOMPHI"}) {
        const Attribute* a = r.take(k);
        if (!a) continue;
        auto v = in.numbers(*a);
        if (v.size() > 1)
          for (size_t i = 1; i < v.size(); ++i)
            if (v[i] != 0)
              throw r.error(*a, "an azimuthal profile (" + written(*a) +
                                    ") is not modelled by turnfit: only a constant factor can be imported");
        const double f = v.empty() ? 1.0 : v[0];
        if (std::string(k) == "COEFDENOMPHI" && f == 0) throw r.error(*a, "division by zero: the constant denominator is 0");
        phi_factor = std::string(k) == "COEFNUMPHI" ? phi_factor * f : phi_factor / f;
      }
      if (phi_factor != 1) {
        t["bmax_T"] = t["bmax_T"].get<double>() * phi_factor;
        remarks.push_back("Trim coil " + c.label + ": its constant azimuthal factor " + num(phi_factor) +
                          " (COEFNUMPHI/COEFDENOMPHI) is folded into bmax_T.");
      }
    }
    const Attribute* pmin = c.find("PHIMIN");
    const Attribute* pmax = c.find("PHIMAX");
    if (version < kPhiWindowSince) {
      if (pmin || pmax)
        note((pmin ? pmin : pmax)->line, r.what() + ": PHIMIN/PHIMAX do not exist before OPAL 2022 (--opal-version " +
                                             version_text() + ")", false);
      r.take("PHIMIN");
      r.take("PHIMAX");
    } else {
      // 2022.1 reads an unset PHIMIN/PHIMAX as 0 and applies a coil only where
      // PHIMIN <= phi <= PHIMAX, phi in [0, 360) deg: unset, it acts at azimuth 0 alone.
      const double a = r.number("PHIMIN", 0.0), b = r.number("PHIMAX", 0.0);
      if (a == b) {
        const double given = t["bmax_T"].get<double>();
        t["bmax_T"] = 0.0;
        remarks.push_back("Trim coil " + c.label + ": OPAL " + version_text() + " applies it only where the azimuth is " +
                          (a == 0 && !pmin && !pmax ? std::string("0 exactly (PHIMIN and PHIMAX unset read as 0)")
                                                    : "exactly PHIMIN = PHIMAX = " + num(a) + " deg") +
                          ", so it acts nowhere: imported with bmax_T 0 (the input's field is " + num(given) +
                          " T in turnfit's sign; give PHIMIN = 0, PHIMAX = 360 for the full circle).");
        note(c.line, r.what() + ": acts nowhere in OPAL " + version_text() + " (PHIMIN = PHIMAX = " + num(a) +
                         "): imported with bmax_T 0, as the description says");
      } else {
        double lo = a, hi = b;
        if (lo < 0 || hi > 360 || lo > 360 || hi < 0)
          throw r.error(*(pmin ? pmin : pmax), "PHIMIN/PHIMAX must be in [0, 360] deg (OPAL 2022.1 does not wrap "
                                               "azimuths), got " + num(a) + ", " + num(b));
        if (lo > hi) hi += 360;  // OPAL's window through azimuth 0
        t["phimin_deg"] = lo;
        t["phimax_deg"] = std::min(hi, lo + 360);
      }
    }
    r.finish();
    out.push_back(t);
  }

  void cavity(const Command& c, double rf_MHz, json& out) {
    Attrs r(c, in, notes);
    const Attribute* type = r.take("TYPE");
    const std::string ty = type ? upper(in.string(*type)) : std::string();
    if (ty != "SINGLEGAP") {
      note(type ? type->line : c.line, r.what() + ": TYPE " + (type ? quote(in.string(*type)) : std::string("(none)")) +
                                           " is not understood (turnfit has SINGLEGAP cavities): cavity left out", false);
      return;
    }
    json k = json::object();
    k["name"] = c.label;
    k["voltage_MV"] = r.required("VOLT");
    if (const Attribute* a = r.take("FMAPFN")) k["profile"] = existing_file(r, *a, "voltage profile");
    else note(c.line, r.what() + ": no FMAPFN: a flat voltage profile");
    const double f = r.required("FREQ");
    if (!(rf_MHz > 0)) throw error(c.line, r.what() + ": a cavity needs the CYCLOTRON's RFFREQ");
    double h = f / rf_MHz;
    if (std::fabs(h - std::round(h)) <= 1e-12 * h) h = std::round(h);
    if (!(h > 0)) throw r.error(*c.find("FREQ"), "must be > 0, got " + num(f));
    if (h != 1) k["harmonic_factor"] = tidy(h);
    k["phase_deg"] = r.number("PHI0", 0.0);
    k["angle_deg"] = r.number("ANGLE", 0.0);
    k["pdis_mm"] = r.number("PDIS", 0.0);
    k["rmin_mm"] = r.number("RMIN", 0.0);
    k["rmax_mm"] = r.required("RMAX");
    lines_of["/cavities/" + std::to_string(out.size())] = c.line;
    k["gap_width_mm"] = r.number("GAPWIDTH", 0.0);
    r.explain("FAST", "OPAL's interpolation shortcut for field maps: no effect on a single gap");
    r.finish();
    out.push_back(k);
  }

  void probe(const Command& c, json& out) {
    Attrs r(c, in, notes);
    const double x0 = r.required("XSTART"), x1 = r.required("XEND");
    const double y0 = r.required("YSTART"), y1 = r.required("YEND");
    const double dx = x1 - x0, dy = y1 - y0, len = std::hypot(dx, dy);
    if (!(len > 0)) throw error(c.line, r.what() + ": XSTART, YSTART and XEND, YEND are the same point");
    // turnfit's probe: s (cos phi, sin phi) + a (sin phi, -cos phi), s from s_min to s_max.
    const double phi = std::atan2(dy, dx), cs = dx / len, sn = dy / len;
    json p = json::object();
    p["name"] = c.label;
    double phi_deg = phi * 180 / M_PI;
    if (phi_deg < 0) phi_deg += 360;
    p["phi_deg"] = tidy(phi_deg);
    p["a_mm"] = tidy(x0 * sn - y0 * cs);
    p["s_min_mm"] = tidy(x0 * cs + y0 * sn);
    p["s_max_mm"] = tidy(x1 * cs + y1 * sn);
    p["step_mm"] = r.number("STEP", 1.0);
    lines_of["/probes/" + std::to_string(out.size())] = c.line;
    if (!(p["step_mm"].get<double>() > 0)) throw r.error(*c.find("STEP"), "must be > 0");
    r.explain("WIDTH", "not used by OPAL");
    r.explain("OUTFN", "OPAL's output file name");
    r.finish();
    out.push_back(p);
  }

  void fieldsolver(const Command& c) {
    Attrs r(c, in, notes);
    const std::string t = upper(r.string("FSTYPE").value_or("NONE"));
    if (t == "NONE") note(c.line, "FIELDSOLVER " + c.label + ": FSTYPE = NONE, no space charge");
    else
      note(c.line,
           "FIELDSOLVER " + c.label + ": space charge (FSTYPE = " + t +
               ") is not imported: turnfit's own particle-in-cell solver is turnfit-track --space-charge --current-uA "
               "--sc-grid (or a space_charge block in the machine)",
           false);
  }

  void distribution(const Command& c) {
    Attrs r(c, in, notes);
    const Attribute* type = r.take("TYPE");
    const std::string t = type ? upper(in.string(*type)) : std::string();
    if (t == "FROMFILE") {
      const Attribute* f = r.take("FNAME");
      if (!f) throw error(c.line, r.what() + ": FROMFILE without FNAME");
      if (!check_files) return;
      const fs::path p = input_path(in.string(*f));
      std::error_code ec;
      if (!fs::is_regular_file(p, ec)) {
        note(f->line, "DISTRIBUTION " + c.label + ": file " + quote(in.string(*f)) + " is not there: not read", false);
        return;
      }
      const InputText txt = read_input(p.string());
      const auto rows = split_lines(txt.text, in.name() + ": " + in.string(*f));
      std::vector<std::vector<double>> parts;
      long count = -1;
      for (size_t i = 0; i < rows.size(); ++i) {
        std::string_view l = trim(rows[i]);
        if (count < 0) {
          if (auto h = l.find('#'); h != std::string_view::npos) l = trim(l.substr(0, h));
          if (l.empty()) continue;
          count = parse_long(l, txt.name, static_cast<long>(i + 1), "particle count");
          if (count < 1) throw data_error(txt.name, static_cast<long>(i + 1), "particle count must be >= 1");
          continue;
        }
        if (l.empty()) continue;
        auto fields = split_blanks(l);
        if (fields.size() != 6) throw data_error(txt.name, static_cast<long>(i + 1), "expected 6 numbers (x px y py z pz)");
        std::vector<double> v;
        for (auto x : fields) v.push_back(parse_double(x, txt.name, static_cast<long>(i + 1), "coordinate"));
        parts.push_back(v);
        if (parts.size() > 2) break;
      }
      bool at_reference = count == 1 && parts.size() == 1 &&
                          std::all_of(parts[0].begin(), parts[0].end(), [](double x) { return x == 0; });
      if (at_reference)
        note(c.line, "DISTRIBUTION " + c.label + ": one particle at the reference, the machine's injection point");
      else
        note(c.line, "DISTRIBUTION " + c.label + ": FROMFILE with offsets is not converted (turnfit-track --bunch "
                                                 "takes a CSV of offsets: turnfit-machine(5) BUNCH)", false);
    } else if (t == "GAUSSMATCHED") {
      note(c.line, "DISTRIBUTION " + c.label + ": GAUSSMATCHED, a bunch matched by OPAL's closed-orbit finder "
                                               "(its tunes): turnfit-orbit computes closed orbits and tunes itself");
    } else {
      note(type ? type->line : c.line, "DISTRIBUTION " + c.label + ": TYPE " + (t.empty() ? std::string("(none)") : t) +
                                            " is not understood", false);
    }
  }
};

}  // namespace

OpalImport import_opal(const std::string& text, const std::string& name, const std::string& in_dir,
                       const std::string& out_dir, double opal_version, bool check_files) {
  Input in(text, name, opal_version);
  Importer imp{in, in_dir, opal_version, check_files, {}, {}, {}, {}};
  imp.notes = in.notes();
  json m = imp.run();
  OpalImport out;
  // The commands as this import reads them, with paths relative to the input's folder: what an
  // export's annotation recorded, if nothing was edited since.
  json opal_part = m;
  rebase_paths(opal_part, "", in_dir);
  if (auto ann = read_annotation(text, name)) {
    const long line = ann->line;
    const std::vector<std::string> changed = changed_sections(ann->opal, opal_part);
    std::string list;
    for (const auto& s : changed) list += (list.empty() ? "" : ", ") + s;
    json restored = ann->machine;
    for (const auto& s : changed) {
      if (opal_part.contains(s)) restored[s] = opal_part[s];
      else restored.erase(s);
    }
    if (!changed.empty() && restored.contains("description") && restored["description"].is_string())
      restored["description"] = restored["description"].get<std::string>() + " Edited in OPAL after turnfit-export-opal: " +
                                list + " read from the commands.";
    try {
      // The edited sections must still fit what the annotation keeps (effects name cavities,
      // design variables point into the document).
      if (!changed.empty()) machine_from_json(restored, name + " (turnfit annotation)", in_dir);
      rebase_paths(restored, in_dir, out_dir);
      out.machine = restored;
      out.from_annotation = changed.empty();
      out.annotation_line = line;
      for (const auto& sec : opal_sections())
        if (std::find(changed.begin(), changed.end(), sec) == changed.end()) out.restored.push_back(sec);
      imp.notes.push_back({line, changed.empty()
                                     ? "turnfit annotation: the commands are those turnfit-export-opal wrote, so the "
                                       "machine it records is restored (names, descriptions, effects, exact values)"
                                     : "turnfit annotation: " + list + " changed since turnfit-export-opal wrote the "
                                       "input and " + std::string(changed.size() == 1 ? "is" : "are") +
                                       " read from the commands; the rest of the machine it records is restored",
                           true});
    } catch (const Error& e) {
      imp.notes.push_back({line, "turnfit annotation: the edited commands (" + list + ") no longer fit the machine it "
                                 "records (" + clip_message(e.what()) + "), so it is not used: the machine is read "
                                 "from the commands alone", false});
    }
  }
  if (out.machine.is_null()) {
    rebase_paths(m, "", out_dir);
    out.machine = m;
  }
  out.notes = imp.notes;
  out.lines = imp.lines_of;
  std::stable_sort(out.notes.begin(), out.notes.end(), [](const Note& a, const Note& b) { return a.line < b.line; });
  return out;
}

Machine validate_import(const OpalImport& r, const std::string& name, const std::string& out_dir) {
  try {
    return machine_from_json(r.machine, name + " (imported machine)", out_dir);
  } catch (const Error& e) {
    // Named by the line the value came from: its command, or the annotation for what the
    // annotation restored (and for what only the annotation carries: bunch, effects, ...).
    std::string msg = e.what();
    const std::string head = name + " (imported machine): ";
    if (msg.rfind(head, 0) == 0) msg = msg.substr(head.size());
    const std::string ptr = msg.substr(0, msg.find(':'));
    const std::string section = ptr.size() > 1 ? ptr.substr(1, ptr.find('/', 1) - 1) : std::string();
    long line = 0;
    std::string best;
    for (const auto& [p, l] : r.lines)
      if (ptr.rfind(p, 0) == 0 && (ptr.size() == p.size() || ptr[p.size()] == '/') && p.size() > best.size())
        best = p, line = l;
    const bool restored = std::find(r.restored.begin(), r.restored.end(), section) != r.restored.end();
    if (r.annotation_line && (restored || best.empty()))
      throw data_error(name, r.annotation_line, "turnfit annotation: the machine it records is not valid: " + msg);
    throw data_error(name, line, "the machine it describes is not valid: " + msg);
  }
}

}  // namespace turnfit
