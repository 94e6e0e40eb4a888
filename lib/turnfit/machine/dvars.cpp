// Design variables: the paper's built-in set, and setting values by name, pointer or file.
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/machine/machine.hpp"

namespace turnfit {
namespace {

using nlohmann::json;

std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return buf;
}

std::string idx(size_t i) { return std::to_string(i); }

DesignVariable make_dvar(const std::string& name, const std::string& unit,
                         const std::string& description, const std::string& pointer, double lower,
                         double upper, double scale = 1.0) {
  DesignVariable dv;
  dv.name = name;
  dv.unit = unit;
  dv.description = description;
  dv.targets.push_back({pointer, scale, false});
  dv.lower = lower;
  dv.upper = upper;
  return dv;
}

template <class T>
int find_named(const std::vector<T>& items, const std::string& name) {
  for (size_t i = 0; i < items.size(); ++i)
    if (items[i].name == name) return static_cast<int>(i);
  return -1;
}

bool is_additive(const DesignVariable& dv) { return !dv.targets.empty() && dv.targets.front().add; }

// The shift all additive variables currently put on one place of the document.
double adds_on(const Machine& m, const std::string& pointer) {
  double sum = 0;
  for (const auto& [name, dv] : m.dvars) {
    if (!is_additive(dv)) continue;
    auto off = m.dvar_offsets.find(name);
    double offset = off == m.dvar_offsets.end() ? 0.0 : off->second;
    for (const auto& t : dv.targets)
      if (t.pointer == pointer) sum += t.scale * offset;
  }
  return sum;
}

json& target(Machine& m, const std::string& pointer) {
  return m.doc.at(json::json_pointer(pointer));
}

// Replacing writes set the base value; additive variables stay on top, so the result does
// not depend on the order in which variables are set (vmaincav1 and vchange, say).
void write_dvar(Machine& m, const DesignVariable& dv, double value) {
  if (is_additive(dv)) {
    double old = m.dvar_offsets[dv.name];
    for (const auto& t : dv.targets) {
      json& j = target(m, t.pointer);
      j = j.get<double>() + t.scale * (value - old);
    }
    m.dvar_offsets[dv.name] = value;
    return;
  }
  for (const auto& t : dv.targets) target(m, t.pointer) = t.scale * value + adds_on(m, t.pointer);
}

// "" when value lies within the bounds (with a little slack for printed-and-read-back values).
std::string bounds_problem(const DesignVariable& dv, double value) {
  double slack = 1e-9 * (dv.upper - dv.lower);
  if (value >= dv.lower - slack && value <= dv.upper + slack) return {};
  return dv.name + " = " + num(value) + " is outside its bounds [" + num(dv.lower) + ", " +
         num(dv.upper) + "]" + (dv.unit.empty() ? "" : " " + dv.unit);
}

// "" when pointer names an existing number a user may change.
std::string pointer_problem(const Machine& m, const std::string& pointer) {
  if (pointer.rfind("/dvars", 0) == 0 || pointer.rfind("/format", 0) == 0)
    return "'" + pointer + "' cannot be set";
  json::json_pointer ptr;
  try {
    ptr = json::json_pointer(pointer);
  } catch (const json::exception&) {
    return "'" + pointer + "' is not a valid JSON pointer";
  }
  if (!m.doc.contains(ptr)) return "'" + pointer + "' does not exist in the machine";
  if (!m.doc.at(ptr).is_number()) return "'" + pointer + "' is not a number";
  return {};
}

void write_pointer(Machine& m, const std::string& pointer, double value) {
  target(m, pointer) = value + adds_on(m, pointer);
}

std::string unknown_dvar(const Machine& m, const std::string& name) {
  std::string best;
  size_t best_d = 3;
  for (const auto& [n, dv] : m.dvars) {
    size_t d = edit_distance(name, n);
    if (d < best_d) best_d = d, best = n;
  }
  std::string msg = "unknown design variable '" + name + "'";
  if (!best.empty()) msg += " (did you mean '" + best + "'?)";
  // The paper's names exist only where the machine has the element they act on.
  static const std::pair<const char*, const char*> needs[] = {
      {"benergy", "an injection block"}, {"prinit", "an injection block"}, {"rinit", "an injection block"},
      {"phiinit", "an injection block"}, {"vmaincav", "cavities main1..main4"}, {"vchange", "cavities main1..main4"},
      {"phimain", "cavities main1..main4"}, {"pdismain", "cavities main1..main4"},
      {"rmainshift", "cavities main1..main4"}, {"vftcav", "a cavity named ft"}, {"phift", "a cavity named ft"},
      {"phirfft", "a cavity named ft"}, {"pdisft", "a cavity named ft"}, {"rftshift", "a cavity named ft"},
      {"rri2", "a probe named RRI2"}, {"rrl", "a probe named RRL"}, {"tc", "trim coils named TC1..TC16"}};
  for (const auto& [prefix, what] : needs)
    if (name.rfind(prefix, 0) == 0 && best.empty()) {
      msg += " (one of the paper's design variables; it needs " + std::string(what) + " in the machine)";
      break;
    }
  return msg;
}

// Whole-token finite decimal; hex floats and "inf"/"nan" are typos on a command line.
bool parse_value(const std::string& s, double& out) { return parse_decimal(s, out); }

std::string message_name(const std::string& path) { return path == "-" ? "<stdin>" : path; }

}  // namespace

