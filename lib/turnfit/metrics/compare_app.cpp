// turnfit-compare: measured against simulated turn radii, per probe and overall, with objectives.
#include "turnfit/metrics/compare_app.hpp"

#include <cmath>
#include <cstdio>
#include <memory>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

void add_compare_options(CLI::App& app, CompareOptions& o) {
  app.description(
      "Compares measured turn radii (peaks from turnfit-peakfind, or a turns table) with simulated\n"
      "ones (turns from turnfit-track), matched by probe and turn number: per probe and overall\n"
      "max |dr|, MAE, MSE, RMS, the paper's l2 norm, the largest errors, turn counts and objectives.\n"
      "dr = r_sim - r_meas of column r_mm. Exit 0 when max |dr| <= --tol and the turn counts\n"
      "agree, 1 otherwise, 64-74 on errors.");
  app.add_option("measured", o.measured, "Measured peaks.csv or turns.csv ('-' for stdin)");
  app.add_option("simulated", o.simulated, "Simulated turns.csv ('-' for stdin)");
  app.add_option("--objectives", o.objectives,
                 "Objectives: [NAME=]PROBE[:L-U][+PROBE[:L-U]...]:NORM,... (norms linf, l2, rms, mae,\n"
                 "mse, wl2, max2, max3; PROBE '*' for every probe), or @FILE: a problem file's\n"
                 "\"objectives\" array (see turnfit-compare(1), OBJECTIVES)");
  app.add_option("--tol", o.tol_mm, "Largest |r_sim - r_meas| in mm that still agrees (exit 0)")
      ->check(CLI::Range(0.0, 1e12))
      ->capture_default_str();
  app.add_option("--residuals", o.residuals, "Write probe,turn,r_meas_mm,r_sim_mm,delta_mm to this CSV");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kFormat, {"json", "text"});
}

bool CompareReport::agrees() const {
  return overall.n > 0 && comparison.violation() == 0 && overall.linf_mm <= tol_mm;
}

CompareReport make_compare_report(TurnTable measured, TurnTable simulated, std::vector<Objective> objectives,
                                  double tol_mm) {
  CompareReport r;
  r.measured = std::move(measured);
  r.simulated = std::move(simulated);
  r.objectives = std::move(objectives);
  r.tol_mm = tol_mm;
  r.comparison = compare_turns(r.measured, r.simulated);
  std::vector<ErrorAccumulator> per_probe(r.comparison.probes.size());
  ErrorAccumulator all;
  for (size_t i = 0; i < r.comparison.residuals.size(); ++i) {
    const auto& res = r.comparison.residuals[i];
    per_probe[static_cast<size_t>(res.probe)].add(res.delta_mm, i);
    all.add(res.delta_mm, i);
  }
  for (const auto& acc : per_probe) r.probe_stats.push_back(acc.stats());
  r.overall = all.stats();
  // Objectives go through the optimizer's path (plan once, match, evaluate), so what the
  // report shows is what an optimization would see.
  const ObjectivePlan plan = plan_objectives(r.objectives, r.measured);
  std::vector<double> delta;
  std::vector<unsigned char> matched;
  match_turns(r.measured, r.simulated, delta, matched);
  r.values.resize(r.objectives.size());
  evaluate_objectives(plan, delta.data(), matched.data(), r.values.data());
  return r;
}

