// Figure data as CSV, the gnuplot script that draws it, and rendering through a gnuplot process.
#include "turnfit/plot/figure.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <sstream>

#include "turnfit/cli/common.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/process.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

namespace {

/// Okabe & Ito's colour-blind-safe palette (yellow left out: unreadable on white), then black.
const char* const kPalette[] = {"#0072B2", "#D55E00", "#009E73", "#CC79A7",
                                "#E69F00", "#56B4E9", "#000000", "#882255"};
constexpr int kPaletteSize = sizeof kPalette / sizeof kPalette[0];

std::string color_of(int c) {
  if (c < 0) return "#999999";
  return kPalette[c % kPaletteSize];
}

/// A name safe in a CSV cell: no separator, quote or line break.
std::string csv_safe(const std::string& s) {
  std::string out = s;
  for (char& ch : out)
    if (ch == ',' || ch == '"' || ch == '\n' || ch == '\r') ch = ' ';
  return out;
}

/// A gnuplot single-quoted string literal (a quote inside is doubled).
std::string gp_quote(const std::string& s) {
  std::string out = "'";
  for (char ch : s) {
    if (ch == '\'') out += "''";
    else if (ch == '\n' || ch == '\r') out += ' ';
    else out += ch;
  }
  return out + "'";
}

/// A gnuplot double-quoted string literal: line breaks become "\n" (a title of two lines).
std::string gp_dquote(const std::string& s) {
  std::string out = "\"";
  for (char ch : s) {
    if (ch == '\\' || ch == '"') out += '\\', out += ch;
    else if (ch == '\n') out += "\\n";
    else if (ch != '\r') out += ch;
  }
  return out + "\"";
}

std::string num(double x) {
  if (std::isnan(x)) return "NaN";
  if (std::isinf(x)) return x > 0 ? "Inf" : "-Inf";
  return cli::fmt(x, 10);
}

bool has_name(const Figure& fig, int panel) {
  for (const auto& s : fig.series)
    if (s.panel == panel && !s.name.empty()) return true;
  return false;
}

/// The plot clause of one series, selecting its rows by k = index.
std::string plot_clause(const Series& s, size_t k) {
  const std::string sel = "($1==" + std::to_string(k) + " ? $";
  auto col = [&](int c) { return sel + std::to_string(c) + " : NaN)"; };
  const std::string title = s.name.empty() ? "notitle" : "title " + gp_quote(s.name);
  const std::string lc = "lc rgb '" + color_of(s.color) + "'";
  const std::string dt = " dt " + std::to_string(1 + s.dash);
  std::ostringstream c;
  // x is selected too, or every series' x would enter the panel's autoscaled range.
  const std::string x = col(4);
  c << "datafile using ";
  switch (s.style) {
    case SeriesStyle::lines:
      c << x << ":" << col(5) << " with lines lw " << num(1.5 * s.size) << dt << " " << lc;
      break;
    case SeriesStyle::points:
      c << x << ":" << col(5) << " with points pt " << s.point << " ps " << num(0.6 * s.size) << " " << lc;
      break;
    case SeriesStyle::linespoints:
      c << x << ":" << col(5) << " with linespoints lw " << num(1.2 * s.size) << dt << " pt " << s.point << " ps "
        << num(0.5 * s.size) << " " << lc;
      break;
    case SeriesStyle::band:
      c << x << ":" << col(6) << ":7 with filledcurves fs transparent solid 0.22 noborder " << lc;
      break;
    case SeriesStyle::impulses:
      c << x << ":" << col(6) << ":(0):($5-$6) with vectors nohead lw " << num(s.size) << dt << " " << lc;
      break;
    case SeriesStyle::labels:
      c << x << ":" << col(5) << ":8 with labels offset 0,0.7 font ',8' tc rgb '" << color_of(s.color) << "'";
      break;
    case SeriesStyle::errorbars:
      c << x << ":" << col(5) << ":6:7 with yerrorbars pt " << s.point << " ps " << num(0.5 * s.size) << " " << lc;
      break;
  }
  c << " " << title;
  return c.str();
}

}  // namespace

