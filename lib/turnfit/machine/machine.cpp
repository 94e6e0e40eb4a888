// Loading and validating machine files: every key is checked so a typo or a wrong unit fails
// loudly.
#include "turnfit/machine/machine.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <set>
#include <utility>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/io/json.hpp"

namespace turnfit {
namespace {

using nlohmann::json;

const char* const kFormat = "turnfit-machine/1";

// CODATA 2018 rest energies [MeV].
constexpr double kProtonMass = 938.27208816;
constexpr double kDeuteronMass = 1875.61294257;
constexpr double kAlphaMass = 3727.3794066;
constexpr double kElectronMass = 0.51099895;
// H2+ = two protons + one electron - binding energy (16.25 eV, ionisation of H2+ to 2p + e).
constexpr double kH2PlusMass = 2 * kProtonMass + kElectronMass - 16.25e-6;

std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return buf;
}

// RFC 6901 escaping, so a key containing '/' or '~' still gives a usable path.
std::string escape_key(const std::string& key) {
  std::string out;
  for (char c : key) {
    if (c == '~')
      out += "~0";
    else if (c == '/')
      out += "~1";
    else
      out += c;
  }
  return out;
}

std::string lower_case(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

// A hint for an unknown key. Units live in key suffixes, so the most likely mistake is the
// right quantity in the wrong unit (voltage_kV for voltage_MV): say so explicitly.
std::string unknown_key_hint(const std::string& key, const std::vector<std::string>& known) {
  auto stem_of = [](const std::string& k) -> std::string {
    size_t u = k.rfind('_');
    return (u == std::string::npos || u == 0) ? std::string() : k.substr(0, u);
  };
  std::string stem = stem_of(key);
  for (const auto& k : known) {
    std::string ks = stem_of(k);
    if (ks.empty()) continue;
    if (!stem.empty() && ks == stem) return " (wrong unit: expected '" + k + "')";
    if (ks == key) return " (missing unit: expected '" + k + "')";
  }
  std::string best;
  size_t best_d = 3;
  for (const auto& k : known) {
    size_t d = lower_case(k) == lower_case(key) ? 0 : edit_distance(key, k);
    if (d < best_d) best_d = d, best = k;
  }
  if (!best.empty()) return " (did you mean '" + best + "'?)";
  return {};
}

// Reads one JSON object, checking its keys against a fixed list and writing defaults of
// numeric keys back, so the normalized document has every number a design variable may
// point at.
class Reader {
 public:
  Reader(json& obj, const std::string& file, std::string path, std::vector<std::string> known)
      : obj_(obj), file_(file), path_(std::move(path)), known_(std::move(known)) {
    if (!obj_.is_object()) throw error_here("expected a JSON object, got " + type_name(obj_));
    for (const auto& item : obj_.items()) {
      if (std::find(known_.begin(), known_.end(), item.key()) == known_.end())
        throw error(item.key(), "unknown key" + unknown_key_hint(item.key(), known_));
    }
  }

  bool has(const std::string& key) const { return obj_.contains(key); }
  json& raw(const std::string& key) { return obj_[key]; }
  std::string at(const std::string& key) const { return path_ + "/" + escape_key(key); }

  Error error(const std::string& key, const std::string& msg) const {
    return data_error(file_, 0, at(key) + ": " + msg);
  }
  Error error_here(const std::string& msg) const {
    return data_error(file_, 0, (path_.empty() ? std::string("/") : path_) + ": " + msg);
  }

  static std::string type_name(const json& j) {
    if (j.is_number()) return "a number";
    if (j.is_string()) return "a string";
    if (j.is_boolean()) return "a boolean";
    if (j.is_null()) return "null";
    if (j.is_array()) return "an array";
    return "an object";
  }

  /// A finite number; absent: the default (written back) or, without one, an error.
  double number(const std::string& key, std::optional<double> def = std::nullopt) {
    if (!has(key)) {
      if (!def) throw error(key, "missing required key");
      obj_[key] = *def;
      return *def;
    }
    return as_number(obj_[key], at(key));
  }

  std::optional<double> opt_number(const std::string& key) {
    if (!has(key)) return std::nullopt;
    return as_number(obj_[key], at(key));
  }

  double as_number(const json& j, const std::string& where) const {
    if (!j.is_number())
      throw data_error(file_, 0, where + ": expected a number, got " + type_name(j));
    double v = j.get<double>();
    if (!std::isfinite(v)) throw data_error(file_, 0, where + ": not a finite number");
    return v;
  }

  int as_integer(const json& j, const std::string& where) const {
    double v = as_number(j, where);
    // JSON has one number type: 8.0 is an integer too.
    if (v != std::floor(v) || std::fabs(v) > std::numeric_limits<int>::max())
      throw data_error(file_, 0, where + ": expected an integer, got " + num(v));
    return static_cast<int>(v);
  }

  int integer(const std::string& key, std::optional<int> def = std::nullopt) {
    if (!has(key)) {
      if (!def) throw error(key, "missing required key");
      obj_[key] = *def;
      return *def;
    }
    return as_integer(obj_[key], at(key));
  }

  std::string string(const std::string& key, std::optional<std::string> def = std::nullopt) {
    if (!has(key)) {
      if (!def) throw error(key, "missing required key");
      return *def;
    }
    const json& j = obj_[key];
    if (!j.is_string()) throw error(key, "expected a string, got " + type_name(j));
    return j.get<std::string>();
  }

  bool boolean(const std::string& key, bool def) {
    if (!has(key)) return def;
    const json& j = obj_[key];
    if (!j.is_boolean()) throw error(key, "expected true or false, got " + type_name(j));
    return j.get<bool>();
  }

  std::vector<double> numbers(const std::string& key) {
    std::vector<double> out;
    if (!has(key)) return out;
    const json& j = obj_[key];
    if (!j.is_array()) throw error(key, "expected an array of numbers, got " + type_name(j));
    for (size_t i = 0; i < j.size(); ++i)
      out.push_back(as_number(j[i], at(key) + "/" + std::to_string(i)));
    return out;
  }

  std::string one_of(const std::string& key, const std::vector<std::string>& choices,
                     std::optional<std::string> def) {
    std::string v = string(key, def);
    if (std::find(choices.begin(), choices.end(), v) == choices.end()) {
      std::string list;
      for (size_t i = 0; i < choices.size(); ++i)
        list += (i ? (i + 1 == choices.size() ? " or " : ", ") : "") + choices[i];
      throw error(key, "unknown value '" + v + "' (expected " + list + ")");
    }
    return v;
  }

 private:
  json& obj_;
  const std::string& file_;
  std::string path_;
  std::vector<std::string> known_;
};

std::string resolve_path(const std::string& dir, const std::string& p) {
  if (p.empty() || dir.empty() || std::filesystem::path(p).is_absolute()) return p;
  return (std::filesystem::path(dir) / p).string();
}

// Checks that `name` is a non-empty string not used before in the same list.
std::string element_name(Reader& r, std::map<std::string, std::string>& seen) {
  std::string name = r.string("name");
  if (name.empty()) throw r.error("name", "must not be empty");
  auto [it, fresh] = seen.emplace(name, r.at("name"));
  if (!fresh) throw r.error("name", "duplicate name '" + name + "' (also " + it->second + ")");
  return name;
}

json& array_at(json& doc, const std::string& key, const std::string& file) {
  json& a = doc[key];
  if (!a.is_array())
    throw data_error(file, 0, "/" + key + ": expected a JSON array, got " + Reader::type_name(a));
  return a;
}

Particle read_particle(json& j, const std::string& file) {
  Reader r(j, file, "/particle", {"species", "mass_MeV", "charge_e"});
  Particle p;
  p.species = r.one_of("species", {"proton", "deuteron", "alpha", "h2+", "custom"}, "proton");
  if (p.species == "custom") {
    p.mass_MeV = r.number("mass_MeV");
    p.charge_e = r.number("charge_e");
    if (p.mass_MeV <= 0) throw r.error("mass_MeV", "must be > 0, got " + num(p.mass_MeV));
    if (p.charge_e == 0) throw r.error("charge_e", "must not be 0");
    return p;
  }
  // A named species fixes mass and charge; a second source of truth would drift.
  for (const char* k : {"mass_MeV", "charge_e"})
    if (r.has(k)) throw r.error(k, "only allowed with species 'custom'");
  return *named_particle(p.species);
}

FieldSpec read_field(json& j, const std::string& file, const std::string& dir) {
  Reader r(j, file, "/field", {"map", "format", "symmetry", "scale", "trimcoil_threshold_T"});
  FieldSpec f;
  f.map = r.string("map");
  if (f.map.empty()) throw r.error("map", "must not be empty");
  f.map = resolve_path(dir, f.map);
  f.format = r.one_of("format", {"psi-ring", "turnfit"}, "psi-ring");
  f.symmetry = r.integer("symmetry", 0);
  if (f.symmetry < 0)
    throw r.error("symmetry", "must be >= 1 (0: from the map), got " + num(f.symmetry));
  f.scale = r.number("scale", 1.0);
  if (f.scale == 0) throw r.error("scale", "must not be 0");
  f.trimcoil_threshold_T = r.number("trimcoil_threshold_T", 0.0);
  if (f.trimcoil_threshold_T < 0)
    throw r.error("trimcoil_threshold_T", "must be >= 0, got " + num(f.trimcoil_threshold_T));
  return f;
}

RfSystem read_rf(json& j, const std::string& file) {
  Reader r(j, file, "/rf", {"harmonic", "frequency_MHz"});
  RfSystem rf;
  rf.harmonic = r.integer("harmonic", 1);
  if (rf.harmonic < 1) throw r.error("harmonic", "must be >= 1, got " + num(rf.harmonic));
  rf.frequency_MHz = r.number("frequency_MHz", 0.0);
  if (rf.frequency_MHz < 0)
    throw r.error("frequency_MHz", "must be >= 0, got " + num(rf.frequency_MHz));
  return rf;
}

Cavity read_cavity(json& j, const std::string& file, const std::string& path,
                   const std::string& dir, std::map<std::string, std::string>& seen) {
  Reader r(j, file, path,
           {"name", "type", "voltage_MV", "profile", "harmonic_factor", "phase_deg", "angle_deg",
            "pdis_mm", "rmin_mm", "rmax_mm", "gap_width_mm", "rshift_mm"});
  Cavity c;
  c.name = element_name(r, seen);
  c.type = r.one_of("type", {"single-gap"}, "single-gap");
  c.voltage_MV = r.number("voltage_MV", 0.0);
  if (r.has("profile")) {
    c.profile = r.string("profile");
    if (c.profile.empty())
      throw r.error("profile", "must not be empty (leave it out for a flat profile)");
    c.profile = resolve_path(dir, c.profile);
  }
  c.harmonic_factor = r.number("harmonic_factor", 1.0);
  if (c.harmonic_factor <= 0)
    throw r.error("harmonic_factor", "must be > 0, got " + num(c.harmonic_factor));
  c.phase_deg = r.number("phase_deg", 0.0);
  c.angle_deg = r.number("angle_deg", 0.0);
  c.pdis_mm = r.number("pdis_mm", 0.0);
  c.rmin_mm = r.number("rmin_mm", 0.0);
  c.rmax_mm = r.number("rmax_mm");
  if (c.rmin_mm < 0) throw r.error("rmin_mm", "must be >= 0, got " + num(c.rmin_mm));
  if (c.rmax_mm <= c.rmin_mm)
    throw r.error("rmax_mm", "must be > rmin_mm (" + num(c.rmin_mm) + "), got " + num(c.rmax_mm));
  c.gap_width_mm = r.number("gap_width_mm", 0.0);
  if (c.gap_width_mm < 0) throw r.error("gap_width_mm", "must be >= 0, got " + num(c.gap_width_mm));
  c.rshift_mm = r.number("rshift_mm", 0.0);
  return c;
}

TrimCoil read_trimcoil(json& j, const std::string& file, const std::string& path,
                       const std::string& dir, int symmetry,
                       std::map<std::string, std::string>& seen) {
  Reader r(j, file, path,
           {"name", "type", "rmin_mm", "rmax_mm", "bmax_T", "coefnum", "coefdenom", "coef_origin_mm",
            "slope_per_mm", "table", "sectors", "phimin_deg", "phimax_deg"});
  TrimCoil t;
  t.name = element_name(r, seen);
  t.type =
      r.one_of("type", {"psi-bfield", "psi-phase", "psi-bfield-mirrored", "table"}, "psi-bfield");
  t.rmin_mm = r.number("rmin_mm", 0.0);
  t.rmax_mm = r.number("rmax_mm");
  if (t.rmin_mm < 0) throw r.error("rmin_mm", "must be >= 0, got " + num(t.rmin_mm));
  if (t.rmax_mm <= t.rmin_mm)
    throw r.error("rmax_mm", "must be > rmin_mm (" + num(t.rmin_mm) + "), got " + num(t.rmax_mm));
  t.bmax_T = r.number("bmax_T", 0.0);
  t.coefnum = r.numbers("coefnum");
  t.coefdenom = r.numbers("coefdenom");
  // Polynomials about the coil (tc-fit writes its window centre): coefficients in r itself
  // cancel to 1e-4 of the peak at r ~ 4 m for the degrees a field description needs.
  if (auto o = r.opt_number("coef_origin_mm")) {
    t.coef_origin_mm = *o;
    if (!(t.coef_origin_mm >= 0)) throw r.error("coef_origin_mm", "must be >= 0, got " + num(t.coef_origin_mm));
  }
  if ((t.type == "psi-bfield" || t.type == "psi-phase") && t.coefnum.empty())
    throw r.error("coefnum", "a " + t.type + " coil needs at least one numerator coefficient");
  if (auto s = r.opt_number("slope_per_mm")) t.slope_per_mm = *s;
  if (t.type == "psi-bfield-mirrored") {
    if (!r.has("slope_per_mm"))
      throw r.error("slope_per_mm", "missing required key (type psi-bfield-mirrored)");
    if (t.slope_per_mm <= 0)
      throw r.error("slope_per_mm", "must be > 0, got " + num(t.slope_per_mm));
  }
  if (t.type == "table") {
    if (!r.has("table")) throw r.error("table", "missing required key (type table)");
  }
  if (r.has("table")) {
    t.table = r.string("table");
    if (t.table.empty()) throw r.error("table", "must not be empty");
    t.table = resolve_path(dir, t.table);
  }
  if (r.has("sectors")) {
    const json& s = r.raw("sectors");
    if (!s.is_array())
      throw r.error("sectors", "expected an array of sector numbers, got " + Reader::type_name(s));
    std::set<int> used;
    for (size_t i = 0; i < s.size(); ++i) {
      std::string where = r.at("sectors") + "/" + std::to_string(i);
      int k = r.as_integer(s[i], where);
      if (k < 1 || (symmetry > 0 && k > symmetry)) {
        std::string range = symmetry > 0 ? "1.." + std::to_string(symmetry) : ">= 1";
        throw data_error(file, 0,
                         where + ": sector " + std::to_string(k) + " out of range (" + range + ")");
      }
      if (!used.insert(k).second)
        throw data_error(file, 0, where + ": sector " + std::to_string(k) + " listed twice");
      t.sectors.push_back(k);
    }
  }
  t.phimin_deg = r.number("phimin_deg", 0.0);
  t.phimax_deg = r.number("phimax_deg", 360.0);
  if (t.phimax_deg <= t.phimin_deg)
    throw r.error("phimax_deg",
                  "must be > phimin_deg (" + num(t.phimin_deg) + "), got " + num(t.phimax_deg));
  return t;
}

Probe read_probe(json& j, const std::string& file, const std::string& path,
                 std::map<std::string, std::string>& seen) {
  Reader r(j, file, path,
           {"name", "phi_deg", "a_mm", "s_min_mm", "s_max_mm", "shift_mm", "step_mm"});
  Probe p;
  p.name = element_name(r, seen);
  p.phi_deg = r.number("phi_deg", 0.0);
  p.a_mm = r.number("a_mm", 0.0);
  p.s_min_mm = r.number("s_min_mm", 0.0);
  p.s_max_mm = r.number("s_max_mm");
  if (p.s_max_mm <= p.s_min_mm)
    throw r.error("s_max_mm",
                  "must be > s_min_mm (" + num(p.s_min_mm) + "), got " + num(p.s_max_mm));
  p.shift_mm = r.number("shift_mm", 0.0);
  p.step_mm = r.number("step_mm", 0.5);
  if (p.step_mm <= 0) throw r.error("step_mm", "must be > 0, got " + num(p.step_mm));
  return p;
}

Injection read_injection(json& j, const std::string& file) {
  Reader r(j, file, "/injection",
           {"energy_MeV", "r_mm", "pr_betagamma", "phi_deg", "z_mm", "pz_betagamma", "t_ns"});
  Injection in;
  in.energy_MeV = r.number("energy_MeV");
  if (in.energy_MeV <= 0) throw r.error("energy_MeV", "must be > 0, got " + num(in.energy_MeV));
  in.r_mm = r.number("r_mm");
  if (in.r_mm <= 0) throw r.error("r_mm", "must be > 0, got " + num(in.r_mm));
  in.pr_betagamma = r.number("pr_betagamma", 0.0);
  in.phi_deg = r.number("phi_deg", 0.0);
  in.z_mm = r.number("z_mm", 0.0);
  in.pz_betagamma = r.number("pz_betagamma", 0.0);
  in.t_ns = r.number("t_ns", 0.0);
  return in;
}

Bunch read_bunch(json& j, const std::string& file, const std::string& dir) {
  Reader r(j, file, "/bunch",
           {"particles", "emittance_r_mm_mrad", "beta_r_m", "alpha_r", "emittance_z_mm_mrad", "beta_z_m",
            "alpha_z", "sigma_E_MeV", "sigma_phase_deg", "cutoff_sigma", "file"});
  Bunch b;
  b.particles = r.integer("particles", 0);
  if (b.particles < 0) throw r.error("particles", "must be >= 0, got " + num(b.particles));
  auto nonneg = [&](const char* key, double& v) {
    v = r.number(key, 0.0);
    if (v < 0) throw r.error(key, "must be >= 0, got " + num(v));
  };
  nonneg("emittance_r_mm_mrad", b.emittance_r_mm_mrad);
  nonneg("beta_r_m", b.beta_r_m);
  b.alpha_r = r.number("alpha_r", 0.0);
  nonneg("emittance_z_mm_mrad", b.emittance_z_mm_mrad);
  nonneg("beta_z_m", b.beta_z_m);
  b.alpha_z = r.number("alpha_z", 0.0);
  nonneg("sigma_E_MeV", b.sigma_E_MeV);
  nonneg("sigma_phase_deg", b.sigma_phase_deg);
  nonneg("cutoff_sigma", b.cutoff_sigma);
  // Each variate is redrawn until it falls inside the cutoff: below 0.5 sigma most draws fail.
  if (b.cutoff_sigma > 0 && b.cutoff_sigma < 0.5)
    throw r.error("cutoff_sigma", "must be 0 (no truncation) or at least 0.5, got " + num(b.cutoff_sigma));
  // An emittance needs its beta function: a sigma from the emittance alone would be a guess.
  if (b.emittance_r_mm_mrad > 0 && !(b.beta_r_m > 0))
    throw r.error("beta_r_m", "must be > 0 when emittance_r_mm_mrad is given");
  if (b.emittance_z_mm_mrad > 0 && !(b.beta_z_m > 0))
    throw r.error("beta_z_m", "must be > 0 when emittance_z_mm_mrad is given");
  b.file = resolve_path(dir, r.string("file", std::string()));
  return b;
}

SpaceChargeSpec read_space_charge(json& j, const std::string& file) {
  Reader r(j, file, "/space_charge", {"current_uA", "grid", "every_steps", "halo_sigma"});
  SpaceChargeSpec sc;
  sc.current_uA = r.number("current_uA");
  if (sc.current_uA < 0) throw r.error("current_uA", "must be >= 0, got " + num(sc.current_uA));
  if (r.has("grid")) {
    const json& g = r.raw("grid");
    if (!g.is_array() || g.size() != 3)
      throw r.error("grid", "expected an array of three grid sizes [radial, vertical, longitudinal]");
    for (size_t k = 0; k < 3; ++k) {
      const json& v = g[k];
      if (!v.is_number_integer() || v.get<long long>() < 8 || v.get<long long>() > 512)
        throw data_error(file, 0, r.at("grid") + "/" + std::to_string(k) +
                                      ": a grid size is a whole number from 8 to 512 (fewer points cannot resolve "
                                      "a bunch)");
      sc.grid[k] = static_cast<int>(v.get<long long>());
    }
  } else {
    r.raw("grid") = json::array({sc.grid[0], sc.grid[1], sc.grid[2]});
  }
  sc.every_steps = r.integer("every_steps", 1);
  if (sc.every_steps < 1 || sc.every_steps > 100000)
    throw r.error("every_steps", "must be from 1 to 100000, got " + num(sc.every_steps));
  sc.halo_sigma = r.number("halo_sigma", 8.0);
  if (sc.halo_sigma != 0 && !(sc.halo_sigma >= 3))
    throw r.error("halo_sigma", "must be 0 (no halo cut) or at least 3, got " + num(sc.halo_sigma));
  return sc;
}

Tracking read_tracking(json& j, const std::string& file) {
  Reader r(j, file, "/tracking", {"integrator", "steps_per_turn", "step_deg", "turns"});
  Tracking t;
  t.integrator = r.string("integrator", std::string());
  t.steps_per_turn = r.integer("steps_per_turn", 0);
  if (t.steps_per_turn < 0)
    throw r.error("steps_per_turn", "must be >= 0, got " + num(t.steps_per_turn));
  t.step_deg = r.number("step_deg", 0.0);
  if (t.step_deg < 0 || t.step_deg > 45 || (t.step_deg > 0 && t.step_deg < 1e-4))
    throw r.error("step_deg", "must be 0 (the default) or in [0.0001, 45], got " + num(t.step_deg));
  t.turns = r.integer("turns", 0);
  if (t.turns < 0) throw r.error("turns", "must be >= 0, got " + num(t.turns));
  return t;
}

// The effect types and the keys each takes ("type" and a free "description" besides).
const std::vector<std::pair<std::string, std::vector<std::string>>>& effect_types() {
  static const std::vector<std::pair<std::string, std::vector<std::string>>> types = {
      {"field-harmonic", {"n", "amplitude_T", "phase_deg", "r_mm", "width_mm"}},
      // The older name of field-harmonic (machine files written before effects were tracked).
      {"harmonic-error", {"n", "amplitude_T", "phase_deg", "r_mm", "width_mm"}},
      {"sector-strength", {"sector", "relative", "transition_deg"}},
      {"trimcoil-sectors", {"coils", "sectors"}},
      {"gap-bow", {"cavity", "sagitta_mm"}},
      {"voltage-tilt", {"cavity", "slope", "pivot_rho_n"}},
      {"probe-offset", {"probe", "dphi_deg", "da_mm", "ds_mm", "pivot_s_mm"}},
      {"injection-offset", {"dr_mm", "dpr_mrad", "dz_mm", "dpz_mrad", "dE_MeV", "dphase_deg"}}};
  return types;
}

// A limit on a parameter: |v| <= lim, with a message that says why the limit exists.
void check_abs(const Reader& r, const std::string& key, double v, double lim, const std::string& why) {
  if (!(std::fabs(v) <= lim))
    throw r.error(key, "must be within [-" + num(lim) + ", " + num(lim) + "]" + why + ", got " + num(v));
}

// Validates `effects` (turnfit-machine(5) "EFFECTS") against the machine read so far: every
// type's keys, units and ranges, and the cavities, probes and coils they name.
Effects read_effects(json& a, const std::string& file, const Machine& m) {
  if (!a.is_array())
    throw data_error(file, 0, "/effects: expected a JSON array, got " + Reader::type_name(a));
  Effects fx;
  std::map<std::string, std::string> seen;  // "kind:target" -> path of the first effect on it
  auto once = [&](const Reader& r, const std::string& key, const std::string& target, const std::string& what) {
    auto [it, fresh] = seen.emplace(what + ":" + target, r.at(key));
    if (!fresh) throw r.error(key, "a second " + what + " '" + target + "' (the first is " + it->second + ")");
  };
  const int sym = m.field.symmetry;
  auto sector_of = [&](const Reader& r, const json& j, const std::string& where) {
    const int k = r.as_integer(j, where);
    if (k < 1 || (sym > 0 && k > sym))
      throw data_error(file, 0, where + ": sector " + std::to_string(k) + " out of range (" +
                                    (sym > 0 ? "1.." + std::to_string(sym) : std::string(">= 1")) + ")");
    return k;
  };
  auto cavity_named = [&](Reader& r) -> const Cavity& {
    const std::string name = r.string("cavity");
    for (const auto& c : m.cavities)
      if (c.name == name) return c;
    throw r.error("cavity", "no cavity named '" + name + "'");
  };
  for (size_t i = 0; i < a.size(); ++i) {
    const std::string where = "/effects/" + std::to_string(i);
    if (!a[i].is_object())
      throw data_error(file, 0, where + ": expected a JSON object, got " + Reader::type_name(a[i]));
    if (!a[i].contains("type")) throw data_error(file, 0, where + "/type: missing required key");
    if (!a[i]["type"].is_string() || a[i]["type"].get<std::string>().empty())
      throw data_error(file, 0, where + "/type: expected a non-empty string");
    const std::string type = a[i]["type"].get<std::string>();
    const auto& types = effect_types();
    auto it = std::find_if(types.begin(), types.end(), [&](const auto& t) { return t.first == type; });
    if (it == types.end()) {
      std::vector<std::string> names;
      std::string list;
      for (const auto& t : types)
        if (t.first != "harmonic-error") names.push_back(t.first), list += (list.empty() ? "" : ", ") + t.first;
      throw data_error(file, 0, where + "/type: unknown effect type '" + type + "'" +
                                    unknown_key_hint(type, names) + " (known: " + list + ")");
    }
    std::vector<std::string> known = it->second;
    known.push_back("type");
    known.push_back("description");
    Reader r(a[i], file, where, known);
    r.string("description", std::string());
    if (type == "field-harmonic" || type == "harmonic-error") {
      FieldHarmonicEffect e;
      e.index = i;
      e.n = r.integer("n", 1);
      if (e.n < 0 || e.n > 64) throw r.error("n", "must be in 0..64, got " + num(e.n));
      e.amplitude_T = r.number("amplitude_T");
      check_abs(r, "amplitude_T", e.amplitude_T, 0.5, " (an error field, not a magnet)");
      e.phase_deg = r.number("phase_deg", 0.0);
      // Both or neither: a centre without a width (or the reverse) is a half-given bump.
      if (r.has("r_mm") != r.has("width_mm"))
        throw r.error(r.has("r_mm") ? "width_mm" : "r_mm",
                      "missing required key (r_mm and width_mm go together; leave both out for every radius)");
      if (r.has("r_mm")) {
        e.r_mm = r.number("r_mm");
        if (!(e.r_mm >= 0)) throw r.error("r_mm", "must be >= 0, got " + num(e.r_mm));
        e.width_mm = r.number("width_mm");
        if (!(e.width_mm > 0)) throw r.error("width_mm", "must be > 0, got " + num(e.width_mm));
      }
      fx.field_harmonics.push_back(e);
    } else if (type == "sector-strength") {
      SectorStrengthEffect e;
      e.index = i;
      if (!r.has("sector")) throw r.error("sector", "missing required key");
      e.sector = sector_of(r, r.raw("sector"), r.at("sector"));
      once(r, "sector", std::to_string(e.sector), "sector-strength on sector");
      e.relative = r.number("relative");
      check_abs(r, "relative", e.relative, 0.1, " (a fraction: 0.001 is 0.1 %)");
      e.transition_deg = r.number("transition_deg", 0.0);
      const double pitch = sym > 0 ? 360.0 / sym : 360.0;
      if (e.transition_deg < 0 || e.transition_deg > pitch)
        throw r.error("transition_deg", "must be in [0, " + num(pitch) + "] (0: a quarter of the sector pitch), got " +
                                            num(e.transition_deg));
      fx.sector_strengths.push_back(e);
    } else if (type == "trimcoil-sectors") {
      TrimcoilSectorsEffect e;
      e.index = i;
      for (const char* k : {"coils", "sectors"})
        if (!r.has(k) || !r.raw(k).is_array() || r.raw(k).empty())
          throw r.error(k, r.has(k) ? "expected a non-empty array" : "missing required key");
      const json& cs = r.raw("coils");
      for (size_t c = 0; c < cs.size(); ++c) {
        const std::string at = r.at("coils") + "/" + std::to_string(c);
        if (!cs[c].is_string()) throw data_error(file, 0, at + ": expected a coil name, got " + Reader::type_name(cs[c]));
        const std::string name = cs[c].get<std::string>();
        if (std::none_of(m.trimcoils.begin(), m.trimcoils.end(), [&](const TrimCoil& t) { return t.name == name; }))
          throw data_error(file, 0, at + ": no trim coil named '" + name + "'");
        auto [s, fresh] = seen.emplace("coil:" + name, at);
        if (!fresh) throw data_error(file, 0, at + ": trim coil '" + name + "' is restricted already (" + s->second + ")");
        e.coils.push_back(name);
      }
      const json& ss = r.raw("sectors");
      for (size_t k = 0; k < ss.size(); ++k) {
        const std::string at = r.at("sectors") + "/" + std::to_string(k);
        const int sec = sector_of(r, ss[k], at);
        if (std::find(e.sectors.begin(), e.sectors.end(), sec) != e.sectors.end())
          throw data_error(file, 0, at + ": sector " + std::to_string(sec) + " listed twice");
        e.sectors.push_back(sec);
      }
      fx.trimcoil_sectors.push_back(e);
    } else if (type == "gap-bow") {
      GapBowEffect e;
      e.index = i;
      const Cavity& c = cavity_named(r);
      e.cavity = c.name;
      once(r, "cavity", c.name, "gap-bow on cavity");
      e.sagitta_mm = r.number("sagitta_mm");
      // A parabola of sagitta s over a chord L has end slopes 4 s / L: at most 0.4, where the
      // chord-projected voltage profile and the local gap normal are still good approximations.
      check_abs(r, "sagitta_mm", e.sagitta_mm, 0.1 * (c.rmax_mm - c.rmin_mm),
                " (a tenth of the gap length " + num(c.rmax_mm - c.rmin_mm) + " mm)");
      fx.gap_bows.push_back(e);
    } else if (type == "voltage-tilt") {
      VoltageTiltEffect e;
      e.index = i;
      e.cavity = cavity_named(r).name;
      once(r, "cavity", e.cavity, "voltage-tilt on cavity");
      e.slope = r.number("slope");
      e.pivot_rho_n = r.number("pivot_rho_n", 0.5);
      if (!(e.pivot_rho_n >= 0 && e.pivot_rho_n <= 1))
        throw r.error("pivot_rho_n", "must be in [0, 1], got " + num(e.pivot_rho_n));
      // The factor 1 + slope (rho_n - pivot) must stay positive over the whole gap.
      if (!(1 - e.slope * e.pivot_rho_n > 0 && 1 + e.slope * (1 - e.pivot_rho_n) > 0))
        throw r.error("slope", "reverses the voltage at one end of the gap (1 + slope (rho_n - pivot_rho_n) <= 0), got " +
                                   num(e.slope));
      fx.voltage_tilts.push_back(e);
    } else if (type == "probe-offset") {
      ProbeOffsetEffect e;
      e.index = i;
      e.probe = r.string("probe");
      if (std::none_of(m.probes.begin(), m.probes.end(), [&](const Probe& p) { return p.name == e.probe; }))
        throw r.error("probe", "no probe named '" + e.probe + "'");
      once(r, "probe", e.probe, "probe-offset on probe");
      e.dphi_deg = r.number("dphi_deg", 0.0);
      check_abs(r, "dphi_deg", e.dphi_deg, 10, " (a misalignment)");
      e.da_mm = r.number("da_mm", 0.0);
      check_abs(r, "da_mm", e.da_mm, 200, " (a misalignment)");
      e.ds_mm = r.number("ds_mm", 0.0);
      check_abs(r, "ds_mm", e.ds_mm, 200, " (a misalignment)");
      e.pivot_s_mm = r.opt_number("pivot_s_mm");
      fx.probe_offsets.push_back(e);
    } else {  // injection-offset
      InjectionOffsetEffect e;
      e.index = i;
      if (fx.injection_offset)
        throw r.error_here("a second injection-offset (the first is /effects/" +
                           std::to_string(fx.injection_offset->index) + "): give one");
      if (!m.injection) throw r.error_here("injection-offset needs the machine's injection block");
      const Injection& in = *m.injection;
      e.dr_mm = r.number("dr_mm", 0.0);
      if (!(in.r_mm + e.dr_mm > 0))
        throw r.error("dr_mm", "puts the start at r <= 0 (injection r_mm " + num(in.r_mm) + "), got " + num(e.dr_mm));
      e.dpr_mrad = r.number("dpr_mrad", 0.0);
      e.dz_mm = r.number("dz_mm", 0.0);
      e.dpz_mrad = r.number("dpz_mrad", 0.0);
      e.dE_MeV = r.number("dE_MeV", 0.0);
      if (!(in.energy_MeV + e.dE_MeV > 0))
        throw r.error("dE_MeV", "leaves no kinetic energy (injection energy_MeV " + num(in.energy_MeV) + "), got " +
                                    num(e.dE_MeV));
      // p_r / p and p_z / p after the offsets: their squares must leave an azimuthal part.
      const double g0 = 1 + in.energy_MeV / m.particle.mass_MeV, P0 = std::sqrt(g0 * g0 - 1);
      const double xr = in.pr_betagamma / P0 + e.dpr_mrad * 1e-3, xz = in.pz_betagamma / P0 + e.dpz_mrad * 1e-3;
      if (!(xr * xr + xz * xz < 1))
        throw r.error(e.dpr_mrad != 0 ? "dpr_mrad" : "dpz_mrad", "leaves the particle no azimuthal momentum");
      e.dphase_deg = r.number("dphase_deg", 0.0);
      if (e.dphase_deg != 0 && !(m.rf.frequency_MHz > 0))
        throw r.error("dphase_deg", "a phase offset needs an RF frequency (rf.frequency_MHz)");
      fx.injection_offset = e;
    }
  }
  return fx;
}

// A design-variable target must be a number the user may vary: not the format tag and not
// the bounds of another design variable.
void check_pointer(const json& doc, const std::string& p, const std::string& file,
                   const std::string& where) {
  if (p.empty() || p[0] != '/')
    throw data_error(file, 0, where + ": JSON pointer must start with '/', got '" + p + "'");
  if (p.rfind("/dvars", 0) == 0 || p.rfind("/format", 0) == 0)
    throw data_error(file, 0, where + ": '" + p + "' cannot be a design-variable target");
  json::json_pointer ptr;
  try {
    ptr = json::json_pointer(p);
  } catch (const json::exception&) {
    throw data_error(file, 0, where + ": '" + p + "' is not a valid JSON pointer");
  }
  if (!doc.contains(ptr))
    throw data_error(file, 0, where + ": '" + p + "' does not exist in the machine");
  if (!doc.at(ptr).is_number()) throw data_error(file, 0, where + ": '" + p + "' is not a number");
}

bool valid_dvar_name(const std::string& n) {
  if (n.empty() || !(std::isalpha(static_cast<unsigned char>(n[0])) || n[0] == '_')) return false;
  return std::all_of(n.begin(), n.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.' || c == '-';
  });
}

// The "dvars" section: new variables (pointer or targets) and bound overrides of built-ins.
void read_dvars(const json& section, const json& doc, const std::string& file,
                std::map<std::string, DesignVariable>& dvars) {
  if (!section.is_object())
    throw data_error(file, 0, "/dvars: expected a JSON object, got " + Reader::type_name(section));
  for (const auto& item : section.items()) {
    const std::string& name = item.key();
    std::string path = "/dvars/" + escape_key(name);
    if (!valid_dvar_name(name))
      throw data_error(
          file, 0,
          path +
              ": design-variable names start with a letter and use letters, digits, '_', '.', '-'");
    json entry = item.value();
    Reader r(entry, file, path,
             {"pointer", "targets", "scale", "add", "lower", "upper", "unit", "description"});
    auto lower = r.opt_number("lower");
    auto upper = r.opt_number("upper");
    DesignVariable dv;
    bool defines = r.has("pointer") || r.has("targets");
    if (!defines) {
      auto it = dvars.find(name);
      if (it == dvars.end())
        throw r.error_here("needs 'pointer' or 'targets' ('" + name +
                           "' is not a built-in design variable of this machine)");
      for (const char* k : {"scale", "add", "unit"})
        if (r.has(k))
          throw r.error(k, "a built-in design variable takes only lower, upper and description");
      dv = it->second;
    } else {
      if (r.has("pointer") && r.has("targets"))
        throw r.error("targets", "give either 'pointer' or 'targets', not both");
      dv.name = name;
      dv.unit = r.string("unit", std::string());
      if (!lower) throw r.error("lower", "missing required key");
      if (!upper) throw r.error("upper", "missing required key");
      if (r.has("pointer")) {
        DesignVariable::Target t;
        t.pointer = r.string("pointer");
        t.scale = r.number("scale", 1.0);
        t.add = r.boolean("add", false);
        if (t.scale == 0) throw r.error("scale", "must not be 0");
        check_pointer(doc, t.pointer, file, r.at("pointer"));
        dv.targets.push_back(t);
      } else {
        for (const char* k : {"scale", "add"})
          if (r.has(k)) throw r.error(k, "goes into each entry of 'targets'");
        json& ts = r.raw("targets");
        if (!ts.is_array() || ts.empty())
          throw r.error("targets", "expected a non-empty array of {pointer, scale, add}");
        for (size_t i = 0; i < ts.size(); ++i) {
          Reader tr(ts[i], file, r.at("targets") + "/" + std::to_string(i),
                    {"pointer", "scale", "add"});
          DesignVariable::Target t;
          t.pointer = tr.string("pointer");
          t.scale = tr.number("scale", 1.0);
          t.add = tr.boolean("add", false);
          if (t.scale == 0) throw tr.error("scale", "must not be 0");
          check_pointer(doc, t.pointer, file, tr.at("pointer"));
          // One value per variable: either it sets every target or it shifts every target.
          if (!dv.targets.empty() && t.add != dv.targets.front().add)
            throw tr.error("add", "all targets of a design variable must agree on 'add'");
          dv.targets.push_back(t);
        }
      }
    }
    if (r.has("description")) dv.description = r.string("description");
    if (lower) dv.lower = *lower;
    if (upper) dv.upper = *upper;
    if (!(dv.lower < dv.upper))
      throw r.error_here("lower (" + num(dv.lower) + ") must be < upper (" + num(dv.upper) + ")");
    // A nominal value outside the bounds is almost always a unit slip (MeV bounds on a GeV
    // variable); the document has no additive offsets applied yet, so its value is nominal.
    const auto& t0 = dv.targets.front();
    double nominal = t0.add ? 0.0 : doc.at(json::json_pointer(t0.pointer)).get<double>() / t0.scale;
    if (nominal < dv.lower || nominal > dv.upper)
      throw r.error_here("nominal value " + num(nominal) + " is outside [" + num(dv.lower) + ", " +
                         num(dv.upper) + "]");
    dvars[name] = dv;
  }
}

// Trim coil 3 may be called TC3 or TC03; with both, tc03mb would not know which to move.
void check_tc_aliases(const Machine& m, const std::string& file) {
  for (int n = 1; n < 10; ++n) {
    std::string a = "TC" + std::to_string(n), b = "TC0" + std::to_string(n);
    int ia = -1, ib = -1;
    for (size_t i = 0; i < m.trimcoils.size(); ++i) {
      if (m.trimcoils[i].name == a) ia = static_cast<int>(i);
      if (m.trimcoils[i].name == b) ib = static_cast<int>(i);
    }
    if (ia >= 0 && ib >= 0)
      throw data_error(file, 0,
                       "/trimcoils/" + std::to_string(std::max(ia, ib)) + "/name: '" + a +
                           "' and '" + b + "' both name trim coil " + std::to_string(n) + " (tc0" +
                           std::to_string(n) + "mb would be ambiguous)");
  }
}

// Validates and normalizes; with_dvars = false skips the design variables (revalidate keeps
// the loaded ones, whose bounds must not drift with every set).
Machine build(const json& input, const std::string& file, const std::string& dir, bool with_dvars) {
  Machine m;
  m.dir = dir;
  m.doc = input;
  json& doc = m.doc;
  Reader top(doc, file, "",
             {"format", "name", "description", "particle", "field", "rf", "cavities", "trimcoils",
              "probes", "injection", "bunch", "space_charge", "tracking", "effects", "dvars"});
  std::string format = top.string("format");
  if (format != kFormat)
    throw top.error("format", "expected '" + std::string(kFormat) + "', got '" + format + "'");
  m.name = top.string("name", std::string());
  top.string("description", std::string());
  if (top.has("particle")) m.particle = read_particle(doc["particle"], file);
  if (!top.has("field")) throw top.error("field", "missing required key");
  m.field = read_field(doc["field"], file, dir);
  if (top.has("rf")) m.rf = read_rf(doc["rf"], file);
  if (top.has("cavities")) {
    json& a = array_at(doc, "cavities", file);
    std::map<std::string, std::string> seen;
    for (size_t i = 0; i < a.size(); ++i)
      m.cavities.push_back(read_cavity(a[i], file, "/cavities/" + std::to_string(i), dir, seen));
  }
  if (top.has("trimcoils")) {
    json& a = array_at(doc, "trimcoils", file);
    std::map<std::string, std::string> seen;
    for (size_t i = 0; i < a.size(); ++i)
      m.trimcoils.push_back(read_trimcoil(a[i], file, "/trimcoils/" + std::to_string(i), dir,
                                          m.field.symmetry, seen));
    check_tc_aliases(m, file);
  }
  if (top.has("probes")) {
    json& a = array_at(doc, "probes", file);
    std::map<std::string, std::string> seen;
    for (size_t i = 0; i < a.size(); ++i)
      m.probes.push_back(read_probe(a[i], file, "/probes/" + std::to_string(i), seen));
  }
  if (top.has("injection")) m.injection = read_injection(doc["injection"], file);
  if (top.has("bunch")) m.bunch = read_bunch(doc["bunch"], file, dir);
  if (top.has("space_charge")) m.space_charge = read_space_charge(doc["space_charge"], file);
  if (top.has("tracking")) m.tracking = read_tracking(doc["tracking"], file);
  if (top.has("effects")) {
    m.effect_set = read_effects(doc["effects"], file, m);
    m.effects = doc["effects"];
  }
  if (with_dvars) {
    // Built-ins first: a file entry of the same name overrides their bounds or definition.
    m.dvars = builtin_dvars(m);
    if (top.has("dvars")) read_dvars(doc["dvars"], doc, file, m.dvars);
    for (const auto& [name, dv] : m.dvars)
      if (!dv.targets.empty() && dv.targets.front().add) m.dvar_offsets[name] = 0.0;
  } else if (top.has("dvars") && !doc["dvars"].is_object()) {
    throw data_error(file, 0, "/dvars: expected a JSON object");
  }
  return m;
}

std::string message_name(const std::string& path) {
  if (path.empty()) return "<machine>";
  if (path == "-") return "<stdin>";
  return path;
}

}  // namespace

Machine machine_from_json(const nlohmann::json& doc, const std::string& name,
                          const std::string& dir) {
  return build(doc, name, dir, true);
}

Machine load_machine(const std::string& path) {
  json doc = read_json(path);
  std::string dir;
  if (path != "-" && !path.empty()) dir = std::filesystem::path(path).parent_path().string();
  Machine m = machine_from_json(doc, message_name(path), dir);
  m.path = path;
  return m;
}

void revalidate(Machine& m) {
  Machine n = build(m.doc, message_name(m.path), m.dir, false);
  n.path = m.path;
  n.dvars = std::move(m.dvars);
  n.dvar_offsets = std::move(m.dvar_offsets);
  m = std::move(n);
}

std::optional<Particle> named_particle(const std::string& species) {
  Particle p;
  p.species = species;
  if (species == "proton") p.mass_MeV = kProtonMass, p.charge_e = 1;
  else if (species == "deuteron") p.mass_MeV = kDeuteronMass, p.charge_e = 1;
  else if (species == "alpha") p.mass_MeV = kAlphaMass, p.charge_e = 2;
  else if (species == "h2+") p.mass_MeV = kH2PlusMass, p.charge_e = 1;
  else return std::nullopt;
  return p;
}

}  // namespace turnfit
