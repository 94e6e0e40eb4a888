// turnfit-localsearch as a library (see localsearch_app.hpp).
#include "turnfit/optimize/localsearch_app.hpp"

#include <cmath>
#include <filesystem>
#include <iostream>
#include <limits>
#include <memory>
#include <sstream>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/metrics/compare_app.hpp"
#include "turnfit/optimize/problem_file.hpp"

namespace turnfit {

void add_localsearch_options(CLI::App& app, LocalSearchOptions& o) {
  app.description(
      "Fits a turn-pattern problem's design variables (turnfit-problem(5): machine, measured peaks,\n"
      "variables, objectives) to the measured turns by bounded Levenberg-Marquardt on every turn's\n"
      "residual, from the machine's values or a --start design. Writes the best design as a dvars\n"
      "file (-o, default stdout) that turnfit-track --dvars reads; --report adds each variable's\n"
      "uncertainty, correlations and what the data do not determine.");
  app.add_option("problem", o.problem, "Turn-pattern problem file (turnfit-problem/1 with a machine)")->required();
  app.add_option("--start", o.start,
                 "Start design: a dvars file {name: value}, a turnfit-nsga front or population log "
                 "(default: the machine's values)");
  app.add_option("--pick", o.pick, "Design of a front or log to start from: linf (smallest largest objective) or sum")
      ->check(CLI::IsMember({"linf", "sum"}));
  app.add_option("--method", o.method,
                 "lm: Levenberg-Marquardt on every turn, then the minimax polish (default); coordinate: the "
                 "paper's one-variable-at-a-time search, for comparison")
      ->check(CLI::IsMember({"lm", "coordinate"}));
  app.add_option("--sweeps", o.sweeps_without_gain,
                 "coordinate: stop after this many sweeps that keep steps but lower no worst turn (default 3)")
      ->check(CLI::Range(1, 1000000));
  app.add_option("--report", o.report, "Write the fit's report (JSON) here");
  app.add_option("--residuals", o.residuals, "Write the result's residuals (turnfit-compare's CSV) here");
  app.add_option("--max-iterations", o.settings.max_iterations, "Levenberg-Marquardt iterations per pass (default 60)")
      ->check(CLI::Range(1, 100000));
  app.add_flag("--central", o.settings.central, "Central differences (twice the evaluations per Jacobian)");
  app.add_option("--fd-step", o.settings.fd_step, "Finite-difference step, fraction of each bound range (default 1e-6)")
      ->check(CLI::Range(1e-12, 0.1));
  app.add_option("--frozen-steps", o.settings.frozen_steps,
                 "Steps on one Jacobian while each lowers the cost by half of what it predicts, at most this many "
                 "in a row (default 8; 0: a new Jacobian every step)")
      ->check(CLI::Range(0, 1000));
  app.add_option("--stages", o.settings.stages,
                 "Pass 1 by turn continuation: the first third of the measured turns, two thirds, all (default 3; "
                 "1: all at once)")
      ->check(CLI::Range(1, 100));
  app.add_flag("!--no-broyden", o.settings.broyden,
               "Frozen steps keep their Jacobian as it was formed (default: Broyden's update after each)");
  app.add_option("--decrement-tolerance", o.settings.decrement_tolerance,
                 "Stop a pass where the Gauss-Newton step would lower chi2 by less than this, in chi2 per degree "
                 "of freedom (default 0.05; 0: Ceres' tolerances alone)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_flag("!--no-minimax", o.settings.minimax,
               "Skip the minimax polish (-o then gets the least-squares design)");
  app.add_option("--minimax-tolerance", o.settings.minimax_tolerance_mm,
                 "How far [mm] a polish step may raise the 2nd or 3rd largest error or the weighted l2 (default 0.01)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_option("--huber", o.settings.huber_k,
                 "With sigma estimated: down-weight a turn whose residual lies beyond K of its sigma, as Huber's "
                 "loss does, and name it in the report (default 3; 0: none)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_option("--weak-prior", o.settings.weak_prior_range,
                 "Width of the weak prior toward the start, in bound ranges (default 0.1; 0: none)")
      ->check(CLI::Range(0.0, 1e6));
  cli::add_common_options(app, o.common, cli::kOutput | cli::kThreads);
}

namespace {

nlohmann::json jnum(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); }

std::string shown(const std::string& path) { return path == "-" ? "<stdin>" : path; }

/// The best design of a front or log: feasible (violation 0), all objectives finite.
std::vector<double> pick_design(const TurnPatternProblem& p, const std::vector<nlohmann::json>& designs,
                                const std::string& file, const std::string& pick) {
  double best = std::numeric_limits<double>::infinity();
  const nlohmann::json* chosen = nullptr;
  for (const auto& design : designs) {
    const nlohmann::json* d = &design;
    if (!d->is_object() || !d->contains("x") || !d->contains("f")) continue;
    const auto& viol = (*d)["violation"];
    if (!viol.is_number() || viol.get<double>() != 0) continue;
    double worst = 0, sum = 0;
    bool finite = (*d)["f"].is_array() && !(*d)["f"].empty();
    for (const auto& f : (*d)["f"]) {
      if (!f.is_number()) {
        finite = false;
        break;
      }
      worst = std::max(worst, f.get<double>());
      sum += f.get<double>();
    }
    if (!finite) continue;
    const double key = pick == "sum" ? sum : worst;
    if (key < best) {
      best = key;
      chosen = d;
    }
  }
  if (!chosen) throw data_error(file, 0, "no feasible design with finite objectives to start from");
  const auto& x = (*chosen)["x"];
  std::vector<double> out = p.start();
  const auto& vars = p.variables();
  if (!x.is_object()) throw data_error(file, 0, "the design's \"x\" is not an object by variable name");
  for (size_t j = 0; j < vars.size(); ++j) {
    if (!x.contains(vars[j].name))
      throw data_error(file, 0, "the design has no value for " + vars[j].name + " (another problem's front?)");
    if (!x[vars[j].name].is_number()) throw data_error(file, 0, "x/" + vars[j].name + ": expected a number");
    out[j] = x[vars[j].name].get<double>();
  }
  return out;
}

}  // namespace