void write_figure_csv(std::ostream& os, const Figure& fig) {
  os << fig.notes;
  os << "k,panel,series,x,y,y_lo,y_hi,label\n";
  for (size_t k = 0; k < fig.series.size(); ++k) {
    const Series& s = fig.series[k];
    const std::string panel = csv_safe(s.panel >= 0 && static_cast<size_t>(s.panel) < fig.panels.size()
                                           ? fig.panels[static_cast<size_t>(s.panel)].title
                                           : std::string());
    const std::string name = csv_safe(s.name);
    for (size_t i = 0; i < s.x.size(); ++i) {
      os << k << ',' << panel << ',' << name << ',' << num(s.x[i]) << ',' << num(i < s.y.size() ? s.y[i] : NAN)
         << ',' << (i < s.y_lo.size() ? num(s.y_lo[i]) : "") << ',' << (i < s.y_hi.size() ? num(s.y_hi[i]) : "")
         << ',' << (i < s.label.size() ? csv_safe(s.label[i]) : "") << '\n';
    }
  }
}

std::string figure_script(const Figure& fig, const std::string& data_name, const std::string& image_name,
                          ImageFormat format) {
  const size_t np = std::max<size_t>(fig.panels.size(), 1);
  const int w = fig.width_px > 0 ? fig.width_px : 1000;
  const int h = fig.height_px > 0 ? fig.height_px : 60 + 320 * static_cast<int>(np);
  std::ostringstream g;
  // Comment lines: a line break in a title or a file name must not start a gnuplot command.
  const auto one_line_of = [](std::string s) {
    for (char& c : s)
      if (c == '\n' || c == '\r') c = ' ';
    return s;
  };
  const std::string one_line = one_line_of(fig.title);
  g << "# turnfit-plot " << fig.kind << (one_line.empty() ? "" : ": " + one_line) << "\n"
    << fig.notes << "# Data: " << one_line_of(data_name) << " (k,panel,series,x,y,y_lo,y_hi,label; a series is the rows of one k).\n"
    << "# Redraw (from any folder): gnuplot " << one_line_of(image_name.substr(0, image_name.rfind('.'))) << ".gp\n"
    << "# Other paths: gnuplot -e \"datafile='other.csv'; outfile='other.png'\" this.gp\n"
    << "lastslash(s) = strstrt(s, \"/\") == 0 ? 0 : strstrt(s, \"/\") + lastslash(s[strstrt(s, \"/\") + 1:])\n"
    << "dir = exists(\"ARG0\") ? ARG0[1:lastslash(ARG0)] : \"\"\n"
    << "if (!exists(\"datafile\")) datafile = dir . " << gp_quote(data_name) << "\n"
    << "if (!exists(\"outfile\")) outfile = dir . " << gp_quote(image_name) << "\n";
  if (format == ImageFormat::svg) {
    g << "set terminal svg size " << w << "," << h << " dynamic noenhanced font 'sans,12' background 'white'\n";
  } else {
    g << "if (strstrt(GPVAL_TERMINALS, \"pngcairo\") > 0) {\n"
      << "  set terminal pngcairo size " << w << "," << h << " noenhanced font 'sans,10'\n"
      << "} else {\n"
      << "  set terminal png size " << w << "," << h << " noenhanced\n"
      << "}\n";
  }
  g << "set output outfile\n"
    << "set datafile separator comma\n"
    << "set datafile columnheaders\n"
    << "set grid lc rgb '#e0e0e0'\n"
    << "set key outside top right horizontal\n"
    << "set border lc rgb '#444444'\n"
    << "set autoscale xfix\n"
    << "set offsets graph 0.01, graph 0.01, 0, 0\n";
  // One panel carries the figure's title on its own first line; several share it above them.
  const bool multi = np > 1;
  if (multi) {
    g << "set multiplot layout " << np << ",1";
    if (!fig.title.empty()) g << " title " << gp_quote(fig.title) << " font ',13'";
    g << "\n";
  }
  for (size_t p = 0; p < np; ++p) {
    const Panel pan = p < fig.panels.size() ? fig.panels[p] : Panel{};
    g << "# panel " << p + 1 << "\n"
      << "unset arrow\nunset label\n"
      << "set title "
      << (!multi && !fig.title.empty() ? gp_dquote(fig.title + (pan.title.empty() ? "" : "\n" + pan.title))
                                       : gp_quote(pan.title))
      << "\n"
      << "set xlabel " << gp_quote(pan.xlabel) << "\n"
      << "set ylabel " << gp_quote(pan.ylabel) << "\n";
    auto bound = [](double v) { return std::isnan(v) ? std::string("*") : num(v); };
    if (pan.has_xrange) g << "set xrange [" << bound(pan.xmin) << ":" << bound(pan.xmax) << "]\n";
    else g << "set xrange [*:*]\n";
    if (pan.has_yrange) g << "set yrange [" << bound(pan.ymin) << ":" << bound(pan.ymax) << "]\n";
    else g << "set yrange [*:*]\n";
    g << (pan.key && has_name(fig, static_cast<int>(p)) ? "set key\n" : "unset key\n");
    // Vertical lines are arrows across the frame; horizontal ones are constant functions, so
    // they are clipped to the frame and enter the autoscaled range (a tolerance stays visible).
    int tag = 1;
    std::vector<std::string> hlines;
    for (const RefLine& l : pan.lines) {
      if (l.vertical) {
        g << "set arrow from " << num(l.at) << ", graph 0 to " << num(l.at) << ", graph 1 nohead dt "
          << 1 + l.dash << " lc rgb '#888888'\n";
        if (!l.text.empty())
          g << "set label " << tag++ << " " << gp_quote(l.text) << " at " << num(l.at) << ", graph 0.97 "
            << (l.text_left ? "right offset -0.3,0" : "offset 0.3,0") << " font ',8' tc rgb '#666666'\n";
      } else {
        hlines.push_back("(" + num(l.at) + ") with lines dt " + std::to_string(1 + l.dash) + " lc rgb '#888888' " +
                         (l.text.empty() ? "notitle" : "title " + gp_quote(l.text)));
      }
    }
    // Bands first so lines and markers are drawn over them.
    std::vector<std::string> clauses;
    for (int pass = 0; pass < 2; ++pass)
      for (size_t k = 0; k < fig.series.size(); ++k) {
        const Series& s = fig.series[k];
        if (s.panel != static_cast<int>(p) || s.x.empty()) continue;
        if ((s.style == SeriesStyle::band) != (pass == 0)) continue;
        clauses.push_back(plot_clause(s, k));
      }
    const bool no_data = clauses.empty();
    clauses.insert(clauses.end(), hlines.begin(), hlines.end());
    if (no_data) {
      // An empty panel still shows its frame and title.
      g << "set xrange [0:1]\nset yrange [0:1]\nset label 99 'no data' at graph 0.5, graph 0.5 center\n"
        << "plot NaN notitle\n";
      continue;
    }
    g << "plot ";
    for (size_t i = 0; i < clauses.size(); ++i) g << (i ? ", \\\n     " : "") << clauses[i];
    g << "\n";
  }
  if (multi) g << "unset multiplot\n";
  g << "set output\n";
  return g.str();
}