std::map<std::string, DesignVariable> builtin_dvars(const Machine& m) {
  std::map<std::string, DesignVariable> out;
  auto add = [&](DesignVariable dv) { out[dv.name] = std::move(dv); };

  if (m.injection) {
    const Injection& in = *m.injection;
    // benergy is in GeV as in the paper; the machine file keeps MeV.
    double e = in.energy_MeV / 1000;
    add(make_dvar("benergy", "GeV", "injection beam energy", "/injection/energy_MeV", e - 5e-4,
                  e + 5e-4, 1000));
    add(make_dvar("prinit", "beta*gamma", "injection radial momentum", "/injection/pr_betagamma",
                  in.pr_betagamma - 5e-3, in.pr_betagamma + 5e-3));
    add(make_dvar("rinit", "mm", "injection radius w.r.t. the global coordinate system",
                  "/injection/r_mm", in.r_mm - 5, in.r_mm + 5));
    add(make_dvar("phiinit", "deg", "injection angle of the beam", "/injection/phi_deg",
                  in.phi_deg - 1, in.phi_deg + 1));
  }

  auto cavity_dvars = [&](int i, const std::string& vname, const std::string& what,
                          const std::string& phi, const std::string& pdis,
                          const std::string& rshift) {
    const Cavity& c = m.cavities[static_cast<size_t>(i)];
    std::string base = "/cavities/" + idx(static_cast<size_t>(i)) + "/";
    double dv = std::max(0.05 * std::fabs(c.voltage_MV), 0.01);
    add(make_dvar(vname, "MV", "RF voltage on " + what, base + "voltage_MV", c.voltage_MV - dv,
                  c.voltage_MV + dv));
    add(make_dvar(phi, "deg", what + " angle w.r.t. the global coordinate system",
                  base + "angle_deg", c.angle_deg - 1, c.angle_deg + 1));
    add(make_dvar(pdis, "mm", "displacement of the " + what + " axis from the global centre",
                  base + "pdis_mm", c.pdis_mm - 5, c.pdis_mm + 5));
    add(make_dvar(rshift, "mm", what + " displacement in radial direction", base + "rshift_mm",
                  c.rshift_mm - 5, c.rshift_mm + 5));
  };
  int mains = 0;
  for (int k = 1; k <= 4; ++k) {
    std::string n = std::to_string(k);
    int i = find_named(m.cavities, "main" + n);
    if (i < 0) continue;
    ++mains;
    cavity_dvars(i, "vmaincav" + n, "main cavity " + n, "phimain" + n, "pdismain" + n,
                 "rmainshift" + n);
  }
  if (mains == 4) {
    // The paper's vchange is the total extra voltage of the four main cavities, a quarter each.
    DesignVariable dv;
    dv.name = "vchange";
    dv.unit = "MV";
    dv.description = "total extra voltage spread over the four main cavities (a quarter each)";
    for (int k = 1; k <= 4; ++k) {
      int i = find_named(m.cavities, "main" + std::to_string(k));
      dv.targets.push_back(
          {"/cavities/" + idx(static_cast<size_t>(i)) + "/voltage_MV", 0.25, true});
    }
    dv.lower = -0.2;
    dv.upper = 0.2;
    add(dv);
  }
  if (int i = find_named(m.cavities, "ft"); i >= 0) {
    cavity_dvars(i, "vftcav", "flat-top cavity", "phift", "pdisft", "rftshift");
    const Cavity& c = m.cavities[static_cast<size_t>(i)];
    add(make_dvar("phirfft", "deg", "RF phase of the flat-top cavity",
                  "/cavities/" + idx(static_cast<size_t>(i)) + "/phase_deg", c.phase_deg - 5,
                  c.phase_deg + 5));
  }

  for (const auto& [probe, prefix] :
       {std::pair<std::string, std::string>{"RRI2", "rri2"}, {"RRL", "rrl"}}) {
    int i = find_named(m.probes, probe);
    if (i < 0) continue;
    const Probe& p = m.probes[static_cast<size_t>(i)];
    std::string base = "/probes/" + idx(static_cast<size_t>(i)) + "/";
    add(make_dvar(prefix + "a", "mm", "offset a of the " + probe + " probe line (paper Eq. 1)",
                  base + "a_mm", p.a_mm - 5, p.a_mm + 5));
    add(make_dvar(prefix + "phi", "deg", "azimuth phi of the " + probe + " probe (paper Eq. 1)",
                  base + "phi_deg", p.phi_deg - 1, p.phi_deg + 1));
    add(make_dvar(prefix + "shift", "mm", "radial start shift of " + probe + " (> 0: outwards)",
                  base + "shift_mm", p.shift_mm - 5, p.shift_mm + 5));
  }

  for (int n = 1; n <= 16; ++n) {
    char two[8];
    std::snprintf(two, sizeof two, "%02d", n);
    int i = find_named(m.trimcoils, "TC" + std::to_string(n));
    if (i < 0) i = find_named(m.trimcoils, std::string("TC") + two);
    if (i < 0) continue;
    double b = m.trimcoils[static_cast<size_t>(i)].bmax_T;
    double span = std::fabs(b) + 2e-3;
    add(make_dvar(std::string("tc") + two + "mb", "T",
                  "maximum field of trim coil TC" + std::to_string(n),
                  "/trimcoils/" + idx(static_cast<size_t>(i)) + "/bmax_T", -span, span));
  }
  return out;
}