std::vector<double> read_start(const TurnPatternProblem& p, const std::string& path, const std::string& pick) {
  std::vector<double> x = p.start();
  if (path.empty()) return x;
  const std::string file = shown(path);
  const std::string text = read_input(path).text;
  size_t first = text.find_first_not_of(" \t\r\n");
  if (first == std::string::npos) throw data_error(file, 0, "empty start file");
  std::vector<nlohmann::json> designs;
  if (text[first] == '[') {  // an nsga front
    nlohmann::json j = parse_json(text, file);
    for (const auto& d : j) designs.push_back(d);
    x = pick_design(p, designs, file, pick);
  } else {
    // A dvars object, or a population log (one JSON object a line, with "record" keys).
    std::istringstream in(text);
    std::string line;
    nlohmann::json first_doc;
    bool log = false;
    if (std::getline(in, line)) {
      try {
        first_doc = parse_json(line, file);
        log = first_doc.is_object() && first_doc.contains("record");
      } catch (const Error&) {
        log = false;
      }
    }
    if (log) {
      std::istringstream all(text);
      while (std::getline(all, line)) {
        if (line.empty()) continue;
        nlohmann::json rec;
        try {
          rec = parse_json(line, file);  // the depth and NUL checks of every JSON input
        } catch (const Error&) {
          continue;  // a torn last line of a killed run
        }
        if (rec.is_object() && rec.value("record", "") == "eval") designs.push_back(rec);
      }
      x = pick_design(p, designs, file, pick);
    } else {
      nlohmann::json j = parse_json(text, file);
      if (!j.is_object()) throw data_error(file, 0, "expected a dvars object {name: value}, a front or a log");
      for (auto it = j.begin(); it != j.end(); ++it) {
        size_t k = 0;
        while (k < p.variables().size() && p.variables()[k].name != it.key()) ++k;
        if (k == p.variables().size())
          throw data_error(file, 0, "/" + it.key() + ": not one of the problem's variables");
        if (!it.value().is_number()) throw data_error(file, 0, "/" + it.key() + ": expected a number");
        x[k] = it.value().get<double>();
      }
    }
  }
  for (size_t j = 0; j < x.size(); ++j)
    if (!(x[j] >= p.lower()[j] && x[j] <= p.upper()[j]))
      throw data_error(file, 0, p.variables()[j].name + " = " + cli::fmt(x[j]) + " lies outside the problem's bounds [" +
                                    cli::fmt(p.lower()[j]) + ", " + cli::fmt(p.upper()[j]) + "]");
  return x;
}

