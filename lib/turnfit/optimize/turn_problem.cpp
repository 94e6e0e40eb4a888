// The turn-pattern problem: machine + measured turns + design variables, evaluated in process.
#include "turnfit/optimize/turn_problem.hpp"

#include <cmath>
#include <filesystem>
#include <set>

#include "turnfit/cli/common.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/optimize/problem_keys.hpp"

namespace turnfit {

std::vector<Objective> paper_objectives() {
  return parse_objectives_spec(
      "RRI2:1-16:linf,RRL:9-31:linf,RRL:32-61:linf,RRL:62-105:linf,RRL:106-148:linf,RRL:149-182:linf");
}

TurnTable read_measured_turns(const std::vector<std::string>& paths) {
  TurnTable out;
  out.format = "peaks";
  std::vector<std::string> from;  // file of each probe
  for (const auto& path : paths) {
    const TurnTable t = turn_table_from_csv(CsvTable::read(path));
    const std::string name = path == "-" ? "<stdin>" : path;
    std::vector<int> index(t.probes.size());
    for (size_t p = 0; p < t.probes.size(); ++p) {
      if (out.probe_index(t.probes[p]) >= 0)
        throw data_error(name, 0, "probe " + t.probes[p] + " is also in " + from[static_cast<size_t>(out.probe_index(t.probes[p]))] +
                                      ": give each probe's peaks once");
      index[p] = static_cast<int>(out.probes.size());
      out.probes.push_back(t.probes[p]);
      from.push_back(name);
    }
    for (TurnPoint pt : t.points) {
      pt.probe = index[static_cast<size_t>(pt.probe)];
      out.points.push_back(std::move(pt));
    }
    out.source += (out.source.empty() ? "" : ", ") + name;
  }
  finish_turn_table(out);
  return out;
}

namespace {

std::string resolve(const std::string& dir, const std::string& path) {
  if (path == "-" || path.empty() || path.front() == '/' || dir.empty()) return path;
  return (std::filesystem::path(dir) / path).lexically_normal().string();
}

std::string known_variables(const Machine& m) {
  std::string s;
  size_t k = 0;
  for (const auto& [name, dv] : m.dvars) {
    if (k++ == 12) return s + ", ... (" + std::to_string(m.dvars.size()) + " in all)";
    s += (s.empty() ? "" : ", ") + name;
  }
  return s.empty() ? "none: the machine has no design variables" : s;
}

}  // namespace

TurnPatternProblem::TurnPatternProblem(std::string name, std::vector<double> lower, std::vector<double> upper,
                                       std::vector<std::string> names, size_t n_objectives, size_t n_constraints)
    : Problem(std::move(name), std::move(lower), std::move(upper), n_objectives, n_constraints, names),
      names_(std::move(names)) {}

std::unique_ptr<TurnPatternProblem> TurnPatternProblem::from_json(const nlohmann::json& j, const std::string& file,
                                                                  const std::string& dir) {
  ProblemKeys k{file};
  static const std::set<std::string> known = {"format",     "name",        "description", "machine",  "peaks",
                                              "variables",  "objectives",  "constraints", "sigma_mm", "reference", "bunch",
                                              "scan_noise"};
  for (auto it = j.begin(); it != j.end(); ++it)
    if (!known.count(it.key()))
      k.fail(it.key(), "unknown key in a turn-pattern problem (known: format, name, description, machine, peaks, "
                       "variables, objectives, constraints, sigma_mm, scan_noise, reference, bunch)");

  // The machine, and every file its model reads. An error in a file the problem names says
  // which key named it (the code stays: 66 for a missing file, 65 for a bad one).
  auto named_by = [&](const std::string& key, auto&& read) {
    try {
      return read();
    } catch (const Error& e) {
      throw Error(e.code(), file + ": " + key + ": " + e.what());
    }
  };
  const std::string machine_path = resolve(dir, k.text(k.need(j, "machine", ""), "machine"));
  Machine m = named_by("machine", [&] { return load_machine(machine_path); });
  if (!m.injection) k.fail("machine", machine_path + " has no injection block to track from");
  if (m.probes.empty()) k.fail("machine", machine_path + " has no probes: it records no turns");
  TrackSettings settings = machine_track_settings(m);
  if (!(settings.turns > 0))
    k.fail("machine", machine_path + ": /tracking/turns: the problem tracks the machine's turn count; give one");

  // Measured turns.
  const auto& jp = k.need(j, "peaks", "");
  std::vector<std::string> peak_files;
  if (jp.is_array()) {
    if (jp.empty()) k.fail("peaks", "an empty list");
    for (size_t i = 0; i < jp.size(); ++i) peak_files.push_back(resolve(dir, k.text(jp[i], "peaks/" + std::to_string(i))));
  } else {
    peak_files.push_back(resolve(dir, k.text(jp, "peaks")));
  }
  TurnTable measured = named_by("peaks", [&] { return read_measured_turns(peak_files); });
  if (measured.points.empty()) k.fail("peaks", "no measured turn in " + measured.source);
  for (const auto& probe : measured.probes) {
    bool have = false;
    for (const auto& p : m.probes) have = have || p.name == probe;
    if (!have) k.fail("peaks", "probe " + probe + " (" + measured.source + ") is not a probe of " + machine_path);
  }

  // Objectives and constraints.
  std::vector<Objective> objectives =
      j.contains("objectives") ? parse_objectives_json(j["objectives"], file + ": objectives") : paper_objectives();
  if (objectives.empty()) k.fail("objectives", "at least one objective");
  ObjectivePlan plan;
  try {
    plan = plan_objectives(objectives, measured);
  } catch (const Error& e) {
    k.fail("objectives", std::string(e.what()) + " (measured: " + measured.source + ")" +
                             (j.contains("objectives") ? ""
                                                       : "; the problem gives no \"objectives\", so the paper's six apply "
                                                         "(RRI2 and RRL): give objectives on the measured probes"));
  }
  bool turn_count = true;
  if (j.contains("constraints")) {
    const auto& c = j["constraints"];
    if (!c.is_array()) k.fail("constraints", "expected a list (known: \"turn-count\")");
    turn_count = false;
    for (size_t i = 0; i < c.size(); ++i) {
      const std::string name = k.text(c[i], "constraints/" + std::to_string(i));
      if (name != "turn-count")
        k.fail("constraints/" + std::to_string(i), "unknown constraint '" + name + "' (known: turn-count)");
      turn_count = true;
    }
  }

  // Variables: "paper", names, or {name, lower, upper, sigma}.
  if (!j.contains("variables")) k.fail("variables", "missing (\"paper\", a list of names, or of {name, lower, upper, sigma})");
  const auto& jv = j["variables"];
  std::vector<TurnVariable> vars;
  std::set<std::string> seen;
  auto add = [&](const std::string& name, const std::string& key) -> TurnVariable& {
    auto it = m.dvars.find(name);
    if (it == m.dvars.end())
      k.fail(key, "'" + name + "' is not a design variable of " + machine_path + " (known: " + known_variables(m) + ")");
    if (!seen.insert(name).second) k.fail(key, "'" + name + "' appears twice");
    TurnVariable v;
    v.name = name;
    v.unit = it->second.unit;
    v.lower = it->second.lower;
    v.upper = it->second.upper;
    v.start = dvar_value(m, name);
    vars.push_back(v);
    return vars.back();
  };
  if (jv.is_string()) {
    if (jv.get<std::string>() != "paper") k.fail("variables", "expected \"paper\", a list of names, or of {name, lower, upper, sigma}");
    for (const auto& [name, dv] : builtin_dvars(m)) add(name, "variables");
    if (vars.empty()) k.fail("variables", "\"paper\": " + machine_path + " has none of the paper's design variables");
  } else if (jv.is_array() && !jv.empty()) {
    for (size_t i = 0; i < jv.size(); ++i) {
      const std::string key = "variables/" + std::to_string(i);
      const auto& e = jv[i];
      if (e.is_string()) {
        add(k.text(e, key), key);
        continue;
      }
      if (!e.is_object()) k.fail(key, "expected a name or {name, lower, upper, sigma}");
      for (auto it = e.begin(); it != e.end(); ++it)
        if (it.key() != "name" && it.key() != "lower" && it.key() != "upper" && it.key() != "sigma")
          k.fail(key + "/" + it.key(), "unknown key (known: name, lower, upper, sigma)");
      if (!e.contains("name")) k.fail(key + "/name", "missing");
      TurnVariable& v = add(k.text(e["name"], key + "/name"), key + "/name");
      if (e.contains("lower")) v.lower = k.number(e["lower"], key + "/lower");
      if (e.contains("upper")) v.upper = k.number(e["upper"], key + "/upper");
      if (!(v.lower < v.upper)) k.fail(key, "lower must be below upper");
      if (e.contains("sigma")) {
        v.sigma = k.number(e["sigma"], key + "/sigma");
        if (!(v.sigma > 0)) k.fail(key + "/sigma", "must be positive");
      }
      if (v.start < v.lower || v.start > v.upper)
        k.fail(key, v.name + "'s value in the machine, " + std::to_string(v.start) + ", lies outside [lower, upper] = [" +
                        cli::fmt(v.lower) + ", " + cli::fmt(v.upper) + "]");
    }
  } else {
    k.fail("variables", "expected \"paper\", a list of names, or of {name, lower, upper, sigma}");
  }
  for (const auto& v : vars) {  // the problem's bounds are the ones set_dvars checks
    m.dvars[v.name].lower = v.lower;
    m.dvars[v.name].upper = v.upper;
  }

  // Peak-position uncertainty: a number, or one per probe.
  std::vector<double> sigma;
  if (j.contains("sigma_mm")) {
    const auto& s = j["sigma_mm"];
    sigma.assign(measured.points.size(), 0);
    if (s.is_number()) {
      const double v = k.number(s, "sigma_mm");
      if (!(v > 0)) k.fail("sigma_mm", "must be positive");
      sigma.assign(measured.points.size(), v);
    } else if (s.is_object()) {
      for (size_t p = 0; p < measured.probes.size(); ++p) {
        const std::string& probe = measured.probes[p];
        if (!s.contains(probe)) k.fail("sigma_mm/" + probe, "missing: give every measured probe's uncertainty");
        const double v = k.number(s[probe], "sigma_mm/" + probe);
        if (!(v > 0)) k.fail("sigma_mm/" + probe, "must be positive");
        auto [b, e] = measured.probe_range(static_cast<int>(p));
        for (size_t i = b; i < e; ++i) sigma[i] = v;
      }
      for (auto it = s.begin(); it != s.end(); ++it)
        if (measured.probe_index(it.key()) < 0) k.fail("sigma_mm/" + it.key(), "not a measured probe");
    } else {
      k.fail("sigma_mm", "expected a number or {probe: number}");
    }
  }

  // The probe drive's correlated error (turnfit-problem(5) "scan_noise").
  ScanNoise scan;
  if (j.contains("scan_noise")) {
    const auto& sn = j["scan_noise"];
    if (!sn.is_object()) k.fail("scan_noise", "expected {\"drive_mm\": rms, \"corr_mm\": length}");
    for (auto it = sn.begin(); it != sn.end(); ++it)
      if (it.key() != "drive_mm" && it.key() != "corr_mm")
        k.fail("scan_noise/" + it.key(), "unknown key (known: drive_mm, corr_mm)");
    scan.drive_mm = k.number(k.need(sn, "drive_mm", "scan_noise"), "scan_noise/drive_mm");
    if (scan.drive_mm < 0) k.fail("scan_noise/drive_mm", "must not be negative");
    if (sn.contains("corr_mm")) scan.corr_mm = k.number(sn["corr_mm"], "scan_noise/corr_mm");
    if (!(scan.corr_mm > 0)) k.fail("scan_noise/corr_mm", "must be positive");
  }

  // What the probes measure: the bunch's centre (default when the machine has a bunch with
  // spread) or the reference particle.
  std::vector<QuadratureNode> nodes = named_by("machine", [&] { return machine_bunch_quadrature(m); });
  std::string bunch_mode = nodes.empty() ? "reference" : "centroid";
  if (j.contains("bunch")) {
    bunch_mode = k.text(j["bunch"], "bunch");
    if (bunch_mode != "centroid" && bunch_mode != "reference")
      k.fail("bunch", "expected \"centroid\" (the bunch's centre, what a probe measures) or \"reference\" (the reference particle)");
    if (bunch_mode == "centroid" && nodes.empty())
      k.fail("bunch", "\"centroid\": " + machine_path + " has no bunch with spread (its bunch block: emittances, sigma_E_MeV, "
                      "sigma_phase_deg, or a bunch file)");
  }
  if (bunch_mode == "reference") nodes.clear();

  std::vector<double> lo, hi;
  std::vector<std::string> names;
  for (const auto& v : vars) {
    lo.push_back(v.lower);
    hi.push_back(v.upper);
    names.push_back(v.name);
  }
  const std::string name = j.contains("name") ? k.text(j["name"], "name") : std::filesystem::path(file).stem().string();
  std::unique_ptr<TurnPatternProblem> p(
      new TurnPatternProblem(name, lo, hi, names, objectives.size(), turn_count ? 1 : 0));
  p->file_ = file;
  p->files_ = named_by("machine", [&] { return read_model_files(m); });
  p->machine_ = std::move(m);
  p->settings_ = settings;
  p->vars_ = std::move(vars);
  p->measured_ = std::move(measured);
  p->objectives_ = std::move(objectives);
  p->plan_ = std::move(plan);
  p->turn_count_ = turn_count;
  p->sigma_mm_ = std::move(sigma);
  p->scan_noise_ = scan;
  p->bunch_mode_ = bunch_mode;
  p->nodes_ = std::move(nodes);
  // The centroid shift at the start, so that every evaluation predicts the bunch's centre from
  // the first; a fit recomputes it as it moves. A start that cannot be simulated keeps none
  // (the reference particle's turns): the optimizer that evaluates it says why.
  if (!p->nodes_.empty()) {
    try {
      p->shift_ = p->centroid_shift(p->start(), resolve_thread_count(0));
    } catch (const Error&) {
      p->shift_ = CentroidShift{};
    }
  }
  return p;
}

std::unique_ptr<TurnPatternProblem> TurnPatternProblem::with_machine(Machine m, std::vector<TurnVariable> vars,
                                                                     const std::vector<double>& shift_x,
                                                                     bool hold_shift) const {
  std::vector<double> lo, hi;
  std::vector<std::string> names;
  for (const auto& v : vars) {
    auto it = m.dvars.find(v.name);
    if (it == m.dvars.end()) throw Error(ExitCode::software, "with_machine: no design variable " + v.name);
    it->second.lower = v.lower;
    it->second.upper = v.upper;
    lo.push_back(v.lower);
    hi.push_back(v.upper);
    names.push_back(v.name);
  }
  if (shift_x.size() != vars.size()) throw Error(ExitCode::software, "with_machine: the shift's design has the wrong size");
  std::unique_ptr<TurnPatternProblem> p(
      new TurnPatternProblem(name(), lo, hi, names, objectives_.size(), turn_count_ ? 1 : 0));
  p->file_ = file_;
  p->files_ = files_;
  p->machine_ = std::move(m);
  p->settings_ = settings_;
  p->vars_ = std::move(vars);
  p->measured_ = measured_;
  p->objectives_ = objectives_;
  p->plan_ = plan_;
  p->turn_count_ = turn_count_;
  p->sigma_mm_ = sigma_mm_;
  p->scan_noise_ = scan_noise_;
  p->bunch_mode_ = bunch_mode_;
  if (!hold_shift) p->nodes_ = nodes_;
  p->shift_ = shift_;
  if (!p->shift_.x.empty()) p->shift_.x = shift_x;
  return p;
}

void TurnPatternProblem::shift_measured(const std::vector<double>& dr_mm) {
  if (dr_mm.size() != measured_.points.size())
    throw Error(ExitCode::software, "shift_measured: one move per measured point");
  for (size_t i = 0; i < dr_mm.size(); ++i) {
    if (!std::isfinite(dr_mm[i])) throw Error(ExitCode::software, "shift_measured: a move that is not finite");
    measured_.points[i].r_mm += dr_mm[i];
  }
}

void TurnPatternProblem::set_sigma_mm(std::vector<double> sigma) {
  if (!sigma.empty() && sigma.size() != measured_.points.size())
    throw Error(ExitCode::software, "set_sigma_mm: one sigma per measured point");
  sigma_mm_ = std::move(sigma);
}

std::vector<double> TurnPatternProblem::start() const {
  std::vector<double> x;
  for (const auto& v : vars_) x.push_back(v.start);
  return x;
}

Machine TurnPatternProblem::machine_at(const std::vector<double>& x) const {
  Machine m = machine_;
  set_dvars(m, names_, x);
  return m;
}

TurnPatternResult TurnPatternProblem::simulate(const std::vector<double>& x) const {
  return std::move(simulate_group(&x, 1)[0]);
}

std::vector<TurnPatternResult> TurnPatternProblem::simulate_many(const std::vector<std::vector<double>>& xs,
                                                                 unsigned threads) const {
  std::vector<TurnPatternResult> out(xs.size());
  const size_t n = xs.size(), lanes = static_cast<size_t>(TrackModel::kMaxLanes);
  if (n == 0) return out;
  const size_t chunks = std::min(n, std::max<size_t>(resolve_thread_count(threads), (n + lanes - 1) / lanes));
  parallel_for(chunks, threads, [&](size_t c, unsigned) {
    const size_t b = c * n / chunks, e = (c + 1) * n / chunks;
    std::vector<TurnPatternResult> r = simulate_group(xs.data() + b, e - b);
    for (size_t i = b; i < e; ++i) out[i] = std::move(r[i - b]);
  });
  return out;
}

std::vector<TurnPatternResult> TurnPatternProblem::simulate_group(const std::vector<double>* xs, size_t count) const {
  std::vector<TurnPatternResult> out(count);
  // Each design's model and reference particle; a design that cannot be built says why.
  std::vector<std::unique_ptr<TrackModel>> models;
  std::vector<const TrackModel*> model_of;
  std::vector<ParticleState> starts;
  std::vector<size_t> design;
  for (size_t i = 0; i < count; ++i) {
    try {
      if (xs[i].size() != vars_.size()) throw Error(ExitCode::software, "a design of the wrong size");
      const Machine m = machine_at(xs[i]);
      auto model = std::make_unique<TrackModel>(make_track_model(m, {}, &files_));
      starts.push_back(injection_state(effective_injection(m), m.particle.mass_MeV));
      model_of.push_back(model.get());
      models.push_back(std::move(model));
      design.push_back(i);
    } catch (const Error& e) {
      out[i].reason = e.what();
    }
  }
  std::vector<std::vector<TurnRecord>> turns(starts.size());
  std::vector<TrackEnd> ends(starts.size());
  track_particles(model_of.data(), starts.data(), starts.size(), settings_, turns.data(), ends.data());
  const auto& shift = shift_.shift_mm;
  for (size_t k = 0; k < design.size(); ++k) {
    TurnPatternResult& r = out[design[k]];
    r.end = ends[k];
    r.simulated.source = "<simulated>";
    r.simulated.format = "turns";
    for (const auto& p : models[k]->probes) r.simulated.probes.push_back(p.name);
    r.simulated.points.reserve(turns[k].size());
    for (const auto& t : turns[k]) {
      TurnPoint pt;
      pt.probe = t.probe;
      pt.turn = t.turn;
      pt.r_mm = t.r_mm;
      // The bunch's centre where the shift is known (at the shift's design every node crossed here).
      const auto p = static_cast<size_t>(t.probe), j = static_cast<size_t>(t.turn - 1);
      if (p < shift.size() && j < shift[p].size() && !std::isnan(shift[p][j])) pt.r_mm += shift[p][j];
      r.simulated.points.push_back(pt);
    }
    finish_turn_table(r.simulated);
    r.violation = match_turns(measured_, r.simulated, r.delta_mm, r.matched);
    r.objectives.resize(plan_.items.size());
    evaluate_objectives(plan_, r.delta_mm.data(), r.matched.data(), r.objectives.data());
    r.ok = true;
  }
  return out;
}

CentroidShift TurnPatternProblem::centroid_shift(const std::vector<double>& x, unsigned threads) const {
  CentroidShift out;
  out.x = x;
  if (nodes_.empty()) return out;
  const Machine m = machine_at(x);
  const TrackModel model = make_track_model(m, {}, &files_);
  const Injection inj = effective_injection(m);
  CentroidTurns ct;
  try {
    ct = centroid_turns(model, injection_state(inj, m.particle.mass_MeV), inj, m.particle.mass_MeV, nodes_, settings_,
                        threads);
  } catch (const Error& e) {
    throw Error(ExitCode::data, file_ + ": the bunch's centroid shift: " + e.what());
  }
  out.nodes = nodes_.size();
  out.shift_mm.resize(model.probes.size());
  double ss = 0;
  for (size_t c = 0; c < ct.reference.size(); ++c) {
    const TurnRecord& t = ct.reference[c];
    auto& v = out.shift_mm[static_cast<size_t>(t.probe)];
    const auto k = static_cast<size_t>(t.turn - 1);
    if (v.size() <= k) v.resize(k + 1, std::nan(""));
    if (!ct.known[c]) continue;
    const double d = ct.centre[c].r_mm - t.r_mm;
    v[k] = d;
    ss += d * d;
    out.max_abs_mm = std::max(out.max_abs_mm, std::fabs(d));
  }
  out.unknown = ct.unknown;
  out.known = ct.reference.size() - ct.unknown;
  out.rms_mm = out.known ? std::sqrt(ss / static_cast<double>(out.known)) : 0;
  return out;
}

double TurnPatternProblem::update_centroid_shift(const std::vector<double>& x, unsigned threads) {
  if (nodes_.empty()) return 0;
  CentroidShift now = centroid_shift(x, threads);
  double change = 0;
  for (size_t p = 0; p < now.shift_mm.size() && p < shift_.shift_mm.size(); ++p)
    for (size_t k = 0; k < now.shift_mm[p].size() && k < shift_.shift_mm[p].size(); ++k)
      if (!std::isnan(now.shift_mm[p][k]) && !std::isnan(shift_.shift_mm[p][k]))
        change = std::max(change, std::fabs(now.shift_mm[p][k] - shift_.shift_mm[p][k]));
  shift_ = std::move(now);
  return change;
}

Evaluation TurnPatternProblem::evaluate(const std::vector<double>& x) const {
  Evaluation e;
  const TurnPatternResult r = simulate(x);
  if (!r.ok) {
    e.ok = false;
    e.reason = r.reason;
    return e;
  }
  for (size_t i = 0; i < r.objectives.size(); ++i) {
    if (std::isnan(r.objectives[i].value)) {
      e.ok = false;
      e.reason = "objective " + objective_spec(objectives_[i]) + " matches no simulated turn (" + r.end.status + ")";
      e.f.clear();
      return e;
    }
    e.f.push_back(r.objectives[i].value);
  }
  if (turn_count_) e.g.push_back(static_cast<double>(r.violation));
  return e;
}

}  // namespace turnfit