double dvar_value(const Machine& m, const std::string& name) {
  auto it = m.dvars.find(name);
  if (it == m.dvars.end()) throw usage_error(unknown_dvar(m, name));
  const DesignVariable& dv = it->second;
  if (is_additive(dv)) {
    auto off = m.dvar_offsets.find(name);
    return off == m.dvar_offsets.end() ? 0.0 : off->second;
  }
  const auto& t = dv.targets.front();
  return (m.doc.at(json::json_pointer(t.pointer)).get<double>() - adds_on(m, t.pointer)) / t.scale;
}

void set_dvar(Machine& m, const std::string& name, double value) {
  auto it = m.dvars.find(name);
  if (it == m.dvars.end()) throw usage_error(unknown_dvar(m, name));
  if (!std::isfinite(value)) throw usage_error("design variable " + name + ": value is not finite");
  std::string bad = bounds_problem(it->second, value);
  if (!bad.empty()) throw usage_error("design variable " + bad);
  Machine work = m;  // m stays as it was if the new machine does not validate
  write_dvar(work, it->second, value);
  try {
    revalidate(work);
  } catch (const Error& e) {
    throw usage_error("design variable " + name + " = " + num(value) +
                      " makes the machine invalid: " + e.what());
  }
  m = std::move(work);
}