namespace {

nlohmann::json summary_json(const TurnPatternProblem& p, const FitSummary& f, double chi2_dof) {
  nlohmann::json j;
  j["simulated"] = f.ok;
  if (!f.ok) {
    j["reason"] = f.reason;
    return j;
  }
  nlohmann::json objs = nlohmann::json::array();
  for (size_t i = 0; i < f.objectives.size(); ++i)
    objs.push_back({{"name", objective_spec(p.objectives()[i])}, {"value_mm", jnum(f.objectives[i])}});
  j["objectives"] = objs;
  j["linf_mm"] = jnum(f.linf_mm);
  j["mae_mm"] = jnum(f.mae_mm);
  j["rms_mm"] = jnum(f.rms_mm);
  j["chi2"] = jnum(f.chi2);
  j["chi2_dof"] = jnum(chi2_dof);
  j["matched"] = f.matched;
  j["turn_count_violation"] = f.violation;
  return j;
}

/// A design as {variable name: value}: the dvars file -o writes, and the report's minimax x.
nlohmann::json design_json(const TurnPatternProblem& p, const std::vector<double>& x) {
  nlohmann::json dv = nlohmann::json::object();
  for (size_t k = 0; k < x.size(); ++k) dv[p.variables()[k].name] = jnum(x[k]);
  return dv;
}

/// What every report starts with: format, provenance, problem, method, start.
nlohmann::json report_head(const TurnPatternProblem& p, const std::string& method, const std::string& start,
                           bool provenance) {
  nlohmann::json j;
  j["format"] = "turnfit-localsearch/1";
  if (provenance) j["provenance"] = cli::provenance();
  j["problem"] = p.file();
  j["method"] = method;
  j["start"] = start.empty() ? "the machine's values" : shown(start);
  // What the model predicts at each probe crossing: the bunch's centre or the reference particle.
  nlohmann::json b = {{"mode", p.bunch_mode()}, {"nodes", p.bunch_nodes().size()}};
  if (!p.bunch_nodes().empty()) {
    const CentroidShift& cs = p.current_centroid_shift();
    b["shift_rms_mm"] = jnum(cs.rms_mm);
    b["shift_max_mm"] = jnum(cs.max_abs_mm);
    b["crossings_without_shift"] = cs.unknown;
  }
  j["bunch"] = b;
  return j;
}

}  // namespace