namespace {

/// Turn numbers as compact ranges: "9-31,33,40-41".
std::string turn_list(const std::vector<int>& turns) {
  std::string s;
  for (size_t i = 0; i < turns.size();) {
    size_t j = i;
    while (j + 1 < turns.size() && turns[j + 1] == turns[j] + 1) ++j;
    if (!s.empty()) s += ",";
    s += std::to_string(turns[i]);
    if (j > i) s += (j == i + 1 ? "," : "-") + std::to_string(turns[j]);
    i = j + 1;
  }
  return s;
}

nlohmann::ordered_json number(double v) {
  return std::isfinite(v) ? nlohmann::ordered_json(v) : nlohmann::ordered_json(nullptr);
}

nlohmann::ordered_json stats_json(const ErrorStats& s, const CompareReport& r, bool with_probe) {
  nlohmann::ordered_json j;
  j["n"] = s.n;
  j["linf_mm"] = number(s.linf_mm);
  j["mae_mm"] = number(s.mae_mm);
  j["mse_mm2"] = number(s.mse_mm2);
  j["rms_mm"] = number(s.rms_mm);
  j["l2_mm"] = number(s.l2_mm);
  j["largest"] = nlohmann::ordered_json::array();
  for (int k = 0; k < 3; ++k) {
    if (s.largest_index[k] == SIZE_MAX) break;
    const auto& res = r.comparison.residuals[s.largest_index[k]];
    nlohmann::ordered_json e;
    if (with_probe) e["probe"] = r.comparison.probes[static_cast<size_t>(res.probe)];
    e["turn"] = res.turn;
    e["delta_mm"] = res.delta_mm;
    j["largest"].push_back(e);
  }
  return j;
}

std::string fixed(double v, int decimals, bool sign = false) {
  if (!std::isfinite(v)) return "-";
  char buf[64];
  std::snprintf(buf, sizeof buf, sign ? "%+.*f" : "%.*f", decimals, v);
  return buf;
}

std::string pad(const std::string& s, size_t width, bool right = true) {
  if (s.size() >= width) return s;
  return right ? std::string(width - s.size(), ' ') + s : s + std::string(width - s.size(), ' ');
}

const char* const kRank[] = {"1st", "2nd", "3rd"};

std::string where_text(const CompareReport& r, size_t index, bool with_probe) {
  if (index == SIZE_MAX) return "-";
  const auto& res = r.comparison.residuals[index];
  std::string s = "turn " + std::to_string(res.turn);
  if (with_probe) s = r.comparison.probes[static_cast<size_t>(res.probe)] + " " + s;
  return s;
}

}  // namespace

void write_errors_json(std::ostream& os, const CompareReport& r, bool provenance) {
  const Comparison& c = r.comparison;
  nlohmann::ordered_json doc;
  doc["format"] = "turnfit-errors/1";
  doc["measured"] = {{"file", r.measured.source}, {"format", r.measured.format}, {"turns", r.measured.points.size()}};
  doc["simulated"] = {
      {"file", r.simulated.source}, {"format", r.simulated.format}, {"turns", r.simulated.points.size()}};
  doc["column"] = "r_mm";
  doc["delta"] = "r_sim_mm - r_meas_mm";
  doc["tol_mm"] = r.tol_mm;
  doc["agree"] = r.agrees();
  doc["within_tol"] = r.overall.n > 0 && r.overall.linf_mm <= r.tol_mm;
  doc["turn_counts_agree"] = c.violation() == 0;
  doc["violation"] = c.violation();

  nlohmann::ordered_json overall = stats_json(r.overall, r, true);
  size_t measured = 0, simulated = 0, matched = 0, missing = 0, extra = 0;
  for (const auto& t : c.counts) {
    measured += t.measured;
    simulated += t.simulated;
    matched += t.matched;
    missing += t.missing.size();
    extra += t.extra.size();
  }
  overall["turn_count"] = {{"measured", measured}, {"simulated", simulated}, {"matched", matched},
                           {"missing", missing},   {"extra", extra},         {"agree", missing + extra == 0}};
  doc["overall"] = overall;

  nlohmann::ordered_json probes = nlohmann::ordered_json::object();
  for (size_t p = 0; p < c.probes.size(); ++p) {
    const TurnCount& t = c.counts[p];
    nlohmann::ordered_json j = stats_json(r.probe_stats[p], r, false);
    j["turn_count"] = {{"measured", t.measured},
                       {"simulated", t.simulated},
                       {"matched", t.matched},
                       {"missing", t.missing.size()},
                       {"extra", t.extra.size()},
                       {"agree", t.missing.empty() && t.extra.empty()},
                       {"missing_turns", t.missing},
                       {"extra_turns", t.extra}};
    probes[c.probes[p]] = j;
  }
  doc["probes"] = probes;
  doc["simulated_only_probes"] = c.simulated_only;

  nlohmann::ordered_json objs = nlohmann::ordered_json::array();
  for (size_t k = 0; k < r.objectives.size(); ++k) {
    const Objective& o = r.objectives[k];
    nlohmann::ordered_json j = nlohmann::ordered_json::parse(json_text(objective_to_json(o)));
    j["spec"] = objective_spec(o);
    j["value"] = number(r.values[k].value);
    j["unit"] = norm_unit(o.norm);
    j["n"] = r.values[k].n;
    j["missing"] = r.values[k].missing;
    objs.push_back(j);
  }
  doc["objectives"] = objs;
  if (provenance) doc["provenance"] = nlohmann::ordered_json::parse(json_text(cli::provenance()));
  os << json_text(doc, 1) << "\n";
}