bool image_format_from_path(const std::string& path, ImageFormat* format) {
  const std::string ext = std::filesystem::path(path).extension().string();
  std::string e;
  for (char c : ext) e += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (e == ".png") *format = ImageFormat::png;
  else if (e == ".svg") *format = ImageFormat::svg;
  else return false;
  return true;
}

namespace {

/// The program to run: the option, else $TURNFIT_GNUPLOT, else gnuplot on PATH.
std::string gnuplot_program(const RenderOptions& o) {
  if (!o.gnuplot.empty()) return o.gnuplot;
  const char* env = std::getenv("TURNFIT_GNUPLOT");
  if (env && *env) return env;
  return "gnuplot";
}

/// Runs gnuplot on script with datafile/outfile set; returns what it printed.
/// Throws EX_UNAVAILABLE when it cannot be started, EX_SOFTWARE when it fails or hangs.
std::string run_gnuplot(const std::string& program, const std::string& script, const std::string& data,
                        const std::string& image, double timeout_s) {
  ProcessSpec spec;
  spec.argv = {program, "-e", "datafile=" + gp_quote(data) + "; outfile=" + gp_quote(image), script};
  spec.timeout_s = timeout_s;
  spec.merge_stderr = true;
  spec.max_output = 1u << 20;
  const ProcessResult r = run_process(spec);
  std::string out = r.out;
  while (!out.empty() && (out.back() == '\n' || out.back() == ' ')) out.pop_back();
  if (!r.started || r.exit_code == 127)
    throw Error(ExitCode::unavailable,
                "cannot run '" + program + "': " + (r.started ? out : r.spawn_error) +
                    " (turnfit-plot draws with gnuplot: install it, e.g. 'apt-get install gnuplot-nox', or name "
                    "it with --gnuplot or TURNFIT_GNUPLOT; --no-render writes the data and script without it)");
  if (!r.ok())
    throw Error(ExitCode::software, program + " failed (" + r.describe(timeout_s) + ") on its script " + script +
                                        (out.empty() ? "" : ":\n" + out));
  return out;
}

/// A fresh private folder for a figure written to stdout.
std::string make_temp_dir() {
  const char* base = std::getenv("TMPDIR");
  std::string pattern = std::string(base && *base ? base : "/tmp") + "/turnfit-plot.XXXXXX";
  std::vector<char> name(pattern.begin(), pattern.end());
  name.push_back('\0');
  if (!::mkdtemp(name.data()))
    throw Error(ExitCode::cant_create, pattern + ": cannot create a temporary folder: " + std::strerror(errno));
  return name.data();
}

}  // namespace