nlohmann::json localsearch_report(const TurnPatternProblem& p, const LocalSearchResult& r, const std::string& start,
                                  bool provenance, double tolerance_mm) {
  nlohmann::json j = report_head(p, "lm", start, provenance);
  nlohmann::json sg = nlohmann::json::object();
  nlohmann::json trust = nlohmann::json::object();
  for (size_t q = 0; q < r.sigma_probes.size(); ++q) {
    sg[r.sigma_probes[q]] = jnum(r.sigma_mm[q]);
    trust[r.sigma_probes[q]] = jnum(q < r.peak_trust.size() ? r.peak_trust[q] : 0.0);
  }
  j["sigma_mm"] = {{"source", r.sigma_source},
                   {"per_probe", sg},
                   {"peak_uncertainties", r.peak_uncertainties},
                   {"peak_trust", trust},
                   {"passes", r.sigma_passes}};
  nlohmann::json outl = nlohmann::json::array();
  for (const auto& o : r.outliers) {
    const TurnPoint& pt = p.measured().points[o.point];
    outl.push_back({{"probe", p.measured().probes[static_cast<size_t>(pt.probe)]},
                    {"turn", pt.turn},
                    {"residual_mm", jnum(o.residual_mm)},
                    {"sigma_mm", jnum(o.sigma_mm)},
                    {"weighted_sigma_mm", jnum(o.weighted_sigma_mm)}});
  }
  j["outliers"] = outl;
  if (!p.bunch_nodes().empty()) {
    j["bunch"]["updates"] = r.centroid_updates;
    j["bunch"]["last_change_mm"] = jnum(r.centroid_change_mm);
    j["bunch"]["tracks"] = r.centroid_tracks;
  }
  const double dof = static_cast<double>(r.before.matched) - static_cast<double>(p.n_variables());
  j["before"] = summary_json(p, r.before, dof > 0 ? r.before.chi2 / dof : std::nan(""));
  j["after"] = summary_json(p, r.after, r.chi2_dof);
  if (!r.x_minimax.empty()) {
    const double dof_m = static_cast<double>(r.minimax.matched) - static_cast<double>(p.n_variables());
    nlohmann::json mm = summary_json(p, r.minimax, dof_m > 0 ? r.minimax.chi2 / dof_m : std::nan(""));
    mm["steps"] = r.minimax_steps;
    mm["evaluations"] = r.minimax_evaluations;
    mm["termination"] = r.minimax_termination;
    mm["held"] = r.minimax_held;
    mm["tolerance_mm"] = tolerance_mm;
    mm["x"] = design_json(p, r.x_minimax);
    j["minimax"] = mm;
  }
  j["evaluations"] = r.evaluations;
  j["failed_evaluations"] = r.failed_evaluations;
  j["iterations"] = r.iterations;
  j["jacobians"] = r.jacobians;
  j["kept_jacobians"] = r.kept_jacobians;
  j["frozen_steps"] = r.frozen_steps;
  j["termination"] = r.termination;
  j["wall_s"] = r.wall_s;
  j["cpu_s"] = r.cpu_s;
  // Every Levenberg-Marquardt iteration: how many evaluations a given RMS took.
  nlohmann::json trace = nlohmann::json::array();
  for (const auto& t : r.trace)
    trace.push_back({{"pass", t.pass},
                     {"iteration", t.iteration},
                     {"evaluations", t.evaluations},
                     {"cost", jnum(t.cost)},
                     {"rms_mm", jnum(t.rms_mm)},
                     {"linf_mm", jnum(t.linf_mm)},
                     {"matched", t.matched},
                     {"accepted", t.accepted},
                     {"relative_decrease", jnum(t.relative_decrease)},
                     {"trust_region_radius", jnum(t.trust_region_radius)},
                     {"fresh_jacobian", t.fresh},
                     {"decrement", jnum(t.decrement)}});
  j["trace"] = trace;
  nlohmann::json vars = nlohmann::json::array();
  for (const auto& v : r.variables)
    vars.push_back({{"name", v.name},
                    {"unit", v.unit},
                    {"start", jnum(v.start)},
                    {"value", jnum(v.value)},
                    {"sigma", jnum(v.sigma)},
                    {"sigma_robust", jnum(v.sigma_robust)},
                    {"lower", jnum(v.lower)},
                    {"upper", jnum(v.upper)},
                    {"determined", v.determined},
                    {"at_bound", v.at_bound}});
  j["variables"] = vars;
  nlohmann::json corr = nlohmann::json::array();
  for (Eigen::Index a = 0; a < r.correlation.rows(); ++a) {
    nlohmann::json row = nlohmann::json::array();
    for (Eigen::Index b = 0; b < r.correlation.cols(); ++b) row.push_back(jnum(r.correlation(a, b)));
    corr.push_back(row);
  }
  j["correlation"] = corr;
  {
    nlohmann::json rob = nlohmann::json::object();
    for (size_t q = 0; q < r.sigma_probes.size() && q < r.robust.lag1.size(); ++q)
      rob[r.sigma_probes[q]] = {{"lag1", jnum(r.robust.lag1[q])}, {"bandwidth_turns", jnum(r.robust.bandwidth[q])}};
    j["robust"] = rob;
  }
  nlohmann::json sv = nlohmann::json::array();
  for (double s : r.singular_values) sv.push_back(jnum(s));
  j["singular_values"] = sv;
  j["identifiability"] = r.identifiability;
  return j;
}