void write_errors_text(std::ostream& os, const CompareReport& r) {
  const Comparison& c = r.comparison;
  auto describe = [](const TurnTable& t) {
    return t.source + (t.format.empty() ? "" : " (" + t.format + ")");
  };
  os << "measured:  " << describe(r.measured) << "\n"
     << "simulated: " << describe(r.simulated) << "\n"
     << "compared:  r_mm, delta = r_sim - r_meas\n";

  for (size_t p = 0; p < c.probes.size(); ++p) {
    const TurnCount& t = c.counts[p];
    const ErrorStats& s = r.probe_stats[p];
    os << "\n" << c.probes[p] << ": " << t.measured << " measured, " << t.simulated << " simulated, " << t.matched
       << " matched turns\n";
    os << "  turn   r_meas [mm]    r_sim [mm]  delta [mm]\n";
    // Walk measured and simulated turns of this probe together, so missing and extra turns
    // appear in place.
    auto [mi, me] = r.measured.probe_range(static_cast<int>(p));
    const int q = r.simulated.probe_index(c.probes[p]);
    size_t si = 0, se = 0;
    if (q >= 0) std::tie(si, se) = r.simulated.probe_range(q);
    size_t ri = 0;  // next residual of this probe
    while (ri < c.residuals.size() && c.residuals[ri].probe != static_cast<int>(p)) ++ri;
    while (mi < me || si < se) {
      const TurnPoint* m = mi < me ? &r.measured.points[mi] : nullptr;
      const TurnPoint* sp = si < se ? &r.simulated.points[si] : nullptr;
      std::string line;
      if (m && (!sp || m->turn < sp->turn)) {
        line = pad(std::to_string(m->turn), 6) + pad(fixed(m->r_mm, 3), 14) + pad("-", 14) + pad("-", 12) +
               "  missing: not simulated";
        if (!m->flag.empty()) line += " [" + m->flag + "]";
        ++mi;
      } else if (sp && (!m || sp->turn < m->turn)) {
        line = pad(std::to_string(sp->turn), 6) + pad("-", 14) + pad(fixed(sp->r_mm, 3), 14) + pad("-", 12) +
               "  extra: not measured";
        ++si;
      } else {
        line = pad(std::to_string(m->turn), 6) + pad(fixed(m->r_mm, 3), 14) + pad(fixed(sp->r_mm, 3), 14) +
               pad(fixed(sp->r_mm - m->r_mm, 3, true), 12);
        std::string note;
        for (int k = 0; k < 3; ++k)
          if (s.largest_index[k] == ri) note = std::string("  <- ") + (k == 0 ? "largest" : kRank[k]);
        if (r.tol_mm > 0 && std::fabs(sp->r_mm - m->r_mm) > r.tol_mm)  // tol 0: every mark would be noise
          note += note.empty() ? "  > tol" : ", > tol";
        if (!m->flag.empty()) note += " [" + m->flag + "]";
        line += note;
        ++mi;
        ++si;
        ++ri;
      }
      os << line << "\n";
    }
    os << "  linf " << fixed(s.linf_mm, 3) << " mm (" << where_text(r, s.largest_index[0], false) << "), 2nd "
       << fixed(s.largest_mm[1], 3) << " mm (" << where_text(r, s.largest_index[1], false) << "), 3rd "
       << fixed(s.largest_mm[2], 3) << " mm (" << where_text(r, s.largest_index[2], false) << ")\n";
  }

  os << "\nsummary (dr = r_sim - r_meas; l2 = sqrt(sum dr^2)/N, rms = sqrt(sum dr^2/N))\n";
  os << "  probe        n   linf [mm]    MAE [mm]    RMS [mm]  MSE [mm2]     l2 [mm]  largest at\n";
  auto row = [&](const std::string& name, const ErrorStats& s, bool with_probe) {
    os << "  " << pad(name, 8, false) << pad(std::to_string(s.n), 6) << pad(fixed(s.linf_mm, 3), 12)
       << pad(fixed(s.mae_mm, 3), 12) << pad(fixed(s.rms_mm, 3), 12) << pad(fixed(s.mse_mm2, 3), 11)
       << pad(fixed(s.l2_mm, 4), 12) << "  " << where_text(r, s.largest_index[0], with_probe) << "\n";
  };
  for (size_t p = 0; p < c.probes.size(); ++p) row(c.probes[p], r.probe_stats[p], false);
  row("all", r.overall, true);

  if (!r.objectives.empty()) {
    size_t width = 9;
    for (const auto& o : r.objectives) width = std::max(width, o.name.size() + 2);
    os << "\nobjectives\n  " << pad("name", width, false) << "norm         value      n  missing\n";
    for (size_t k = 0; k < r.objectives.size(); ++k) {
      const auto& o = r.objectives[k];
      const auto& v = r.values[k];
      os << "  " << pad(o.name, width, false) << pad(norm_name(o.norm), 4, false) << pad(fixed(v.value, 3), 10) << " "
         << pad(norm_unit(o.norm), 3, false) << pad(std::to_string(v.n), 6) << pad(std::to_string(v.missing), 9)
         << "\n";
    }
  }

  os << "\nturn counts: ";
  if (c.violation() == 0) {
    os << "agree";
  } else {
    os << "DIFFER (a constraint violation of " << c.violation() << " turn" << (c.violation() == 1 ? "" : "s") << ")";
    for (const auto& t : c.counts) {
      if (!t.missing.empty()) os << "\n  " << t.probe << ": not simulated: " << turn_list(t.missing);
      if (!t.extra.empty()) os << "\n  " << t.probe << ": not measured: " << turn_list(t.extra);
    }
  }
  os << "\n";
  if (!c.simulated_only.empty()) {
    os << "not compared (simulated only):";
    for (const auto& n : c.simulated_only) os << " " << n;
    os << "\n";
  }
  os << "result: max |dr| " << fixed(r.overall.linf_mm, 3) << " mm, tolerance " << cli::fmt(r.tol_mm, 6) << " mm: "
     << (r.agrees() ? "agree" : "DIFFER") << "\n";
}