RenderResult render_figure(const Figure& fig, const RenderOptions& o) {
  const std::string ext = o.format == ImageFormat::svg ? ".svg" : ".png";
  const bool to_stdout = o.image.empty() || o.image == "-";
  std::string tmpdir;
  std::string image = o.image;
  std::vector<StopCleanup> stop;  // a stop signal removes the private folder and what is in it
  if (to_stdout) {
    tmpdir = make_temp_dir();
    image = tmpdir + "/figure" + ext;
    stop.push_back(StopCleanup::path(tmpdir));
    for (const char* f : {"/figure.png", "/figure.svg", "/figure.plot.csv", "/figure.gp"})
      stop.push_back(StopCleanup::path(tmpdir + f));
  }
  struct Cleanup {
    std::string dir;
    ~Cleanup() {
      if (!dir.empty()) {
        std::error_code ec;
        std::filesystem::remove_all(dir, ec);
      }
    }
  } cleanup{tmpdir};

  ImageFormat by_name;
  const std::string stem = image_format_from_path(image, &by_name)
                               ? image.substr(0, image.size() - std::filesystem::path(image).extension().string().size())
                               : image;
  RenderResult res;
  res.data = stem + ".plot.csv";
  res.script = stem + ".gp";
  const std::string image_name = std::filesystem::path(image).filename().string();
  const std::string data_name = std::filesystem::path(res.data).filename().string();
  if (!to_stdout && (res.data == image || res.script == image))
    throw usage_error(image + ": the image would overwrite its own data or script; name it .png or .svg");

  for (const std::string& out : {image, res.data, res.script})
    for (const std::string& in : o.inputs) {
      std::error_code ec;
      if (in != "-" && std::filesystem::equivalent(in, out, ec))
        throw usage_error(out + " is an input: the figure (IMAGE, STEM.plot.csv, STEM.gp) would overwrite it");
    }
  OutputFile data(res.data), script(res.script);
  write_figure_csv(data.stream(), fig);
  script.stream() << figure_script(fig, data_name, image_name, o.format);
  data.stream().flush();
  script.stream().flush();
  if (!data.stream() || !script.stream())
    throw Error(ExitCode::io, res.data + ": write error");
  if (!o.render) {
    if (to_stdout) throw usage_error("--no-render needs -o FILE (the data and script are written beside it)");
    data.commit();
    script.commit();
    res.image.clear();
    return res;
  }
  OutputFile img(image);
  if (img.temp_path().empty())
    throw usage_error(image + ": turnfit-plot writes images to regular files (or '-' for stdout)");
  const std::string log = run_gnuplot(gnuplot_program(o), script.temp_path().empty() ? res.script : script.temp_path(),
                                      data.temp_path().empty() ? res.data : data.temp_path(), img.temp_path(),
                                      o.timeout_s);
  struct stat st {};
  if (::stat(img.temp_path().c_str(), &st) != 0 || st.st_size == 0)
    throw Error(ExitCode::software, gnuplot_program(o) + " wrote no image" + (log.empty() ? "" : ":\n" + log));
  if (!o.quiet && !log.empty()) {
    std::istringstream in(log);
    std::string line;
    while (std::getline(in, line))
      if (!line.empty()) std::cerr << "turnfit-plot: gnuplot: " << line << "\n";
  }
  data.commit();
  script.commit();
  img.commit();
  res.image = image;
  res.log = log;
  if (to_stdout) {
    // Read the image and remove the folder before writing: a reader that goes away (SIGPIPE)
    // must not leave the folder behind.
    const std::string bytes = read_input(image).text;
    std::error_code ec;
    std::filesystem::remove_all(cleanup.dir, ec);
    cleanup.dir.clear();
    std::cout.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    std::cout.flush();
    if (!std::cout) throw Error(ExitCode::io, "<stdout>: write error");
    res = RenderResult{"-", "", "", log};
  }
  return res;
}

}  // namespace turnfit