nlohmann::json coordinate_report(const TurnPatternProblem& p, const CoordinateResult& r, const std::string& start,
                                 bool provenance) {
  nlohmann::json j = report_head(p, "coordinate", start, provenance);
  j["before"] = summary_json(p, r.before, std::nan(""));
  j["after"] = summary_json(p, r.after, std::nan(""));
  auto norms = [](const CoordinateNorms& n) {
    return nlohmann::json{{"linf_mm", jnum(n.linf_mm)}, {"second_mm", jnum(n.second_mm)}, {"third_mm", jnum(n.third_mm)},
                          {"weighted_l2_mm", jnum(n.wl2_mm)}};
  };
  j["norms_before"] = norms(r.norms_before);
  j["norms_after"] = norms(r.norms_after);
  j["evaluations"] = r.evaluations;
  j["accepted_steps"] = r.accepted;
  j["sweeps"] = r.sweeps;
  j["refused_failed"] = r.refused_failed;
  j["termination"] = r.termination;
  j["wall_s"] = r.wall_s;
  j["cpu_s"] = r.cpu_s;
  nlohmann::json vars = nlohmann::json::array();
  for (size_t k = 0; k < r.x.size(); ++k) {
    const TurnVariable& v = p.variables()[k];
    vars.push_back({{"name", v.name},
                    {"unit", v.unit},
                    {"start", jnum(v.start)},
                    {"value", jnum(r.x[k])},
                    {"lower", jnum(v.lower)},
                    {"upper", jnum(v.upper)},
                    {"effect_linf_mm", jnum(k < r.effect_linf_mm.size() ? r.effect_linf_mm[k] : std::nan(""))},
                    {"effect_weighted_l2_mm", jnum(k < r.effect_wl2_mm.size() ? r.effect_wl2_mm[k] : std::nan(""))}});
  }
  j["variables"] = vars;
  return j;
}

