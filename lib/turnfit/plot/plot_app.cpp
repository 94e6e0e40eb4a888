// turnfit-plot: figures from the tools' tables, drawn by gnuplot with their data and script kept.
#include "turnfit/plot/plot_app.hpp"

#include <unistd.h>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <set>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/metrics/metrics.hpp"
#include "turnfit/optimize/problems.hpp"
#include "turnfit/peaks/peaks.hpp"

namespace turnfit {

void add_plot_options(CLI::App& app, PlotOptions& o) {
  app.description(
      "Figures from turnfit's tables, drawn by gnuplot (PNG or SVG). Beside IMAGE it writes\n"
      "IMAGE's stem + .plot.csv (the data) and + .gp (the script): 'gnuplot STEM.gp' redraws the figure,\n"
      "edit the script to restyle it. Kinds: profile, separation, residuals, trimcoils, front.");
  app.require_subcommand(1, 1);
  cli::add_common_options(app, o.common, cli::kOutput);
  app.add_option("--format", o.image_format, "Image format (default: by -o's extension, else png)")
      ->check(CLI::IsMember({"png", "svg"}));
  app.add_option("--title", o.title, "Figure title");
  app.add_option("--size", o.size, "Image size W,H in pixels (default: 1000 wide, 320 high per panel)");
  app.add_option("--xrange", o.xrange, "x range MIN:MAX of every panel (a side may be empty)");
  app.add_option("--yrange", o.yrange, "y range MIN:MAX of every panel (a side may be empty)");
  app.add_option("--probe", o.probes, "Only this probe (repeatable; default: every probe)")->allow_extra_args(false);
  app.add_flag("--no-render", o.no_render, "Write the data and the gnuplot script only (gnuplot not needed)");
  app.add_option("--gnuplot", o.gnuplot, "The gnuplot program (default: $TURNFIT_GNUPLOT, else gnuplot on PATH)");

  auto sub = [&](const char* name, const char* what) {
    CLI::App* s = app.add_subcommand(name, what);
    s->fallthrough();
    s->callback([&o, name] { o.kind = name; });
    return s;
  };
  CLI::App* p = sub("profile", "Probe profiles with their peaks and turn numbers, a panel per profile (paper Figs. 3-4)");
  p->add_option("profiles", o.inputs, "Profile CSVs (position_mm,intensity; '-' for stdin)")->required();
  p->add_option("--peaks", o.peaks, "Peaks to mark (turnfit-peakfind's table; repeatable; matched by probe)")->allow_extra_args(false);
  p->add_option("--turns", o.turns,
                "Turns to tick under the profile (turnfit-track's turns, or any probe,turn,r_mm table; repeatable)")->allow_extra_args(false);
  p->add_option("--label", o.labels, "A name per --turns file (default: its file stem)")->allow_extra_args(false);
  p->add_option("--label-every", o.label_every, "Number every N-th turn (0: about 25 numbers a panel)")
      ->check(CLI::Range(0, 1000000));

  CLI::App* s = sub("separation", "Turn separation r(n) - r(n-1) per turn, a panel per probe (paper Figs. 6-7)");
  s->add_option("tables", o.inputs, "Peaks or turns tables (probe,turn,r_mm; '-' for stdin)")->required();
  s->add_option("--label", o.labels, "A name per table (default: its file stem)")->allow_extra_args(false);

  CLI::App* r = sub("residuals", "Residual per turn, a panel per probe, a series per model (paper Figs. 18-19)");
  r->add_option("residuals", o.inputs, "turnfit-compare --residuals tables ('-' for stdin)")->required();
  r->add_option("--label", o.labels, "A name per table (default: its file stem)")->allow_extra_args(false);
  r->add_option("--objectives", o.objectives, "Mark these turn groups (turnfit-compare's --objectives spec)");
  r->add_option("--tol", o.tol_mm, "Draw lines at +-TOL mm")->check(CLI::Range(0.0, 1e6));

  CLI::App* t = sub("trimcoils", "Trim coil fits: phase shifts with their scans, and field shapes (paper Figs. 8-9)");
  t->add_option("fits", o.inputs, "turnfit-tc-fit --format csv outputs ('-' for stdin)")->required();
  t->add_option("--label", o.labels, "A name per fit file (default: its file stem)")->allow_extra_args(false);
  t->add_option("--phase", o.phase, "The phase-shift scans (tc-fit's inputs; repeatable)")->allow_extra_args(false);
  t->add_option("--coil", o.coils, "Only this coil (repeatable)")->allow_extra_args(false);

  CLI::App* f = sub("front", "Non-dominated fronts of turnfit-nsga in the plane of two objectives");
  f->add_option("fronts", o.inputs, "turnfit-nsga --front files ('-' for stdin)")->required();
  f->add_option("--label", o.labels, "A name per front (default: its file stem)")->allow_extra_args(false);
  f->add_option("--axes", o.axes, "The two objectives drawn, 1-based")->capture_default_str();
  f->add_option("--true-front", o.true_front, "Draw this built-in problem's true front (ZDT1, TNK, ...)");
}

namespace {

std::string stem_of(const std::string& path) {
  if (path.empty() || path == "-") return "stdin";
  return std::filesystem::path(path).stem().string();
}

/// --label for input i, else the file stem.
std::string label_of(const PlotOptions& o, const std::vector<std::string>& files, size_t i) {
  return i < o.labels.size() ? o.labels[i] : stem_of(files[i]);
}

bool wanted(const std::vector<std::string>& only, const std::string& name) {
  return only.empty() || std::find(only.begin(), only.end(), name) != only.end();
}

/// "MIN:MAX" with either side optional; false if absent.
bool parse_range(const std::string& spec, const char* what, bool* has_lo, double* lo, bool* has_hi, double* hi) {
  if (spec.empty()) return false;
  const auto colon = spec.find(':');
  if (colon == std::string::npos) throw usage_error(std::string(what) + " '" + spec + "': expected MIN:MAX");
  auto parse = [&](const std::string& s, bool* has, double* v) {
    *has = !s.empty();
    if (s.empty()) return;
    if (!parse_decimal(s, *v))
      throw usage_error(std::string(what) + " " + quote(spec) + ": " + quote(s) + " is not a number");
  };
  parse(spec.substr(0, colon), has_lo, lo);
  parse(spec.substr(colon + 1), has_hi, hi);
  if (*has_lo && *has_hi && !(*lo < *hi)) throw usage_error(std::string(what) + " '" + spec + "': MIN must be below MAX");
  return true;
}

/// The options' --xrange/--yrange applied to every panel (a missing side stays automatic).
void apply_ranges(const PlotOptions& o, Figure& fig) {
  bool hl = false, hh = false;
  double lo = 0, hi = 0;
  if (parse_range(o.xrange, "--xrange", &hl, &lo, &hh, &hi))
    for (auto& p : fig.panels) {
      p.has_xrange = true;
      p.xmin = hl ? lo : NAN;
      p.xmax = hh ? hi : NAN;
    }
  if (parse_range(o.yrange, "--yrange", &hl, &lo, &hh, &hi))
    for (auto& p : fig.panels) {
      p.has_yrange = true;
      p.ymin = hl ? lo : NAN;
      p.ymax = hh ? hi : NAN;
    }
}

/// Rejects more than one '-' among all inputs (stdin can be read once).
void check_stdin_once(const std::vector<const std::vector<std::string>*>& lists) {
  int n = 0;
  for (const auto* l : lists)
    for (const auto& f : *l) n += f == "-";
  if (n > 1) throw usage_error("'-' (stdin) given " + std::to_string(n) + " times; it can be read once");
}

void check_labels(const PlotOptions& o, size_t n, const char* what) {
  if (o.labels.size() > n)
    throw usage_error(std::to_string(o.labels.size()) + " --label for " + std::to_string(n) + " " + what);
}

/// Linear interpolation of a profile at x (the ends beyond).
double profile_at(const ProbeProfile& p, double x) {
  const auto& xs = p.position_mm;
  if (x <= xs.front()) return p.intensity.front();
  if (x >= xs.back()) return p.intensity.back();
  const size_t j = static_cast<size_t>(std::upper_bound(xs.begin(), xs.end(), x) - xs.begin());
  const double t = (x - xs[j - 1]) / (xs[j] - xs[j - 1]);
  return p.intensity[j - 1] + t * (p.intensity[j] - p.intensity[j - 1]);
}

/// A round labelling stride giving at most about `target` labels for n turns.
int auto_stride(size_t n, size_t target) {
  static const int steps[] = {1, 2, 5, 10, 20, 25, 50, 100, 200, 500, 1000};
  for (int s : steps)
    if (n <= target * static_cast<size_t>(s)) return s;
  return static_cast<int>((n + target - 1) / target);
}

}  // namespace

Figure profile_figure(const PlotOptions& o) {
  check_stdin_once({&o.inputs, &o.peaks, &o.turns});
  if (o.labels.size() > o.turns.size())
    throw usage_error(std::to_string(o.labels.size()) + " --label for " + std::to_string(o.turns.size()) +
                      " --turns files (in profile, --label names the --turns files)");
  // probe,turn,r_mm[,flag] tables, read as compare reads them (sorted by probe and turn).
  std::vector<TurnTable> peaks, turns;
  for (const auto& f : o.peaks) peaks.push_back(turn_table_from_csv(CsvTable::read(f)));
  for (const auto& f : o.turns) turns.push_back(turn_table_from_csv(CsvTable::read(f)));
  Figure fig;
  fig.kind = "profile";
  fig.title = o.title;
  std::set<std::string> probes_marked;
  for (const auto& file : o.inputs) {
    const ProbeProfile prof = read_profile(file);
    std::string probe = prof.probe.empty() ? stem_of(file) : prof.probe;
    if (!wanted(o.probes, probe)) continue;
    const int pi = static_cast<int>(fig.panels.size());
    Panel pan;
    pan.title = probe + (file == "-" ? "" : " (" + std::filesystem::path(file).filename().string() + ")");
    pan.xlabel = "position along the probe [mm]";
    pan.ylabel = "intensity";
    double ymax = 0;
    for (double v : prof.intensity) ymax = std::max(ymax, v);
    if (!(ymax > 0)) ymax = 1;
    Series line;
    line.panel = pi;
    line.name = "profile";
    line.color = 0;
    line.size = 0.7;
    line.x = prof.position_mm;
    line.y = prof.intensity;
    fig.series.push_back(std::move(line));

    Series ok, flagged, numbers;
    ok.panel = flagged.panel = numbers.panel = pi;
    ok.style = flagged.style = SeriesStyle::points;
    numbers.style = SeriesStyle::labels;
    ok.color = 1;
    ok.point = 7;
    ok.name = "peaks";
    flagged.color = 3;
    flagged.point = 6;
    flagged.size = 1.6;
    flagged.name = "flagged peaks (merged, wide, weak, gap, edge, ambiguous, cross)";
    numbers.color = 6;
    std::vector<const TurnPoint*> rows;
    for (const TurnTable& pk : peaks) {
      const auto [first, last] = pk.probe_range(pk.probe_index(probe));
      for (size_t i = first; i < last; ++i) rows.push_back(&pk.points[i]);
    }
    if (!rows.empty()) probes_marked.insert(probe);
    const int every = o.label_every > 0 ? o.label_every : auto_stride(rows.size(), 25);
    for (const TurnPoint* row : rows) {
      Series& dst = row->flag.empty() || row->flag == "ok" ? ok : flagged;
      const double y = profile_at(prof, row->r_mm);
      dst.x.push_back(row->r_mm);
      dst.y.push_back(y);
      if (row->turn % every == 0 || row == rows.front()) {
        numbers.x.push_back(row->r_mm);
        numbers.y.push_back(y);
        numbers.label.push_back(std::to_string(row->turn));
      }
    }
    for (Series* s : {&ok, &flagged, &numbers})
      if (!s->x.empty()) fig.series.push_back(std::move(*s));
    for (size_t k = 0; k < turns.size(); ++k) {
      const auto [first, last] = turns[k].probe_range(turns[k].probe_index(probe));
      if (first == last) continue;
      Series ticks;
      ticks.panel = pi;
      ticks.style = SeriesStyle::impulses;
      ticks.color = static_cast<int>(2 + k) % 8 == 3 ? 4 : static_cast<int>(2 + k);
      ticks.name = label_of(o, o.turns, k);
      const double top = -0.02 * ymax * static_cast<double>(1 + 2 * k), bottom = top - 0.035 * ymax;
      for (size_t i = first; i < last; ++i) {
        ticks.x.push_back(turns[k].points[i].r_mm);
        ticks.y.push_back(top);
        ticks.y_lo.push_back(bottom);
      }
      fig.series.push_back(std::move(ticks));
    }
    fig.panels.push_back(pan);
  }
  if (fig.panels.empty())
    throw usage_error("no profile left to draw (--probe " + (o.probes.empty() ? std::string() : o.probes.front()) +
                      " matches none of the profiles' probes)");
  for (size_t k = 0; k < o.peaks.size(); ++k) {
    bool any = false;
    for (const auto& p : peaks[k].probes) any = any || probes_marked.count(p);
    if (!any)
      cli::warn(o.common, o.peaks[k] + ": no peaks of the profiles' probes (probe names must match)");
  }
  apply_ranges(o, fig);
  return fig;
}

Figure separation_figure(const PlotOptions& o) {
  check_stdin_once({&o.inputs});
  check_labels(o, o.inputs.size(), "tables");
  Figure fig;
  fig.kind = "separation";
  fig.title = o.title;
  std::map<std::string, int> panel_of;
  for (size_t k = 0; k < o.inputs.size(); ++k) {
    const TurnTable t = turn_table_from_csv(CsvTable::read(o.inputs[k]));
    for (size_t p = 0; p < t.probes.size(); ++p) {
      const std::string& probe = t.probes[p];
      if (!wanted(o.probes, probe)) continue;
      auto [it, fresh] = panel_of.emplace(probe, static_cast<int>(fig.panels.size()));
      if (fresh) {
        Panel pan;
        pan.title = probe;
        pan.xlabel = "turn n";
        pan.ylabel = "r(n) - r(n-1) [mm]";
        fig.panels.push_back(pan);
      }
      Series s;
      s.panel = it->second;
      s.style = SeriesStyle::linespoints;
      s.color = static_cast<int>(k);
      s.name = label_of(o, o.inputs, k);
      const auto range = t.probe_range(static_cast<int>(p));
      for (size_t i = range.first + 1; i < range.second; ++i) {
        const TurnPoint& a = t.points[i - 1];
        const TurnPoint& b = t.points[i];
        if (b.turn != a.turn + 1) continue;
        s.x.push_back(b.turn);
        s.y.push_back(b.r_mm - a.r_mm);
      }
      if (!s.x.empty()) fig.series.push_back(std::move(s));
    }
  }
  if (fig.panels.empty()) throw usage_error("no probe left to draw (check --probe)");
  apply_ranges(o, fig);
  return fig;
}

Figure residuals_figure(const PlotOptions& o) {
  check_stdin_once({&o.inputs});
  check_labels(o, o.inputs.size(), "tables");
  const std::vector<Objective> objectives = o.objectives.empty() ? std::vector<Objective>{}
                                                                 : parse_objectives_spec(o.objectives);
  Figure fig;
  fig.kind = "residuals";
  fig.title = o.title;
  std::map<std::string, int> panel_of;
  std::vector<std::string> panel_probe;
  struct Worst {
    double abs = -1;
    int turn = 0;
    std::string model;
  };
  std::vector<std::vector<Worst>> worst;  // per panel, per model
  for (size_t k = 0; k < o.inputs.size(); ++k) {
    const CsvTable t = CsvTable::read(o.inputs[k]);
    t.require_columns({"probe", "turn", "delta_mm"});
    const size_t cp = t.column("probe"), ct = t.column("turn"), cd = t.column("delta_mm");
    std::map<std::string, Series> by_probe;
    std::vector<std::string> order;
    for (size_t i = 0; i < t.rows(); ++i) {
      const std::string& probe = t.cell(i, cp);
      if (!wanted(o.probes, probe)) continue;
      const double turn = t.number(i, ct);
      if (turn != std::floor(turn))
        throw data_error(t.name(), t.line(i), "column 'turn': " + t.cell(i, ct) + " is not a turn number");
      if (!by_probe.count(probe)) order.push_back(probe);
      Series& s = by_probe[probe];
      s.x.push_back(turn);
      s.y.push_back(t.number(i, cd));
    }
    for (const auto& probe : order) {
      auto [it, fresh] = panel_of.emplace(probe, static_cast<int>(fig.panels.size()));
      if (fresh) {
        Panel pan;
        pan.xlabel = "turn n";
        pan.ylabel = "r_sim - r_meas [mm]";
        pan.lines.push_back({false, 0.0, "", 0});
        if (o.tol_mm > 0) {
          pan.lines.push_back({false, o.tol_mm, "+-" + cli::fmt(o.tol_mm, 4) + " mm", 1});
          pan.lines.push_back({false, -o.tol_mm, "", 1});
        }
        for (const Objective& obj : objectives)
          for (const TurnRange& part : obj.parts) {
            if (part.probe != probe && part.probe != "*") continue;
            const std::string spec = objective_spec(obj);
            if (part.first_turn != INT_MIN)
              pan.lines.push_back({true, part.first_turn - 0.5, obj.name.empty() ? spec : obj.name, 2});
            if (part.last_turn != INT_MAX) pan.lines.push_back({true, part.last_turn + 0.5, "", 2});
          }
        fig.panels.push_back(pan);
        panel_probe.push_back(probe);
        worst.emplace_back();
      }
      Series s = std::move(by_probe[probe]);
      // Sort by turn so the line runs along the turns whatever the table's order.
      std::vector<size_t> idx(s.x.size());
      for (size_t i = 0; i < idx.size(); ++i) idx[i] = i;
      std::sort(idx.begin(), idx.end(), [&](size_t a, size_t b) { return s.x[a] < s.x[b]; });
      Series d;
      d.panel = it->second;
      d.style = SeriesStyle::linespoints;
      d.color = static_cast<int>(k);
      d.point = k % 2 ? 5 : 7;
      d.name = label_of(o, o.inputs, k);
      Worst w;
      w.model = d.name;
      for (size_t i : idx) {
        d.x.push_back(s.x[i]);
        d.y.push_back(s.y[i]);
        if (std::abs(s.y[i]) > w.abs) w = {std::abs(s.y[i]), static_cast<int>(s.x[i]), d.name};
      }
      worst[static_cast<size_t>(it->second)].push_back(w);
      fig.series.push_back(std::move(d));
    }
  }
  if (fig.panels.empty()) throw usage_error("no residuals left to draw (check --probe and the tables)");
  // Group boundaries outside the turns drawn would be drawn outside the frame: dropped (a
  // group's name moves to its other boundary if that one stays).
  for (size_t p = 0; p < fig.panels.size(); ++p) {
    double lo = INFINITY, hi = -INFINITY;
    for (const auto& s : fig.series)
      if (s.panel == static_cast<int>(p))
        for (double x : s.x) lo = std::min(lo, x), hi = std::max(hi, x);
    std::vector<RefLine> kept;
    std::string pending;
    for (RefLine l : fig.panels[p].lines) {
      if (!l.vertical) {
        kept.push_back(l);
        continue;
      }
      if (!(l.at > lo && l.at < hi)) {
        if (!l.text.empty()) pending = l.text;
        continue;
      }
      if (l.text.empty() && !pending.empty()) {
        l.text = pending;  // the group's end: its name goes left of the line, inside the group
        l.text_left = true;
      }
      pending.clear();
      kept.push_back(l);
    }
    fig.panels[p].lines = kept;
  }
  // Titles carry the largest residual of every model: what the objectives judge.
  for (size_t p = 0; p < fig.panels.size(); ++p) {
    std::string title = panel_probe[p] + ": max |dr|";
    for (size_t m = 0; m < worst[p].size(); ++m) {
      const Worst& w = worst[p][m];
      title += (m ? ", " : " ") + cli::fmt(std::round(w.abs * 100) / 100, 6) + " mm (turn " +
               std::to_string(w.turn) + (worst[p].size() > 1 ? ", " + w.model : "") + ")";
    }
    fig.panels[p].title = title;
  }
  apply_ranges(o, fig);
  return fig;
}

Figure trimcoils_figure(const PlotOptions& o) {
  check_stdin_once({&o.inputs, &o.phase});
  check_labels(o, o.inputs.size(), "fit files");
  Figure fig;
  fig.kind = "trimcoils";
  fig.title = o.title;
  Panel phase, field;
  phase.title = "phase shift per coil: scans and fitted delta sin(phi) (1-sigma band)";
  phase.xlabel = "r [mm]";
  phase.ylabel = "delta sin(phi)";
  field.title = "field shapes (peak +1; the coil's field is bmax_T times this; 1-sigma band)";
  field.xlabel = "r [mm]";
  field.ylabel = "B / bmax";
  field.lines.push_back({false, 0.0, "", 0});
  fig.panels = {phase, field};
  std::map<std::string, int> color_of;  // by coil, in first-appearance order
  auto coil_color = [&](const std::string& c) {
    auto it = color_of.emplace(c, static_cast<int>(color_of.size())).first;
    return it->second;
  };
  size_t ncoils = 0;
  for (size_t k = 0; k < o.inputs.size(); ++k) {
    const CsvTable t = CsvTable::read(o.inputs[k]);
    t.require_columns({"coil", "r_mm", "dsinphi_fit", "dsinphi_sigma", "b_shape", "b_shape_sigma"});
    const size_t cc = t.column("coil"), cr = t.column("r_mm"), cf = t.column("dsinphi_fit"),
                 cfs = t.column("dsinphi_sigma"), cb = t.column("b_shape"), cbs = t.column("b_shape_sigma");
    // tc-fit writes nan where a value is undefined (beyond a tracked fit's last scan radius).
    auto value = [&](size_t i, size_t c) {
      const std::string& s = t.cell(i, c);
      if (s == "nan" || s == "NaN" || s == "-nan") return static_cast<double>(NAN);
      return t.number(i, c);
    };
    std::vector<std::string> order;
    std::map<std::string, std::vector<size_t>> rows;
    for (size_t i = 0; i < t.rows(); ++i) {
      const std::string& coil = t.cell(i, cc);
      if (!wanted(o.coils, coil)) continue;
      if (!rows.count(coil)) order.push_back(coil);
      rows[coil].push_back(i);
    }
    const std::string file_label = label_of(o, o.inputs, k);
    ncoils = std::max(ncoils, order.size());
    for (const auto& coil : order) {
      const int color = coil_color(coil);
      const std::string name = o.inputs.size() > 1 ? coil + " " + file_label : coil;
      Series fb, fl, bb, bl;
      fb.panel = fl.panel = 0;
      bb.panel = bl.panel = 1;
      fb.style = bb.style = SeriesStyle::band;
      fb.color = fl.color = bb.color = bl.color = color;
      fl.dash = bl.dash = static_cast<int>(k % 4);
      fl.name = bl.name = name;
      for (size_t i : rows[coil]) {
        const double r = t.number(i, cr), f = value(i, cf), fs = value(i, cfs), b = value(i, cb), bs = value(i, cbs);
        fl.x.push_back(r);
        fl.y.push_back(f);
        bl.x.push_back(r);
        bl.y.push_back(b);
        if (std::isfinite(fs)) {
          fb.x.push_back(r);
          fb.y.push_back(f);
          fb.y_lo.push_back(f - fs);
          fb.y_hi.push_back(f + fs);
        }
        if (std::isfinite(bs)) {
          bb.x.push_back(r);
          bb.y.push_back(b);
          bb.y_lo.push_back(b - bs);
          bb.y_hi.push_back(b + bs);
        }
      }
      for (Series* s : {&fb, &fl, &bb, &bl})
        if (!s->x.empty()) fig.series.push_back(std::move(*s));
    }
  }
  for (const auto& f : o.phase) {
    const CsvTable t = CsvTable::read(f);
    t.require_columns({"r_mm", "dsinphi"});
    std::string file_coil;
    for (const auto& c : t.comments()) {
      const auto at = c.find("coil=");
      if (at != std::string::npos && (at == 0 || c[at - 1] == ' ' || c[at - 1] == '#'))
        file_coil = c.substr(at + 5, c.find_first_of(" \t", at + 5) - (at + 5));
    }
    if (file_coil.empty() && !t.has_column("coil")) file_coil = stem_of(f);
    const bool per_row = t.has_column("coil");
    const size_t cc = per_row ? t.column("coil") : 0, cr = t.column("r_mm"), cd = t.column("dsinphi");
    std::map<std::string, Series> pts;
    std::vector<std::string> order;
    for (size_t i = 0; i < t.rows(); ++i) {
      const std::string coil = per_row ? t.cell(i, cc) : file_coil;
      if (!wanted(o.coils, coil)) continue;
      if (!pts.count(coil)) order.push_back(coil);
      Series& s = pts[coil];
      s.x.push_back(t.number(i, cr));
      s.y.push_back(t.number(i, cd));
    }
    for (const auto& coil : order) {
      Series s = std::move(pts[coil]);
      s.panel = 0;
      s.style = SeriesStyle::points;
      s.point = 6;
      s.color = coil_color(coil);
      fig.series.push_back(std::move(s));
    }
  }
  if (fig.series.empty()) throw usage_error("no trim coil left to draw (check --coil and the files)");
  // The shapes' own range, not their bands': a poorly determined band (a pole near the window's
  // end) would squash every shape.
  double lo = 0;
  for (const auto& s : fig.series)
    if (s.panel == 1 && s.style == SeriesStyle::lines)
      for (double v : s.y)
        if (std::isfinite(v)) lo = std::min(lo, v);
  fig.panels[1].has_yrange = true;
  fig.panels[1].ymin = std::floor((lo - 0.15) * 10) / 10;
  fig.panels[1].ymax = 1.3;
  // Many coils: name each field shape at its peak instead of a long key.
  if (ncoils > 6) {
    fig.panels[0].key = fig.panels[1].key = false;
    Series names;
    names.panel = 1;
    names.style = SeriesStyle::labels;
    names.color = 6;
    for (const auto& s : fig.series) {
      if (s.panel != 1 || s.style != SeriesStyle::lines || s.name.empty()) continue;
      size_t best = 0;
      for (size_t i = 0; i < s.y.size(); ++i)
        if (std::isfinite(s.y[i]) && (!std::isfinite(s.y[best]) || s.y[i] > s.y[best])) best = i;
      names.x.push_back(s.x[best]);
      names.y.push_back(s.y[best]);
      names.label.push_back(s.name);
    }
    fig.series.push_back(std::move(names));
  }
  apply_ranges(o, fig);
  return fig;
}

Figure front_figure(const PlotOptions& o) {
  check_stdin_once({&o.inputs});
  check_labels(o, o.inputs.size(), "fronts");
  int a = 0, b = 0;
  char tail = 0;
  if (std::sscanf(o.axes.c_str(), "%d,%d%c", &a, &b, &tail) != 2 || a < 1 || b < 1 || a == b)
    throw usage_error("--axes '" + o.axes + "': expected two different objective numbers I,J (from 1)");
  const size_t ia = static_cast<size_t>(a - 1), ib = static_cast<size_t>(b - 1);
  Figure fig;
  fig.kind = "front";
  fig.title = o.title;
  Panel pan;
  pan.xlabel = "f" + std::to_string(a);
  pan.ylabel = "f" + std::to_string(b);
  fig.panels.push_back(pan);
  if (!o.true_front.empty()) {
    const auto problem = make_problem(o.true_front);
    if (std::max(ia, ib) >= problem->n_objectives())
      throw usage_error("--axes " + o.axes + ": " + problem->name() + " has " +
                        std::to_string(problem->n_objectives()) + " objectives");
    std::vector<std::vector<double>> tf = problem->true_front(problem->n_objectives() > 2 ? 2000 : 500);
    if (tf.empty()) throw usage_error("--true-front " + o.true_front + ": its true front is not known");
    std::sort(tf.begin(), tf.end(), [&](const auto& p, const auto& q) { return p[ia] < q[ia]; });
    Series t;
    t.name = problem->name() + " true front";
    t.style = SeriesStyle::points;
    t.color = -1;
    t.point = 7;
    t.size = 0.4;
    for (const auto& p : tf) {
      t.x.push_back(p[ia]);
      t.y.push_back(p[ib]);
    }
    fig.series.push_back(std::move(t));
  }
  for (size_t k = 0; k < o.inputs.size(); ++k) {
    const std::string& file = o.inputs[k];
    const std::string name = file == "-" ? "<stdin>" : file;
    const nlohmann::json j = read_json(file);
    if (!j.is_array()) throw data_error(name, 0, "a front is a JSON array of {\"id\", \"x\", \"f\", \"violation\"}");
    Series s;
    s.name = label_of(o, o.inputs, k);
    s.style = SeriesStyle::points;
    s.color = static_cast<int>(k);
    s.point = k % 2 ? 6 : 7;
    for (size_t i = 0; i < j.size(); ++i) {
      const auto& e = j[i];
      if (!e.is_object() || !e.contains("f") || !e["f"].is_array())
        throw data_error(name, 0, "entry " + std::to_string(i) + ": expected an object with an \"f\" array");
      const auto& f = e["f"];
      if (std::max(ia, ib) >= f.size())
        throw usage_error("--axes " + o.axes + ": " + name + " has " + std::to_string(f.size()) + " objectives");
      if (!f[ia].is_number() || !f[ib].is_number())
        throw data_error(name, 0, "entry " + std::to_string(i) + ": \"f\" holds a non-number");
      s.x.push_back(f[ia].get<double>());
      s.y.push_back(f[ib].get<double>());
    }
    if (s.x.empty()) cli::warn(o.common, name + ": an empty front");
    fig.series.push_back(std::move(s));
  }
  fig.width_px = 800;
  fig.height_px = 640;
  apply_ranges(o, fig);
  return fig;
}

Figure build_figure(const PlotOptions& o) {
  if (o.kind == "profile") return profile_figure(o);
  if (o.kind == "separation") return separation_figure(o);
  if (o.kind == "residuals") return residuals_figure(o);
  if (o.kind == "trimcoils") return trimcoils_figure(o);
  if (o.kind == "front") return front_figure(o);
  throw usage_error("unknown figure '" + o.kind + "' (profile, separation, residuals, trimcoils, front)");
}

int run_plot(const PlotOptions& o) {
  RenderOptions r;
  r.image = o.common.output.empty() ? "-" : o.common.output;
  r.render = !o.no_render;
  r.gnuplot = o.gnuplot;
  r.quiet = o.common.quiet;
  for (const auto* list : {&o.inputs, &o.peaks, &o.turns, &o.phase}) r.inputs.insert(r.inputs.end(), list->begin(), list->end());
  if (!o.image_format.empty()) {
    r.format = o.image_format == "svg" ? ImageFormat::svg : ImageFormat::png;
  } else if (!image_format_from_path(r.image, &r.format)) {
    r.format = ImageFormat::png;
    if (r.image != "-")
      cli::warn(o.common, r.image + ": neither .png nor .svg: writing PNG (--format svg for SVG)");
  }
  if (r.image == "-" && r.render && ::isatty(1))
    throw usage_error("will not write an image to a terminal: give -o FILE.png or -o FILE.svg (or pipe it)");
  int w = 0, h = 0;  // 0: the figure's own size
  if (!o.size.empty()) {
    char tail = 0;
    if (std::sscanf(o.size.c_str(), "%d,%d%c", &w, &h, &tail) != 2 || w < 100 || h < 100 || w > 20000 || h > 20000)
      throw usage_error("--size '" + o.size + "': expected W,H in pixels, each 100 to 20000");
  }
  Figure fig = build_figure(o);
  if (w > 0) {
    fig.width_px = w;
    fig.height_px = h;
  }
  if (!o.common.no_provenance) fig.notes = cli::provenance_comment();
  render_figure(fig, r);
  return 0;
}

}  // namespace turnfit