namespace {

/// One write of a set of values: a design variable's, or a JSON pointer's (a name starting '/').
struct Write {
  std::string name;
  double value;
};

void apply_write(Machine& m, const Write& w) {
  if (w.name[0] == '/') write_pointer(m, w.name, w.value);
  else write_dvar(m, m.dvars.at(w.name), w.value);
}

/// Revalidates m after `writes`; if it fails, names the first write after which m no longer
/// validates (found by applying them again one at a time from `before`): "name = value makes
/// the machine invalid: why".
void revalidate_after(Machine& m, const Machine& before, const std::vector<Write>& writes,
                      const std::function<Error(const std::string&)>& make_error) {
  try {
    revalidate(m);
    return;
  } catch (const Error& all) {
    Machine step = before;
    for (const Write& w : writes) {
      apply_write(step, w);
      try {
        revalidate(step);
      } catch (const std::exception& e) {  // an intermediate state is not validated otherwise
        throw make_error(w.name + " = " + num(w.value) + " makes the machine invalid: " + e.what());
      }
    }
    throw make_error(std::string("these values make the machine invalid: ") + all.what());
  }
}

}  // namespace

void set_dvars(Machine& m, const std::vector<std::string>& names, const std::vector<double>& values) {
  if (names.size() != values.size()) throw Error(ExitCode::software, "set_dvars: as many values as names");
  Machine work = m;
  std::vector<Write> writes;
  for (size_t i = 0; i < names.size(); ++i) {
    auto it = work.dvars.find(names[i]);
    if (it == work.dvars.end()) throw usage_error(unknown_dvar(work, names[i]));
    if (!std::isfinite(values[i])) throw usage_error("design variable " + names[i] + ": value is not finite");
    std::string bad = bounds_problem(it->second, values[i]);
    if (!bad.empty()) throw usage_error("design variable " + bad);
    write_dvar(work, it->second, values[i]);
    writes.push_back({names[i], values[i]});
  }
  revalidate_after(work, m, writes, [](const std::string& why) { return usage_error("design variable " + why); });
  m = std::move(work);
}

void apply_sets(Machine& m, const std::vector<std::string>& assignments) {
  if (assignments.empty()) return;
  Machine work = m;
  std::vector<Write> writes;
  for (const auto& a : assignments) {
    std::string where = "--set '" + a + "': ";
    size_t eq = a.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == a.size())
      throw usage_error("--set '" + a + "': expected NAME=VALUE");
    std::string name = a.substr(0, eq), text = a.substr(eq + 1);
    double value = 0;
    if (!parse_value(text, value))
      throw usage_error(where + "'" + text + "' is not a finite number");
    if (name[0] == '/') {
      std::string bad = pointer_problem(work, name);
      if (!bad.empty()) throw usage_error(where + bad);
      write_pointer(work, name, value);
      writes.push_back({name, value});
      continue;
    }
    auto it = work.dvars.find(name);
    if (it == work.dvars.end()) throw usage_error(where + unknown_dvar(work, name));
    std::string bad = bounds_problem(it->second, value);
    if (!bad.empty()) throw usage_error(where + bad);
    write_dvar(work, it->second, value);
    writes.push_back({name, value});
  }
  revalidate_after(work, m, writes, [](const std::string& why) { return usage_error("--set " + why); });
  m = std::move(work);
}

void apply_dvars_file(Machine& m, const std::string& path) {
  json values = read_json(path);
  std::string file = message_name(path);
  if (!values.is_object())
    throw data_error(file, 0,
                     "expected a JSON object of design-variable values {\"name\": number}");
  Machine work = m;
  std::vector<Write> writes;
  for (const auto& item : values.items()) {
    const std::string& name = item.key();
    std::string where = name.size() && name[0] == '/' ? name : "/" + name;
    const json& v = item.value();
    if (!v.is_number()) throw data_error(file, 0, where + ": expected a number");
    double value = v.get<double>();
    if (!std::isfinite(value)) throw data_error(file, 0, where + ": not a finite number");
    if (!name.empty() && name[0] == '/') {
      std::string bad = pointer_problem(work, name);
      if (!bad.empty()) throw data_error(file, 0, where + ": " + bad);
      write_pointer(work, name, value);
      writes.push_back({name, value});
      continue;
    }
    auto it = work.dvars.find(name);
    if (it == work.dvars.end()) throw data_error(file, 0, where + ": " + unknown_dvar(work, name));
    std::string bad = bounds_problem(it->second, value);
    if (!bad.empty()) throw data_error(file, 0, where + ": " + bad);
    write_dvar(work, it->second, value);
    writes.push_back({name, value});
  }
  revalidate_after(work, m, writes, [&file](const std::string& why) { return data_error(file, 0, why); });
  m = std::move(work);
}

}  // namespace turnfit
