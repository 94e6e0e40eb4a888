// Turn matching, error norms and objectives (seed paper Secs. "Turn Pattern Matching",
// "Aggregation of turns", "Local search").
#include "turnfit/metrics/metrics.hpp"

#include <algorithm>
#include <limits>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

struct NormInfo {
  Norm norm;
  const char* name;
};
constexpr NormInfo kNorms[] = {
    {Norm::linf, "linf"}, {Norm::l2, "l2"},   {Norm::rms, "rms"},   {Norm::mae, "mae"},
    {Norm::mse, "mse"},   {Norm::wl2, "wl2"}, {Norm::max2, "max2"}, {Norm::max3, "max3"},
};

/// The value of a pooled norm from the statistics (wl2 is not pooled: see evaluate_objectives).
double pooled_value(Norm norm, const ErrorStats& s) {
  switch (norm) {
    case Norm::linf: return s.linf_mm;
    case Norm::l2: return s.l2_mm;
    case Norm::rms: return s.rms_mm;
    case Norm::mae: return s.mae_mm;
    case Norm::mse: return s.mse_mm2;
    case Norm::max2: return s.largest_mm[1];
    case Norm::max3: return s.largest_mm[2];
    case Norm::wl2: break;
  }
  return kNaN;
}

std::string range_text(int first, int last) {
  if (first == INT_MIN && last == INT_MAX) return "";
  if (first == last) return std::to_string(first);
  return std::to_string(first) + "-" + std::to_string(last);
}

/// A non-negative whole number filling the token, or false.
bool parse_turn(std::string_view s, int* out) {
  if (s.empty() || s.size() > 9) return false;
  int v = 0;
  for (char c : s) {
    if (c < '0' || c > '9') return false;
    v = v * 10 + (c - '0');
  }
  *out = v;
  return true;
}

bool valid_probe_name(std::string_view s) {
  return !s.empty() && s.find_first_of(":+,= \t") == std::string_view::npos;
}

/// Parses "PROBE", "PROBE:N" or "PROBE:L-U"; an empty string on success, else what is wrong.
std::string parse_part(std::string_view text, TurnRange* part) {
  auto colon = text.find(':');
  std::string_view probe = text.substr(0, colon);
  if (!valid_probe_name(probe)) return "'" + std::string(probe) + "' is not a probe name";
  part->probe = std::string(probe);
  part->first_turn = INT_MIN;
  part->last_turn = INT_MAX;
  if (colon == std::string_view::npos) return {};
  std::string_view range = text.substr(colon + 1);
  auto dash = range.find('-');
  int first = 0, last = 0;
  if (dash == std::string_view::npos) {
    if (!parse_turn(range, &first)) return "'" + std::string(range) + "' is not a turn number or range L-U";
    last = first;
  } else if (!parse_turn(range.substr(0, dash), &first) || !parse_turn(range.substr(dash + 1), &last)) {
    return "'" + std::string(range) + "' is not a turn range L-U";
  }
  if (first > last) return "turn range " + std::string(range) + " is empty (first > last)";
  part->first_turn = first;
  part->last_turn = last;
  return {};
}

/// Parses one spec item; an empty string on success, else what is wrong.
std::string parse_item(std::string_view item, Objective* obj) {
  item = trim(item);
  if (item.empty()) return "empty objective";
  auto eq = item.find('=');
  if (eq != std::string_view::npos) {
    obj->name = std::string(trim(item.substr(0, eq)));
    if (obj->name.empty()) return "empty name before '='";
    item = trim(item.substr(eq + 1));
  }
  auto colon = item.rfind(':');
  if (colon == std::string_view::npos) return "expected PROBE[:TURNS]:NORM";
  std::string_view norm = item.substr(colon + 1);
  if (!parse_norm(norm, &obj->norm))
    return "unknown norm '" + std::string(norm) + "' (norms: " + norm_names() + ")";
  std::string_view parts = item.substr(0, colon);
  obj->parts.clear();
  while (true) {
    auto plus = parts.find('+');
    TurnRange part;
    std::string err = parse_part(trim(parts.substr(0, plus)), &part);
    if (!err.empty()) return err;
    obj->parts.push_back(part);
    if (plus == std::string_view::npos) break;
    parts = parts.substr(plus + 1);
  }
  if (obj->name.empty()) obj->name = objective_spec(*obj);
  return {};
}

