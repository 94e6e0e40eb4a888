// turnfit-diagnose as a library (see diagnose_app.hpp).
#include "turnfit/diagnose/diagnose_app.hpp"

#include <cmath>
#include <filesystem>
#include <iostream>
#include <memory>
#include <sstream>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/optimize/localsearch_app.hpp"
#include "turnfit/optimize/problem_file.hpp"
#include "turnfit/plot/figure.hpp"

namespace turnfit {

using nlohmann::json;

void add_diagnose_options(CLI::App& app, DiagnoseOptions& o) {
  app.description(
      "Diagnoses a turn-pattern mismatch (turnfit-problem(5): machine, measured peaks, variables): fits the\n"
      "design variables, estimates the noise from the residual itself, locates where the residual departs\n"
      "from noise and how (offset, trend, oscillation at the radial tune, step, outliers), screens every\n"
      "effect of turnfit-machine(5) EFFECTS that no variable represents, refits the strongest, selects by\n"
      "BIC and held-out turns, and reports what is missing (turnfit-diagnosis(5)) with detection limits.");
  app.add_option("problem", o.problem, "Turn-pattern problem file (turnfit-problem/1 with a machine)")->required();
  app.add_option("--start", o.start,
                 "Start of the base fit: a dvars file {name: value}, a turnfit-nsga front or population log "
                 "(default: the machine's values)");
  app.add_option("--pick", o.pick, "Design of a front or log to start from: linf or sum")
      ->check(CLI::IsMember({"linf", "sum"}));
  app.add_option("--effects", o.effects,
                 "Effect types to try: all (default) or a comma list of field-harmonic, sector-strength, "
                 "trimcoil-sectors, gap-bow, voltage-tilt, probe-offset, injection-offset");
  app.add_option("--markdown", o.markdown, "Write the report for people (Markdown) here");
  app.add_option("--machine-out", o.machine_out,
                 "Write the machine with the effects found and the fitted design variables here");
  app.add_option("--figures", o.figures,
                 "Write figures here (PNG with data and gnuplot script): residuals before and after, "
                 "each effect's signature");
  app.add_option("--margin", o.settings.margin,
                 "Chi2 an effect must gain beyond BIC's k ln N (default 10: look-elsewhere over the catalogue)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_option("--max-effects", o.settings.max_effects, "Effects selected at most (default 4)")
      ->check(CLI::Range(1, 20));
  app.add_option("--refits", o.settings.refits, "Candidates refitted nonlinearly per round (default 3)")
      ->check(CLI::Range(1, 50));
  app.add_option("--siblings", o.settings.siblings,
                 "Also refit up to this many other instances of a refitted candidate's type (other sectors, "
                 "cavities, coil groups) whose linear screen gains at least --sibling-fraction of its gain "
                 "(default 6; 0: none)")
      ->check(CLI::Range(0, 50));
  app.add_option("--sibling-fraction", o.settings.sibling_fraction,
                 "See --siblings (default 0.5)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--from-start", o.settings.from_start_shortfall,
                 "Round 1: fit a candidate again from the machine's values when its refit from the fit gains less "
                 "than this fraction of its linear screen (default 0.9; 0: never)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--extra-refits", o.settings.extra_refits,
                 "Round 1: refit up to this many more candidates, in the screen's order, while the best refit "
                 "gains less than --screen-trust of the next one's linear screen (default 4; 0: never)")
      ->check(CLI::Range(0, 50));
  app.add_option("--screen-trust", o.settings.screen_trust, "See --extra-refits (default 0.5)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--whole-fits", o.settings.whole_fits,
                 "Round 1: when two or more refits gain at least --whole-fraction of the round's best gain, fit up "
                 "to this many of them from the machine's values too, the best first (default 10; 0: never)")
      ->check(CLI::Range(0, 100));
  app.add_option("--whole-fraction", o.settings.whole_fraction, "See --whole-fits (default 0.7)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--challengers", o.settings.challengers,
                 "Round 1: when a fit from the machine's values comes within --challenge-fraction of the round's "
                 "best gain, fit up to this many refits within that fraction from the machine's values too "
                 "(default 4; 0: never)")
      ->check(CLI::Range(0, 50));
  app.add_option("--challenge-fraction", o.settings.challenge_fraction, "See --challengers (default 0.1)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--neighbours", o.settings.neighbour_refits,
                 "Refit up to this many unrefitted ring neighbours (sectors k - 1 and k + 1) of the sectors whose "
                 "refit comes within --neighbour-fraction of the round's best gain (default 2; 0: never)")
      ->check(CLI::Range(0, 50));
  app.add_option("--neighbour-fraction", o.settings.neighbour_fraction, "See --neighbours (default 0.1)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--polish-passes", o.settings.polish_passes,
                 "Take a fit that ran out of iterations on from where it stopped, at most this many times: the "
                 "state before each screen, the null refits, the elimination fits, and the refits within 30 in chi2 of a round's "
                 "best or short of --screen-trust of their screen (default 3; 0: never)")
      ->check(CLI::Range(0, 20));
  app.add_option("--scan-noise", o.scan_noise,
                 "The probe drive's correlated error, rms and correlation length along the wire's travel: "
                 "DRIVE_MM or DRIVE_MM,CORR_MM (default corr 10 mm; overrides the problem's scan_noise; 0: the "
                 "turns independent)");
  app.add_option("--folds", o.settings.folds, "Interleaved held-out folds (default 5)")->check(CLI::Range(2, 50));
  app.add_option("--limit-checks", o.settings.limit_checks,
                 "Sizes at which each candidate's linear detection limit is checked by fitting the variables to the "
                 "base model with the effect at that size (default 0: linear limits only; each size costs two fits)")
      ->check(CLI::Range(0, 10));
  app.add_option("--weak-prior-centre", o.weak_prior_centre,
                 "Where the fits hold the weak prior of variables without a problem prior: machine (the machine's "
                 "values, as the linear screen does; default) or start (each fit's start, localsearch's rule)")
      ->check(CLI::IsMember({"start", "machine"}));
  app.add_option("--measured-at", o.measured_at,
                 "I=PEAKS[,PEAKS...]: the machine's turns measured at beam current I [uA] (repeatable; two or more "
                 "make space charge a candidate, scored on what changes with the current)")
      ->allow_extra_args(false);
  app.add_option("--sc-particles", o.sc_particles, "Bunch tracked for the space-charge signature (default 2000)")
      ->check(CLI::Range(16, 10000000));
  app.add_option("--sc-grid", o.sc_grid, "Solver grid of the space-charge signature (default 16x16x16)");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kThreads);
}

std::vector<std::string> parse_effect_types(const std::string& spec) {
  if (spec == "all" || spec.empty()) return {};
  std::vector<std::string> out;
  std::stringstream ss(spec);
  std::string t;
  const auto& known = catalogue_types();
  while (std::getline(ss, t, ',')) {
    if (std::find(known.begin(), known.end(), t) == known.end()) {
      std::string list;
      for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
      throw usage_error("--effects: unknown effect type '" + t + "' (known: all, " + list + ")");
    }
    if (std::find(out.begin(), out.end(), t) == out.end()) out.push_back(t);
  }
  if (out.empty()) throw usage_error("--effects: give all or effect types separated by commas");
  return out;
}

namespace {

std::string shown(const std::string& path) { return path == "-" ? "<stdin>" : path; }

json jnum(double v) { return std::isfinite(v) ? json(v) : json(nullptr); }

json figures_json(const FitFigures& f) {
  return {{"linf_mm", jnum(f.linf_mm)},
          {"rms_mm", jnum(f.rms_mm)},
          {"chi2", jnum(f.chi2)},
          {"dof", jnum(f.dof)},
          {"chi2_per_dof", jnum(f.chi2_per_dof)},
          {"held_out_chi2_per_point", jnum(f.held_out_chi2_per_point)},
          {"held_out_rms_mm", jnum(f.held_out_rms_mm)},
          {"points", f.points}};
}

std::string num(const json& j, int digits = 3) {
  if (!j.is_number()) return "-";
  return cli::fmt(j.get<double>(), digits);
}

}  // namespace

json diagnosis_report(const TurnPatternProblem& p, const Diagnosis& d, const std::string& start, bool provenance) {
  json j;
  j["format"] = "turnfit-diagnosis/1";
  if (provenance) j["provenance"] = cli::provenance();
  j["problem"] = p.file();
  j["machine"] = p.machine().path;
  j["start"] = start.empty() ? "the machine's values" : shown(start);
  j["verdict"] = d.verdict;
  j["effects"] = d.effects;
  j["ambiguous"] = d.ambiguous;
  j["overdispersion"] = d.overdispersion;
  if (!d.uncertainty.is_null()) j["uncertainty"] = d.uncertainty;
  json located = json::array();
  for (const auto& f : d.located_before.findings) located.push_back(f);
  j["located"] = located;
  j["located_after"] = d.located_after.findings;
  j["candidates"] = d.candidates;
  j["not_candidates"] = d.not_candidates;
  j["before"] = figures_json(d.before);
  j["after"] = figures_json(d.after);
  json noise = json::object();
  for (size_t k = 0; k < d.noise.probes.size(); ++k)
    noise[d.noise.probes[k]] = {{"scatter_mm", d.noise.scatter_mm[k]},
                                {"peak_trust", d.noise.trust[k]},
                                {"second_differences", d.noise.differences[k]},
                                {"source", "the residual's second differences along consecutive turns: sigma^2 = "
                                           "scatter^2 + (peak_trust r_err_mm)^2"}};
  size_t outliers = 0;
  for (unsigned char o : d.noise.outlier) outliers += o != 0;
  j["noise"] = {{"probes", noise}, {"outliers", outliers}, {"scatter_by_round_mm", d.noise_rounds},
                {"before_chi2_first_noise", d.before_first_noise_chi2}};
  if (d.noise.scan.active())
    j["noise"]["scan_noise"] = {{"drive_mm", d.noise.scan.drive_mm},
                                {"corr_mm", d.noise.scan.corr_mm},
                                {"source", "given (the problem's scan_noise or --scan-noise): each probe's turns "
                                           "share drive_mm^2 exp(-|dr| / corr_mm) beside sigma^2"}};
  // The base fit: localsearch's least squares with its own sigma, then refitted with the noise.
  json base = {{"evaluations", d.base_fit.evaluations},
               {"wall_s", d.base_fit.wall_s},
               {"chi2_dof_localsearch", jnum(d.base_fit.chi2_dof)},
               {"linf_mm", jnum(d.base_fit.after.linf_mm)},
               {"rms_mm", jnum(d.base_fit.after.rms_mm)},
               {"sigma_source", d.base_fit.sigma_source}};
  j["base_fit"] = base;
  json vars = json::object(), before = json::object();
  for (size_t k = 0; k < d.x_after.size(); ++k) {
    vars[p.variables()[k].name] = d.x_after[k];
    before[p.variables()[k].name] = d.x_base[k];
  }
  j["dvars_before"] = before;
  j["dvars_after"] = vars;
  j["rounds"] = d.rounds;
  j["eliminations"] = d.eliminations;
  j["evaluations"] = d.evaluations;
  j["wall_s"] = d.wall_s;
  j["limit_checks"] = {{"evaluations", d.limit_check_designs}, {"wall_s", d.limit_check_wall_s}};
  j["weak_prior_centre"] = d.weak_prior_at_machine ? "machine" : "start";
  return j;
}

std::string diagnosis_markdown(const TurnPatternProblem& p, const json& r) {
  std::ostringstream md;
  md << "# Diagnosis of " << p.file() << "\n\n";
  const std::string v = r["verdict"];
  md << "**Verdict: " << v << "**";
  if (v == "nothing-missing")
    md << ": after the fit of the design variables the residual is consistent with its noise, and no effect "
          "of the catalogue would gain enough to earn its parameters.";
  else if (v == "missing-physics") {
    const size_t n = r["effects"].size() +
                     (r.contains("space_charge") && r["space_charge"]["verdict"] == "named" ? 1 : 0);
    md << ": " << n << " effect" << (n == 1 ? "" : "s") << " the model lacks, named below"
       << (r["effects"].empty() ? "." : ", modelled and refitted.");
  }
  else
    md << ": the residual is significant, but no effect of the catalogue explains it. Where it lies is below.";
  md << "\n\n";

  md << "## Fit before and after\n\n| | worst turn [mm] | RMS [mm] | chi2/dof | held-out RMS [mm] |\n|---|---|---|---|---|\n";
  for (const char* k : {"before", "after"})
    md << "| " << k << " | " << num(r[k]["linf_mm"]) << " | " << num(r[k]["rms_mm"]) << " | "
       << num(r[k]["chi2_per_dof"]) << " | " << num(r[k]["held_out_rms_mm"]) << " |\n";
  md << "\nNoise, estimated from the residual's second differences (peak uncertainties added in quadrature):";
  for (auto it = r["noise"]["probes"].begin(); it != r["noise"]["probes"].end(); ++it)
    md << " " << it.key() << " " << num(it.value()["scatter_mm"]) << " mm (peak uncertainties times "
       << num(it.value()["peak_trust"], 2) << ");";
  md << " " << r["noise"]["outliers"] << " single outlier(s) left out.";
  if (r["noise"].contains("scan_noise"))
    md << " Beside it, the probe drive's error given, " << num(r["noise"]["scan_noise"]["drive_mm"])
       << " mm correlated over " << num(r["noise"]["scan_noise"]["corr_mm"])
       << " mm: every chi2 here is taken with the turns' whole covariance.";
  md << "\n\n";

  if (r.contains("space_charge")) {
    const json& c = r["space_charge"];
    md << "## Space charge (measurements at " << c["measurements"].size() << " currents)\n\n**"
       << c["verdict"].get<std::string>() << "**: " << c["reason"].get<std::string>()
       << ". The turns' widths squared change with the current by alpha = " << num(c["alpha"], 3) << " +- "
       << num(c["alpha_sigma"], 2) << " times what the bunch's own field gives them (the model's largest change "
       << num(c["signature_max_mm2"], 3) << " mm^2); chi2 gain " << num(c["gain"], 3) << " against the threshold "
       << num(c["threshold"], 3) << "; the model's space charge alone would gain " << num(c["gain_at_model"], 3)
       << ". The turns' positions: alpha " << num(c["centroids"]["alpha"], 3) << " +- "
       << num(c["centroids"]["alpha_sigma"], 2) << ", gain " << num(c["centroids"]["gain"], 3)
       << " (the model's own would gain " << num(c["centroids"]["gain_at_model"], 3) << ").\n\n";
  }
  if (!r["effects"].empty()) {
    md << "## Missing physics\n\n";
    for (const auto& e : r["effects"]) {
      md << "- **" << e["label"].get<std::string>() << "**" << (e["ambiguous"].get<bool>() ? " (ambiguous, see below)" : "")
         << ": ";
      std::string sep;
      for (auto it = e["parameters"].begin(); it != e["parameters"].end(); ++it) {
        md << sep << it.key() << " = ";
        if (it.value().is_number()) {
          md << num(it.value(), 4);
          if (e["sigma"].contains(it.key())) md << " +- " << num(e["sigma"][it.key()], 2);
        } else {
          md << json_text(it.value());
        }
        sep = ", ";
      }
      md << "; delta chi2 " << num(e["delta_chi2"], 4) << ", delta BIC " << num(e["delta_bic"], 4)
         << ", held-out gain " << num(e["held_out_gain"], 4) << ".\n";
      if (e.contains("bias_unseen") && !e["bias_unseen"].empty()) {
        md << "  What an effect not named could move, one at a time at its detection limit:";
        std::string sep2 = " ";
        for (auto it = e["bias_unseen"].begin(); it != e["bias_unseen"].end(); ++it) {
          const json& b = it.value();
          md << sep2 << it.key() << " by " << num(b["shift"], 2) << " (" << b["from"].get<std::string>() << ")";
          sep2 = "; ";
        }
        md << ".\n";
      }
      json entry = e["parameters"];
      entry["type"] = e["type"];
      md << "  Machine-file entry: `" << json_text(entry) << "`\n";
    }
    md << "\n";
  }
  if (!r["ambiguous"].empty()) {
    md << "## Ambiguous\n\nThese explain the residual about as well (delta BIC within 6";
    if (r.value("overdispersion", 1.0) > 1)
      md << ", every chi2 divided by the final model's chi2/dof " << num(r["overdispersion"], 4);
    md << "):\n\n";
    for (const auto& a : r["ambiguous"]) {
      md << "- " << a["selected"].get<std::string>() << " against";
      for (const auto& c : a["effects"]) md << " " << c["label"].get<std::string>() << " (delta BIC " << num(c["delta_bic"], 4) << ");";
      md << "\n";
    }
    md << "\n";
  }
  if (r.contains("eliminations") && !r["eliminations"].empty()) {
    md << "## Each effect taken out again\n\nThe others refitted without it; it stays when the chi2 they lose "
          "(divided by the whole model's chi2/dof when that exceeds 1) earns its parameters:\n\n";
    for (const auto& e : r["eliminations"])
      md << "- " << e["label"].get<std::string>() << ": chi2 up by " << num(e["delta_chi2"], 4) << " (must earn "
         << num(e["threshold"], 3) << ")" << (e["dropped"].get<bool>() ? ": taken out" : "") << "\n";
    md << "\n";
  }
  md << "## Where the residual lies (after the base fit)\n\n";
  size_t shown_n = 0;
  for (const auto& f : r["located"]) {
    if (f["kind"] == "overall") {
      md << "- overall: chi2 " << num(f["chi2"], 4) << " on " << num(f["dof"], 4) << " degrees of freedom (p = "
         << num(f["p_value"], 2) << ")" << (f["significant"].get<bool>() ? ", significant" : ", consistent with noise")
         << "\n";
      continue;
    }
    if (!f.contains("text") || !f.value("significant", false)) continue;
    md << "- " << f["probe"].get<std::string>() << ": " << f["text"].get<std::string>() << " (delta chi2 "
       << num(f.contains("delta_chi2") ? f["delta_chi2"] : f["chi2"], 4) << ")\n";
    ++shown_n;
  }
  if (shown_n == 0) md << "- no offset, trend, oscillation, step or region beyond the noise\n";
  for (const auto& f : r["located"])
    if (f["kind"] == "outlier")
      md << "- " << f["probe"].get<std::string>() << ": " << f["text"].get<std::string>() << "\n";
  md << "\n";

  // Detection limits, per type: the smallest and largest over the type's instances.
  md << "## What was checked, and what would have been seen\n\n"
        "Detection limit: the size whose signature, after the design variables take up what they can, "
        "would pass the selection threshold (k ln N + margin in chi2) at this noise, in the model linearized at "
        "the base fit; \"fits\" where it was checked by fitting the variables to the base model with the effect "
        "at that size (--limit-checks).\n\n"
        "| candidate | status | delta chi2 | limit | taken up by |\n|---|---|---|---|---|\n";
  size_t rows = 0;
  for (const auto& c : r["candidates"]) {
    const std::string type = c["type"];
    // Every candidate but the long lists of coil groups and bump places, which show their best.
    if ((type == "trimcoil-sectors" || type == "field-harmonic") && rows > 40) continue;
    std::string lim;
    for (auto it = c["detection_limit"].begin(); it != c["detection_limit"].end(); ++it)
      lim += (lim.empty() ? "" : ", ") + it.key() + " " + num(it.value(), 2);
    std::string by;
    for (const auto& b : c["absorbed_by"])
      by += (by.empty() ? "" : ", ") + b["variable"].get<std::string>() + " (" + num(b["sigmas"], 2) + " sigma)";
    md << "| " << c["label"].get<std::string>() << " | " << c["status"].get<std::string>() << " | "
       << num(c["delta_chi2"], 3) << " | " << lim << " | " << by << " |\n";
    ++rows;
  }
  md << "\n";
  if (!r["not_candidates"].empty()) {
    md << "Not candidates (a design variable represents them, or they leave no trace in radial turns):\n\n";
    for (const auto& n : r["not_candidates"]) {
      md << "- " << n["type"].get<std::string>();
      if (!n["instance"].empty()) md << " " << json_text(n["instance"]);
      md << ": " << n["reason"].get<std::string>();
      if (!n["variables"].empty()) {
        md << " (";
        std::string sep;
        for (const auto& x : n["variables"]) md << sep << x.get<std::string>(), sep = ", ";
        md << ")";
      }
      md << "\n";
    }
  }
  md << "\n" << r["evaluations"] << " designs simulated in " << num(r["wall_s"], 3) << " s.\n";
  return md.str();
}

json relocate_machine_paths(json doc, const std::string& from_dir, const std::string& out_path) {
  namespace fs = std::filesystem;
  if (out_path == "-" || out_path.empty()) return doc;
  const fs::path to = fs::absolute(fs::path(out_path)).parent_path();
  const fs::path from = fs::absolute(from_dir.empty() ? fs::path(".") : fs::path(from_dir));
  auto fix = [&](json& v) {
    if (!v.is_string() || v.get<std::string>().empty()) return;
    const fs::path p(v.get<std::string>());
    if (p.is_absolute()) return;
    const fs::path abs = (from / p).lexically_normal();
    const fs::path rel = abs.lexically_relative(to);
    v = rel.empty() ? abs.string() : rel.string();
  };
  if (doc.contains("field") && doc["field"].contains("map")) fix(doc["field"]["map"]);
  for (const char* list : {"cavities", "trimcoils"})
    if (doc.contains(list) && doc[list].is_array())
      for (auto& e : doc[list])
        for (const char* k : {"profile", "table"})
          if (e.contains(k)) fix(e[k]);
  if (doc.contains("bunch") && doc["bunch"].contains("file")) fix(doc["bunch"]["file"]);
  return doc;
}

namespace {

/// Residuals before and after per probe, with the noise band and the located regions; and each
/// effect's signature beside the residual it explains.
void write_figures(const TurnPatternProblem& p, const Diagnosis& d, const json& report, const std::string& dir,
                   bool quiet) {
  std::filesystem::create_directories(dir);
  const TurnTable& meas = p.measured();
  Figure fig;
  fig.kind = "diagnose";
  fig.title = "turnfit-diagnose: model minus measurement, before and after (" + report["verdict"].get<std::string>() + ")";
  for (size_t pr = 0; pr < meas.probes.size(); ++pr) {
    Panel panel;
    panel.title = meas.probes[pr];
    panel.xlabel = "turn";
    panel.ylabel = "model - measured [mm]";
    panel.lines.push_back({false, 0, "", 1, false});
    for (const auto& f : report["located"])
      if (f.value("probe", "") == meas.probes[pr] && f.value("significant", false) && f.contains("turns") &&
          f["kind"] == "region") {
        panel.lines.push_back({true, f["turns"][0].get<double>() - 0.5, "", 2, false});
        panel.lines.push_back({true, f["turns"][1].get<double>() + 0.5, "", 2, false});
      }
    fig.panels.push_back(panel);
    Series band, before, after;
    band.panel = before.panel = after.panel = static_cast<int>(pr);
    band.name = "noise (1 sigma)";
    band.style = SeriesStyle::band;
    band.color = -1;
    before.name = "after the design variables' fit";
    before.style = SeriesStyle::points;
    before.color = 0;
    before.point = 6;
    after.name = d.effects.empty() ? "" : "with the effects found";
    after.style = SeriesStyle::points;
    after.color = 1;
    auto [b, e] = meas.probe_range(static_cast<int>(pr));
    for (size_t i = b; i < e; ++i) {
      const double t = meas.points[i].turn;
      band.x.push_back(t), band.y.push_back(0), band.y_lo.push_back(-d.noise.sigma_mm[i]),
          band.y_hi.push_back(d.noise.sigma_mm[i]);
      if (!std::isnan(d.residual_before_mm[i])) before.x.push_back(t), before.y.push_back(d.residual_before_mm[i]);
      if (!std::isnan(d.residual_after_mm[i])) after.x.push_back(t), after.y.push_back(d.residual_after_mm[i]);
    }
    fig.series.push_back(band);
    fig.series.push_back(before);
    if (!d.effects.empty()) fig.series.push_back(after);
  }
  RenderOptions ro;
  ro.quiet = quiet;
  ro.image = (std::filesystem::path(dir) / "residuals.png").string();
  render_figure(fig, ro);

  for (size_t k = 0; k < d.effects.size(); ++k) {
    Figure sf;
    sf.kind = "diagnose";
    sf.title = "effect " + std::to_string(k + 1) + ": " + d.effects[k]["label"].get<std::string>() +
               ", its signature (design variables refitted) beside the residual";
    for (size_t pr = 0; pr < meas.probes.size(); ++pr) {
      Panel panel;
      panel.title = meas.probes[pr];
      panel.xlabel = "turn";
      panel.ylabel = "[mm]";
      panel.lines.push_back({false, 0, "", 1, false});
      sf.panels.push_back(panel);
      Series res, sig;
      res.panel = sig.panel = static_cast<int>(pr);
      res.name = "residual before";
      res.style = SeriesStyle::points;
      res.point = 6;
      res.color = 0;
      sig.name = "the effect's signature";
      sig.style = SeriesStyle::lines;
      sig.color = 2;
      sig.size = 2;
      auto [b, e] = meas.probe_range(static_cast<int>(pr));
      for (size_t i = b; i < e; ++i) {
        const double t = meas.points[i].turn;
        if (!std::isnan(d.residual_before_mm[i])) res.x.push_back(t), res.y.push_back(d.residual_before_mm[i]);
        if (!std::isnan(d.signatures_mm[k][i])) sig.x.push_back(t), sig.y.push_back(d.signatures_mm[k][i]);
      }
      sf.series.push_back(res);
      sf.series.push_back(sig);
    }
    ro.image = (std::filesystem::path(dir) / ("effect-" + std::to_string(k + 1) + ".png")).string();
    render_figure(sf, ro);
  }
}

}  // namespace

int run_diagnose(const DiagnoseOptions& o) {
  const std::string out_path = o.common.output.empty() ? "-" : o.common.output;
  const int stdout_users = (out_path == "-") + (o.markdown == "-") + (o.machine_out == "-");
  if (stdout_users > 1) throw usage_error("only one of -o, --markdown and --machine-out can be stdout");
  if (o.problem == "-" && o.start == "-") throw usage_error("the problem and --start cannot both be stdin");
  DiagnoseSettings s = o.settings;
  s.types = parse_effect_types(o.effects);
  s.weak_prior_at_machine = o.weak_prior_centre == "machine";
  s.threads = cli::resolve_threads(o.common.threads);
  if (!o.common.quiet) s.log = [](const std::string& line) { std::cerr << "turnfit-diagnose: " << line << "\n"; };

  LoadedProblem lp = load_problem(o.problem, "", -1);
  auto* p = dynamic_cast<TurnPatternProblem*>(lp.problem.get());
  if (!p)
    throw usage_error(shown(o.problem) + " is not a turn-pattern problem (it names no machine): turnfit-diagnose "
                                         "diagnoses a machine against measured turns");
  if (!o.scan_noise.empty()) p->set_scan_noise(scan_noise_from_text(o.scan_noise, "--scan-noise"));
  const std::vector<double> x0 = read_start(*p, o.start, o.pick);
  {
    const TurnPatternResult r0 = p->simulate(x0);
    size_t matched = 0;
    for (unsigned char m : r0.matched) matched += m != 0;
    if (!r0.ok || matched == 0) {
      const std::string why = !r0.ok ? "the start cannot be simulated: " + r0.reason
                                     : "the start reaches no measured turn (" + r0.end.status + ")";
      if (!o.start.empty()) throw data_error(shown(o.start), 0, why);
      throw data_error(shown(o.problem), 0, "machine: " + p->machine().path + ": " + why);
    }
  }
  // Outputs are opened (an unwritable path fails at once) and released again during the
  // diagnosis, then written and committed together: a failed or killed run leaves none.
  for (const std::string& path : {out_path, o.markdown, o.machine_out})
    if (!path.empty() && path != "-") OutputFile probe(path);
  if (!o.figures.empty() && std::filesystem::exists(o.figures) && !std::filesystem::is_directory(o.figures))
    throw usage_error("--figures: " + o.figures + " exists and is not a folder");

  // Measurements at other currents, checked before the work.
  std::vector<CurrentMeasurement> at_currents;
  for (const std::string& a : o.measured_at) {
    const size_t eq = a.find('=');
    CurrentMeasurement cm;
    size_t used = 0;
    try {
      cm.current_uA = std::stod(a.substr(0, eq), &used);
    } catch (const std::exception&) {
      used = std::string::npos;
    }
    if (eq == std::string::npos || used != eq || eq + 1 >= a.size() || !(cm.current_uA >= 0) ||
        !std::isfinite(cm.current_uA))
      throw usage_error("--measured-at '" + a + "': expected I=PEAKS, a current >= 0 in uA and a peaks file");
    std::stringstream files(a.substr(eq + 1));
    std::string f;
    while (std::getline(files, f, ','))
      if (!f.empty()) cm.peaks.push_back(f);
    if (cm.peaks.empty()) throw usage_error("--measured-at '" + a + "': no peaks file");
    for (const auto& path : cm.peaks)
      if (!std::filesystem::exists(path)) throw open_error(path, "no such file");
    at_currents.push_back(cm);
  }
  if (at_currents.size() == 1)
    throw usage_error("--measured-at: one measurement has nothing to compare with (give two or more currents)");
  if (!at_currents.empty() && o.problem == "-")
    throw usage_error("--measured-at reads the problem file again for each measurement: not with a problem on stdin");
  CurrentTestSettings cts;
  cts.particles = static_cast<size_t>(o.sc_particles);
  cts.grid = sc::parse_grid(o.sc_grid);
  cts.threads = s.threads;
  cts.margin = s.margin;

  const Diagnosis d = diagnose(*p, x0, s);
  json report = diagnosis_report(*p, d, o.start, !o.common.no_provenance);
  if (!at_currents.empty()) {
    if (s.log) s.log("space charge: the signature at " + std::to_string(at_currents.size()) + " currents");
    const json pj = read_json(o.problem);
    const std::string dir = std::filesystem::absolute(o.problem).parent_path().string();
    const CurrentTest ct = space_charge_candidate(*p, pj, dir, d.x_base, at_currents, cts);
    report["space_charge"] = ct.report;
    // Named, space charge is missing physics whatever the single measurement showed.
    if (ct.named && report["verdict"] != "missing-physics") report["verdict"] = "missing-physics";
  }

  std::unique_ptr<OutputFile> rep = std::make_unique<OutputFile>(out_path);
  std::unique_ptr<OutputFile> md = o.markdown.empty() ? nullptr : std::make_unique<OutputFile>(o.markdown);
  std::unique_ptr<OutputFile> mo = o.machine_out.empty() ? nullptr : std::make_unique<OutputFile>(o.machine_out);
  rep->stream() << json_text(report, 1) << "\n";
  if (md) md->stream() << diagnosis_markdown(*p, report);
  if (mo) {
    json doc = relocate_machine_paths(d.machine_after, p->machine().dir, o.machine_out);
    doc["description"] = std::string(doc.value("description", "")) +
                         (doc.value("description", "").empty() ? "" : " ") + "Diagnosed by turnfit-diagnose (" +
                         d.verdict + ") against " + p->file() + ": design variables at the refit, effects found appended.";
    mo->stream() << json_text(doc, 1) << "\n";
  }
  if (!o.figures.empty()) write_figures(*p, d, report, o.figures, o.common.quiet);
  if (mo) mo->commit();
  if (md) md->commit();
  rep->commit();
  if (!o.common.quiet) {
    std::cerr << "turnfit-diagnose: " << report["verdict"].get<std::string>();
    for (const auto& e : d.effects) std::cerr << "; " << e["label"].get<std::string>();
    if (report.contains("space_charge"))
      std::cerr << "; space charge " << report["space_charge"]["verdict"].get<std::string>() << " (alpha "
                << cli::fmt(report["space_charge"]["alpha"].get<double>(), 3) << " +- "
                << cli::fmt(report["space_charge"]["alpha_sigma"].get<double>(), 2) << ", gain "
                << cli::fmt(report["space_charge"]["gain"].get<double>(), 3) << " against "
                << cli::fmt(report["space_charge"]["threshold"].get<double>(), 3) << ")";
    std::cerr << " (worst turn " << cli::fmt(d.before.linf_mm, 3) << " -> " << cli::fmt(d.after.linf_mm, 3)
              << " mm, chi2/dof " << cli::fmt(d.before.chi2_per_dof, 3) << " -> " << cli::fmt(d.after.chi2_per_dof, 3)
              << "; " << d.evaluations << " designs, " << cli::fmt(d.wall_s, 3) << " s)\n";
  }
  return 0;
}

}  // namespace turnfit