int run_localsearch(const LocalSearchOptions& o) {
  const std::string out_path = o.common.output.empty() ? "-" : o.common.output;
  int stdout_users = (out_path == "-") + (o.report == "-") + (o.residuals == "-");
  if (stdout_users > 1) throw usage_error("only one of -o, --report and --residuals can be stdout");
  if (o.problem == "-" && o.start == "-") throw usage_error("the problem and --start cannot both be stdin");
  LoadedProblem lp = load_problem(o.problem, "", -1);
  auto* p = dynamic_cast<TurnPatternProblem*>(lp.problem.get());
  if (!p)
    throw usage_error(shown(o.problem) + " is not a turn-pattern problem (it names no machine): turnfit-localsearch "
                                         "fits a machine to measured turns");
  const std::vector<double> x0 = read_start(*p, o.start, o.pick);
  {  // A start that loses the particle is bad data; say whether the start file or the machine is at fault.
    const TurnPatternResult r0 = p->simulate(x0);
    size_t matched = 0;
    for (unsigned char m : r0.matched) matched += m != 0;
    if (!r0.ok || matched == 0) {
      const std::string of = o.start.empty() ? " (the machine's values)" : " (in " + shown(o.problem) + ")";
      const std::string why = !r0.ok ? "the start" + of + " cannot be simulated: " + r0.reason
                                     : "the start" + of + " reaches no measured turn (" + r0.end.status + ")";
      if (!o.start.empty()) throw data_error(shown(o.start), 0, why);
      throw data_error(shown(o.problem), 0, "machine: " + p->machine().path + ": " + why);
    }
  }

  LocalSearchSettings s = o.settings;
  s.threads = cli::resolve_threads(o.common.threads);
  if (!o.common.quiet && cli::stderr_is_tty())
    s.progress = [](int pass, int it, double cost) {
      std::cerr << "\rturnfit-localsearch: pass " << pass << " iteration " << it << "  cost " << cli::fmt(cost, 6)
                << "     " << std::flush;
    };
  // Every output is opened before the fit (an unwritable path fails at once) and committed
  // after it, so a failed or killed run leaves earlier files untouched. A file's temporary is
  // removed again during the fit and made anew after it, so a killed fit leaves none behind.
  std::unique_ptr<OutputFile> best = std::make_unique<OutputFile>(out_path);
  std::unique_ptr<OutputFile> report = o.report.empty() ? nullptr : std::make_unique<OutputFile>(o.report);
  std::unique_ptr<OutputFile> residuals = o.residuals.empty() ? nullptr : std::make_unique<OutputFile>(o.residuals);
  auto release = [](std::unique_ptr<OutputFile>& f) {
    if (f && !f->temp_path().empty()) f.reset();
  };
  auto reopen = [](std::unique_ptr<OutputFile>& f, const std::string& path) {
    if (!f && !path.empty()) f = std::make_unique<OutputFile>(path);
  };
  release(best), release(report), release(residuals);

  // Writes the design, the report and the residuals, then commits them together.
  auto write_outputs = [&](const std::vector<double>& x, const nlohmann::json& rep) {
    reopen(best, out_path), reopen(report, o.report), reopen(residuals, o.residuals);
    best->stream() << json_text(design_json(*p, x), 1) << "\n";
    if (report) report->stream() << json_text(rep, 1) << "\n";
    if (residuals) {
      const TurnPatternResult fin = p->simulate(x);
      CompareReport cr = make_compare_report(p->measured(), fin.simulated, p->objectives(), 0);
      write_residuals_csv(residuals->stream(), cr, !o.common.no_provenance);
    }
    if (residuals) residuals->commit();
    if (report) report->commit();
    best->commit();
  };

  if (o.method == "coordinate") {
    CoordinateSettings cs;
    cs.threads = s.threads;
    cs.max_sweeps_without_gain = o.sweeps_without_gain;
    cs.tolerance_mm = s.minimax_tolerance_mm;
    if (!o.common.quiet && cli::stderr_is_tty())
      cs.progress = [](int sweep, double linf) {
        std::cerr << "\rturnfit-localsearch: sweep " << sweep << "  worst turn " << cli::fmt(linf, 4) << " mm     "
                  << std::flush;
      };
    // The centroid shift at the start, held for the whole search (its rule compares designs).
    if (p->current_centroid_shift().x != x0) p->update_centroid_shift(x0, s.threads);
    const CoordinateResult c = coordinate_search(*p, x0, cs);
    if (cs.progress) std::cerr << "\n";
    write_outputs(c.x, !o.report.empty() ? coordinate_report(*p, c, o.start, !o.common.no_provenance) : nlohmann::json());
    if (!o.common.quiet) {
      char buf[512];
      std::snprintf(buf, sizeof buf,
                    "turnfit-localsearch: coordinate search: worst turn %.3f -> %.3f mm, RMS %.3f -> %.3f mm; %zu "
                    "evaluations, %zu sweeps, %zu steps kept, %.1f s (%s)\n",
                    c.before.linf_mm, c.after.linf_mm, c.before.rms_mm, c.after.rms_mm, c.evaluations, c.sweeps,
                    c.accepted, c.wall_s, c.termination.c_str());
      std::cerr << buf;
    }
    return 0;
  }

  const LocalSearchResult r = local_search(*p, x0, s);
  if (s.progress) std::cerr << "\n";
  // The design written: the minimax polish's (the least-squares one when it found nothing
  // better, or without it); the report has both.
  write_outputs(r.x_minimax.empty() ? r.x : r.x_minimax,
                !o.report.empty() ? localsearch_report(*p, r, o.start, !o.common.no_provenance, s.minimax_tolerance_mm)
                       : nlohmann::json());

  if (!o.common.quiet) {
    char buf[512];
    std::snprintf(buf, sizeof buf,
                  "turnfit-localsearch: worst turn %.3f -> %.3f mm, RMS %.3f -> %.3f mm, chi2/dof %.3g (sigma %s); "
                  "%zu evaluations, %d iterations, %.1f s (%s)\n",
                  r.before.linf_mm, r.after.linf_mm, r.before.rms_mm, r.after.rms_mm, r.chi2_dof,
                  r.sigma_source.rfind("problem", 0) == 0 ? "from the problem" : "estimated", r.evaluations,
                  r.iterations, r.wall_s, r.termination.c_str());
    std::cerr << buf;
    if (!r.x_minimax.empty()) {
      std::snprintf(buf, sizeof buf,
                    "turnfit-localsearch: minimax polish: worst turn %.3f -> %.3f mm, RMS %.3f mm; %d steps, %zu "
                    "evaluations (%s)\n",
                    r.after.linf_mm, r.minimax.linf_mm, r.minimax.rms_mm, r.minimax_steps, r.minimax_evaluations,
                    r.minimax_termination.c_str());
      std::cerr << buf;
    }
    for (const auto& v : r.variables)
      if (v.at_bound) cli::warn(o.common, v.name + " ended on a bound (" + cli::fmt(v.value) + ")");
    for (const auto& out : r.outliers) {
      const TurnPoint& pt = p->measured().points[out.point];
      cli::warn(o.common, p->measured().probes[static_cast<size_t>(pt.probe)] + " turn " + std::to_string(pt.turn) +
                              ": residual " + cli::fmt(out.residual_mm, 3) + " mm, " +
                              cli::fmt(std::fabs(out.residual_mm) / out.sigma_mm, 2) +
                              " sigma: down-weighted as an outlier (--huber; check its peak)");
    }
    if (r.failed_evaluations)
      cli::warn(o.common, std::to_string(r.failed_evaluations) + " evaluations could not be simulated (penalized)");
  }
  return 0;
}

}  // namespace turnfit