/// "turns": N or [L, U] of a JSON part.
void json_turns(const nlohmann::json& t, TurnRange* part, const std::string& where) {
  auto turn = [&](const nlohmann::json& v) {
    if (!v.is_number_integer() || v.get<long long>() < 0 || v.get<long long>() > 999999999)
      throw data_error(where, 0, "a turn is a whole number >= 0, got " + json_text(v));
    return static_cast<int>(v.get<long long>());
  };
  if (t.is_array()) {
    if (t.size() != 2) throw data_error(where, 0, "\"turns\" is N or [first, last], got " + json_text(t));
    part->first_turn = turn(t[0]);
    part->last_turn = turn(t[1]);
    if (part->first_turn > part->last_turn)
      throw data_error(where, 0, "turn range " + json_text(t) + " is empty (first > last)");
  } else {
    part->first_turn = part->last_turn = turn(t);
  }
}

TurnRange json_part(const nlohmann::json& j, const std::string& where, bool allow_norm_keys) {
  if (!j.is_object()) throw data_error(where, 0, "expected an object, got " + json_text(j));
  TurnRange part;
  for (const auto& [key, value] : j.items()) {
    if (key == "probe") {
      if (!value.is_string() || !valid_probe_name(value.get<std::string>()))
        throw data_error(where, 0, "\"probe\" must be a probe name (or \"*\"), got " + json_text(value));
      part.probe = value.get<std::string>();
    } else if (key == "turns") {
      json_turns(value, &part, where + ".turns");
    } else if (!(allow_norm_keys && (key == "name" || key == "norm" || key == "parts"))) {
      throw data_error(where, 0, "unknown key \"" + key + "\" (known: " +
                                     (allow_norm_keys ? "name, probe, turns, parts, norm" : "probe, turns") + ")");
    }
  }
  if (part.probe.empty()) throw data_error(where, 0, "\"probe\" is missing");
  return part;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Norms

const char* norm_name(Norm norm) {
  for (const auto& n : kNorms)
    if (n.norm == norm) return n.name;
  return "?";
}

bool parse_norm(std::string_view name, Norm* norm) {
  for (const auto& n : kNorms)
    if (name == n.name) {
      *norm = n.norm;
      return true;
    }
  return false;
}

std::string norm_names() {
  std::string s;
  for (const auto& n : kNorms) s += (s.empty() ? "" : ", ") + std::string(n.name);
  return s;
}

const char* norm_unit(Norm norm) { return norm == Norm::mse ? "mm2" : "mm"; }

double ErrorAccumulator::sum_sq_mm2() const { return nan_ ? kNaN : sum_sq_; }

ErrorStats ErrorAccumulator::stats() const {
  ErrorStats s;
  s.n = n_;
  s.largest_index.fill(SIZE_MAX);
  if (n_ == 0 || nan_) {
    s.linf_mm = s.mae_mm = s.mse_mm2 = s.rms_mm = s.l2_mm = kNaN;
    s.largest_mm.fill(kNaN);
    return s;
  }
  const double n = static_cast<double>(n_);
  s.linf_mm = top_[0];
  s.mae_mm = sum_abs_ / n;
  s.mse_mm2 = sum_sq_ / n;
  s.rms_mm = std::sqrt(s.mse_mm2);
  // Paper, Sec. "Aggregation of turns": sigma = (1/N) sqrt(sum (r_m - r_s)^2).
  s.l2_mm = std::sqrt(sum_sq_) / n;
  for (int k = 0; k < 3; ++k) {
    s.largest_mm[k] = k < top_n_ ? top_[k] : kNaN;
    if (k < top_n_) s.largest_index[k] = top_index_[k];
  }
  return s;
}

ErrorStats error_stats(const double* delta_mm, size_t n) {
  ErrorAccumulator acc;
  for (size_t i = 0; i < n; ++i) acc.add(delta_mm[i], i);
  return acc.stats();
}

// ---------------------------------------------------------------------------------------------
// Turn tables

int TurnTable::probe_index(const std::string& name) const {
  for (size_t i = 0; i < probes.size(); ++i)
    if (probes[i] == name) return static_cast<int>(i);
  return -1;
}

std::pair<size_t, size_t> TurnTable::probe_range(int probe) const {
  auto lo = std::lower_bound(points.begin(), points.end(), probe,
                             [](const TurnPoint& p, int v) { return p.probe < v; });
  auto hi = std::upper_bound(lo, points.end(), probe, [](int v, const TurnPoint& p) { return v < p.probe; });
  return {static_cast<size_t>(lo - points.begin()), static_cast<size_t>(hi - points.begin())};
}

void finish_turn_table(TurnTable& table) {
  std::stable_sort(table.points.begin(), table.points.end(), [](const TurnPoint& a, const TurnPoint& b) {
    return a.probe != b.probe ? a.probe < b.probe : a.turn < b.turn;
  });
  for (size_t i = 1; i < table.points.size(); ++i) {
    const TurnPoint &a = table.points[i - 1], &b = table.points[i];
    if (a.probe == b.probe && a.turn == b.turn) {
      // Report the later line; stable sorting kept file order among equal keys.
      const TurnPoint& later = a.line > b.line ? a : b;
      const TurnPoint& first = a.line > b.line ? b : a;
      throw data_error(table.source, later.line,
                       "probe " + table.probes[static_cast<size_t>(a.probe)] + " turn " + std::to_string(a.turn) +
                           " appears twice" +
                           (first.line > 0 ? " (first at line " + std::to_string(first.line) + ")" : ""));
    }
  }
}

TurnTable turn_table_from_csv(const CsvTable& csv) {
  csv.require_columns({"probe", "turn", "r_mm"});
  TurnTable t;
  t.source = csv.name();
  t.format = csv.has_column("height") ? "peaks" : csv.has_column("s_mm") ? "turns" : "";
  const size_t cp = csv.column("probe"), ct = csv.column("turn"), cr = csv.column("r_mm");
  const bool has_flag = csv.has_column("flag");
  const size_t cf = has_flag ? csv.column("flag") : 0;
  const bool has_err = csv.has_column("r_err_mm");
  const size_t ce = has_err ? csv.column("r_err_mm") : 0;
  t.points.reserve(csv.rows());
  for (size_t row = 0; row < csv.rows(); ++row) {
    const std::string& name = csv.cell(row, cp);
    if (!valid_probe_name(name))
      throw data_error(csv.name(), csv.line(row), "column 'probe': '" + name + "' is not a probe name");
    int probe = t.probe_index(name);
    if (probe < 0) {
      probe = static_cast<int>(t.probes.size());
      t.probes.push_back(name);
    }
    TurnPoint p;
    p.probe = probe;
    const long turn = parse_long(csv.cell(row, ct), csv.name(), csv.line(row), "column 'turn'");
    if (turn < 0 || turn > 999999999)
      throw data_error(csv.name(), csv.line(row), "column 'turn': " + std::to_string(turn) + " is out of range");
    p.turn = static_cast<int>(turn);
    p.r_mm = csv.number(row, cr);
    p.line = csv.line(row);
    if (has_flag) p.flag = csv.cell(row, cf);
    if (has_err) p.r_err_mm = csv.number(row, ce);
    t.points.push_back(std::move(p));
  }
  finish_turn_table(t);
  return t;
}

// ---------------------------------------------------------------------------------------------
// Matching

size_t Comparison::violation() const {
  size_t v = 0;
  for (const auto& c : counts) v += c.missing.size() + c.extra.size();
  return v;
}

Comparison compare_turns(const TurnTable& measured, const TurnTable& simulated) {
  Comparison cmp;
  cmp.probes = measured.probes;
  for (const auto& name : simulated.probes)
    if (measured.probe_index(name) < 0) cmp.simulated_only.push_back(name);
  cmp.residuals.reserve(measured.points.size());
  for (int p = 0; p < static_cast<int>(measured.probes.size()); ++p) {
    TurnCount count;
    count.probe = measured.probes[static_cast<size_t>(p)];
    auto [mi, me] = measured.probe_range(p);
    const int q = simulated.probe_index(count.probe);
    size_t si = 0, se = 0;
    if (q >= 0) std::tie(si, se) = simulated.probe_range(q);
    count.measured = me - mi;
    count.simulated = se - si;
    // Merge join: both ranges are sorted by turn and unique.
    while (mi < me || si < se) {
      const TurnPoint* m = mi < me ? &measured.points[mi] : nullptr;
      const TurnPoint* s = si < se ? &simulated.points[si] : nullptr;
      if (m && (!s || m->turn < s->turn)) {
        count.missing.push_back(m->turn);
        ++mi;
      } else if (s && (!m || s->turn < m->turn)) {
        count.extra.push_back(s->turn);
        ++si;
      } else {
        cmp.residuals.push_back({p, m->turn, m->r_mm, s->r_mm, s->r_mm - m->r_mm, mi});
        ++count.matched;
        ++mi;
        ++si;
      }
    }
    cmp.counts.push_back(std::move(count));
  }
  return cmp;
}

size_t match_turns(const TurnTable& measured, const TurnTable& simulated, std::vector<double>& delta_mm,
                   std::vector<unsigned char>& matched) {
  delta_mm.assign(measured.points.size(), kNaN);
  matched.assign(measured.points.size(), 0);
  size_t violation = 0;
  for (int p = 0; p < static_cast<int>(measured.probes.size()); ++p) {
    auto [mi, me] = measured.probe_range(p);
    const int q = simulated.probe_index(measured.probes[static_cast<size_t>(p)]);
    size_t si = 0, se = 0;
    if (q >= 0) std::tie(si, se) = simulated.probe_range(q);
    while (mi < me && si < se) {
      const int mt = measured.points[mi].turn, st = simulated.points[si].turn;
      if (mt < st) {
        ++violation;
        ++mi;
      } else if (st < mt) {
        ++violation;
        ++si;
      } else {
        delta_mm[mi] = simulated.points[si].r_mm - measured.points[mi].r_mm;
        matched[mi] = 1;
        ++mi;
        ++si;
      }
    }
    violation += (me - mi) + (se - si);
  }
  return violation;
}

// ---------------------------------------------------------------------------------------------
// Objectives

std::string objective_spec(const Objective& obj) {
  std::string s;
  for (const auto& p : obj.parts) {
    if (!s.empty()) s += "+";
    s += p.probe;
    std::string r = range_text(p.first_turn, p.last_turn);
    if (!r.empty()) s += ":" + r;
  }
  return s + ":" + norm_name(obj.norm);
}

std::vector<Objective> parse_objectives_spec(const std::string& spec) {
  std::vector<Objective> out;
  std::string_view rest = spec;
  if (trim(rest).empty()) throw usage_error("--objectives: empty list");
  while (true) {
    auto comma = rest.find(',');
    std::string_view item = rest.substr(0, comma);
    Objective obj;
    std::string err = parse_item(item, &obj);
    if (!err.empty()) throw usage_error("--objectives: '" + std::string(trim(item)) + "': " + err);
    out.push_back(std::move(obj));
    if (comma == std::string_view::npos) break;
    rest = rest.substr(comma + 1);
  }
  return out;
}

std::vector<Objective> parse_objectives_json(const nlohmann::json& j, const std::string& where) {
  if (!j.is_array()) throw data_error(where, 0, std::string("\"objectives\" must be an array, got ") + j.type_name());
  std::vector<Objective> out;
  for (size_t i = 0; i < j.size(); ++i) {
    const std::string at = where + ": objectives[" + std::to_string(i) + "]";
    const auto& e = j[i];
    Objective obj;
    if (e.is_string()) {
      std::string err = parse_item(e.get<std::string>(), &obj);
      if (!err.empty()) throw data_error(at, 0, err);
      out.push_back(std::move(obj));
      continue;
    }
    if (!e.is_object()) throw data_error(at, 0, "expected an object or a spec string, got " + json_text(e));
    if (!e.contains("norm") || !e["norm"].is_string())
      throw data_error(at, 0, "\"norm\" is missing or not a string (norms: " + norm_names() + ")");
    if (!parse_norm(e["norm"].get<std::string>(), &obj.norm))
      throw data_error(at, 0, "unknown norm \"" + e["norm"].get<std::string>() + "\" (norms: " + norm_names() + ")");
    if (e.contains("parts")) {
      if (e.contains("probe") || e.contains("turns"))
        throw data_error(at, 0, "give either \"parts\" or \"probe\"/\"turns\", not both");
      for (const auto& [key, value] : e.items())
        if (key != "name" && key != "norm" && key != "parts")
          throw data_error(at, 0, "unknown key \"" + key + "\" (known: name, probe, turns, parts, norm)");
      const auto& parts = e["parts"];
      if (!parts.is_array() || parts.empty()) throw data_error(at, 0, "\"parts\" must be a non-empty array");
      for (size_t k = 0; k < parts.size(); ++k)
        obj.parts.push_back(json_part(parts[k], at + ".parts[" + std::to_string(k) + "]", false));
    } else {
      obj.parts.push_back(json_part(e, at, true));
    }
    if (e.contains("name")) {
      if (!e["name"].is_string() || e["name"].get<std::string>().empty())
        throw data_error(at, 0, "\"name\" must be a non-empty string");
      obj.name = e["name"].get<std::string>();
    } else {
      obj.name = objective_spec(obj);
    }
    out.push_back(std::move(obj));
  }
  if (out.empty()) throw data_error(where, 0, "\"objectives\" is empty");
  return out;
}

std::vector<Objective> objectives_from_document(const nlohmann::json& doc, const std::string& where) {
  if (doc.is_array()) return parse_objectives_json(doc, where);
  if (doc.is_object()) {
    if (!doc.contains("objectives")) throw data_error(where, 0, "no \"objectives\" key");
    return parse_objectives_json(doc["objectives"], where);
  }
  throw data_error(where, 0, "expected a problem file (object with \"objectives\") or an objectives array");
}

nlohmann::json objective_to_json(const Objective& obj) {
  auto part_json = [](const TurnRange& p) {
    nlohmann::json j = {{"probe", p.probe}};
    if (p.first_turn != INT_MIN || p.last_turn != INT_MAX) j["turns"] = {p.first_turn, p.last_turn};
    return j;
  };
  nlohmann::json j = {{"name", obj.name}};
  if (obj.parts.size() == 1) {
    j.update(part_json(obj.parts[0]));
  } else {
    j["parts"] = nlohmann::json::array();
    for (const auto& p : obj.parts) j["parts"].push_back(part_json(p));
  }
  j["norm"] = norm_name(obj.norm);
  return j;
}

ObjectivePlan plan_objectives(const std::vector<Objective>& objectives, const TurnTable& measured) {
  ObjectivePlan plan;
  for (const auto& obj : objectives) {
    ObjectivePlan::Item item;
    item.norm = obj.norm;
    for (const auto& part : obj.parts) {
      std::vector<int> probes;
      if (part.probe == "*") {
        for (int p = 0; p < static_cast<int>(measured.probes.size()); ++p) probes.push_back(p);
      } else {
        const int p = measured.probe_index(part.probe);
        if (p < 0) {
          std::string hint, have;
          size_t best = SIZE_MAX;
          for (const auto& name : measured.probes) {
            have += (have.empty() ? "" : ", ") + name;
            const size_t d = edit_distance(part.probe, name);
            if (d < best && d <= 2) {
              best = d;
              hint = "; did you mean " + name + "?";
            }
          }
          throw data_error(measured.source, 0,
                           "objective " + obj.name + ": probe " + part.probe +
                               " is not in the measured data (probes: " + (have.empty() ? "none" : have) + ")" +
                               hint);
        }
        probes.push_back(p);
      }
      size_t covered = 0;
      for (int p : probes) {
        auto [lo, hi] = measured.probe_range(p);
        auto b = measured.points.begin();
        auto first = std::lower_bound(b + static_cast<long>(lo), b + static_cast<long>(hi), part.first_turn,
                                      [](const TurnPoint& t, int v) { return t.turn < v; });
        auto last = std::upper_bound(first, b + static_cast<long>(hi), part.last_turn,
                                     [](int v, const TurnPoint& t) { return v < t.turn; });
        if (first == last) continue;  // '*' may include probes outside the range
        item.parts.push_back({static_cast<size_t>(first - b), static_cast<size_t>(last - b)});
        covered += static_cast<size_t>(last - first);
      }
      if (covered == 0) {
        std::string part_text = part.probe;
        std::string r = range_text(part.first_turn, part.last_turn);
        if (!r.empty()) part_text += ":" + r;
        throw data_error(measured.source, 0,
                         "objective " + obj.name + ": " + part_text + " covers no measured turn");
      }
      item.measured += covered;
    }
    plan.items.push_back(std::move(item));
  }
  return plan;
}

void evaluate_objectives(const ObjectivePlan& plan, const double* delta_mm, const unsigned char* matched,
                         ObjectiveValue* out) {
  for (size_t k = 0; k < plan.items.size(); ++k) {
    const auto& item = plan.items[k];
    ObjectiveValue v;
    if (item.norm == Norm::wl2) {
      // Local search (paper Sec. "Local search"): the l2 error with each part weighing the
      // same however many turns it has (16 RRI2 turns against 174 RRL turns), i.e.
      // sqrt(mean over parts of the part's mean square residual). Parts without a matched
      // turn are left out of the mean.
      double sum = 0;
      size_t parts = 0;
      for (const auto& part : item.parts) {
        ErrorAccumulator acc;
        for (size_t i = part.begin; i < part.end; ++i) {
          if (matched[i])
            acc.add(delta_mm[i], i);
          else
            ++v.missing;
        }
        if (acc.n() == 0) continue;
        v.n += acc.n();
        sum += acc.sum_sq_mm2() / static_cast<double>(acc.n());
        ++parts;
      }
      v.value = parts ? std::sqrt(sum / static_cast<double>(parts)) : kNaN;
    } else {
      ErrorAccumulator acc;
      for (const auto& part : item.parts)
        for (size_t i = part.begin; i < part.end; ++i) {
          if (matched[i])
            acc.add(delta_mm[i], i);
          else
            ++v.missing;
        }
      v.n = acc.n();
      v.value = pooled_value(item.norm, acc.stats());
    }
    out[k] = v;
  }
}

}  // namespace turnfit