void write_residuals_csv(std::ostream& os, const CompareReport& r, bool provenance) {
  if (provenance) os << cli::provenance_comment();
  os << "# delta_mm = r_sim_mm - r_meas_mm\n";
  os << "probe,turn,r_meas_mm,r_sim_mm,delta_mm\n";
  char buf[256];
  for (const auto& res : r.comparison.residuals) {
    std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6f,%.6f\n", r.comparison.probes[static_cast<size_t>(res.probe)].c_str(),
                  res.turn, res.r_meas_mm, res.r_sim_mm, res.delta_mm);
    os << buf;
  }
  // Unmatched turns as comments: the table stays numeric, and a reader still sees them.
  for (const auto& t : r.comparison.counts) {
    if (!t.missing.empty()) os << "# missing probe=" << t.probe << " turns=" << turn_list(t.missing) << " (not simulated)\n";
    if (!t.extra.empty()) os << "# extra probe=" << t.probe << " turns=" << turn_list(t.extra) << " (not measured)\n";
  }
}

int run_compare(const CompareOptions& o) {
  if (o.measured.empty() || o.simulated.empty())
    throw usage_error("give a measured and a simulated file ('-' for stdin)");
  const bool objectives_stdin = o.objectives == "@-";
  if ((o.measured == "-") + (o.simulated == "-") + objectives_stdin > 1)
    throw usage_error("only one input can be stdin (measured, simulated, --objectives @-)");
  const bool out_stdout = o.common.output.empty() || o.common.output == "-";
  if (out_stdout && o.residuals == "-") throw usage_error("-o and --residuals cannot both be stdout");

  // Parse everything before reading data, so a bad option fails fast.
  std::vector<Objective> objectives;
  if (!o.objectives.empty()) {
    if (o.objectives.front() == '@') {
      const std::string path = o.objectives.substr(1);
      if (path.empty()) throw usage_error("--objectives @FILE: no file name after '@'");
      InputText in = read_input(path);
      objectives = objectives_from_document(parse_json(in.text, in.name), in.name);
    } else {
      objectives = parse_objectives_spec(o.objectives);
    }
  }
  TurnTable measured = turn_table_from_csv(CsvTable::read(o.measured));
  TurnTable simulated = turn_table_from_csv(CsvTable::read(o.simulated));
  if (measured.points.empty()) throw data_error(measured.source, 0, "no measured turns");
  CompareReport report = make_compare_report(std::move(measured), std::move(simulated), std::move(objectives), o.tol_mm);
  if (report.overall.n == 0)
    cli::warn(o.common, "no turn matched: no probe and turn number in common");

  // Open both outputs before committing either, so a failing one leaves neither behind.
  OutputFile out(o.common.output);
  std::unique_ptr<OutputFile> res_out;
  if (!o.residuals.empty()) res_out = std::make_unique<OutputFile>(o.residuals);
  if (o.common.format == "text")
    write_errors_text(out.stream(), report);
  else
    write_errors_json(out.stream(), report, !o.common.no_provenance);
  if (res_out) write_residuals_csv(res_out->stream(), report, !o.common.no_provenance);
  out.commit();
  if (res_out) res_out->commit();
  return report.agrees() ? 0 : 1;
}

}  // namespace turnfit
