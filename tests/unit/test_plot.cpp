// turnfit-plot: figure data and scripts, the figures built from tool outputs, and rendering.
#include <sys/stat.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "../support.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/peaks/peaks.hpp"
#include "turnfit/plot/plot_app.hpp"

using namespace turnfit;

namespace {

using test::TempDir;

bool exists(const std::string& p) { return std::filesystem::exists(p); }

std::string slurp(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

/// Whether gnuplot is on PATH (where render() looks for it).
bool have_gnuplot() { return std::system("command -v gnuplot > /dev/null 2>&1") == 0; }

const Series* find_series(const Figure& f, int panel, const std::string& name) {
  for (const auto& s : f.series)
    if (s.panel == panel && s.name == name) return &s;
  return nullptr;
}

const std::string kRing8 = TURNFIT_SOURCE_SHARE "/ring8";

}  // namespace

TEST_CASE("figure data: one row per point, series selected by k, cells made CSV-safe", "[plot]") {
  Figure f;
  f.panels.resize(2);
  f.panels[0].title = "RRL, \"x\"";
  Series a, b;
  a.name = "model, nominal";
  a.x = {1, 2, 3};
  a.y = {0.5, NAN, 1.5};
  b.panel = 1;
  b.style = SeriesStyle::band;
  b.x = {4};
  b.y = {1};
  b.y_lo = {0.5};
  b.y_hi = {1.5};
  f.series = {a, b};
  std::ostringstream os;
  write_figure_csv(os, f);
  const CsvTable t = CsvTable::parse(os.str(), "fig");
  REQUIRE(t.rows() == 4);
  CHECK(t.cell(0, t.column("panel")).rfind("RRL   x", 0) == 0);
  CHECK(t.cell(0, t.column("series")) == "model  nominal");
  CHECK(t.cell(1, t.column("y")) == "NaN");
  CHECK(t.cell(3, t.column("k")) == "1");
  CHECK(t.number(3, t.column("y_hi")) == 1.5);
  CHECK(t.cell(0, t.column("y_lo")).empty());
}

TEST_CASE("figure script: a plot per panel, quoting, ranges, terminal by format", "[plot]") {
  Figure f;
  f.kind = "residuals";
  f.title = "it's";
  f.panels.resize(2);
  f.panels[0].has_xrange = true;
  f.panels[0].xmin = NAN;
  f.panels[0].xmax = 5;
  f.panels[1].lines.push_back({false, 2.0, "tol", 1});
  Series a;
  a.name = "o'k";
  a.x = {1};
  a.y = {1};
  f.series = {a};
  const std::string png = figure_script(f, "fig.plot.csv", "fig.png", ImageFormat::png);
  CHECK(png.find("pngcairo") != std::string::npos);
  CHECK(png.find("set multiplot layout 2,1 title 'it''s' font") != std::string::npos);
  CHECK(png.find("title 'o''k'") != std::string::npos);
  CHECK(png.find("set xrange [*:5]") != std::string::npos);
  CHECK(png.find("($1==0 ? $4 : NaN)") != std::string::npos);
  // The empty panel still draws its reference line and says it has no data.
  CHECK(png.find("'no data'") != std::string::npos);
  CHECK(png.find("datafile = dir . 'fig.plot.csv'") != std::string::npos);
  const std::string svg = figure_script(f, "fig.plot.csv", "fig.svg", ImageFormat::svg);
  CHECK(svg.find("set terminal svg") != std::string::npos);
  ImageFormat fmt = ImageFormat::png;
  CHECK(image_format_from_path("a/b.SVG", &fmt));
  CHECK(fmt == ImageFormat::svg);
  CHECK_FALSE(image_format_from_path("a/b.pdf", &fmt));
}

TEST_CASE("profile figure: peaks sit on the profile, flagged apart, turns ticked beneath", "[plot]") {
  TempDir tmp;
  const std::string profile = kRing8 + "/measured/RRI2.csv";
  const ProbeProfile prof = read_profile(profile);
  // Peaks where the profile is highest in two windows, one flagged, and a probe not drawn.
  auto argmax = [&](double lo, double hi) {
    size_t best = 0;
    double top = -1;
    for (size_t i = 0; i < prof.position_mm.size(); ++i)
      if (prof.position_mm[i] >= lo && prof.position_mm[i] <= hi && prof.intensity[i] > top) {
        top = prof.intensity[i];
        best = i;
      }
    return best;
  };
  const size_t i1 = argmax(2080, 2105), i2 = argmax(2105, 2127);
  std::ostringstream pk;
  pk.precision(17);
  pk << "# a comment\nprobe,turn,r_mm,height,area,width_mm,flag\n"
     << "RRI2,1," << prof.position_mm[i1] << ",1,1,2,ok\nRRI2,2," << prof.position_mm[i2] << ",1,1,2,merged\n"
     << "RRL,9,2300,1,1,2,ok\n";
  PlotOptions o;
  o.kind = "profile";
  o.inputs = {profile};
  o.peaks = {tmp.file("peaks.csv", pk.str())};
  o.turns = {tmp.file("turns.csv", "probe,turn,r_mm\nRRI2,1,2095\nRRI2,2,2117\nRRI2,3,2139\n")};
  o.labels = {"model"};
  o.common.quiet = true;
  const Figure f = build_figure(o);
  REQUIRE(f.panels.size() == 1);
  CHECK(f.panels[0].title.find("RRI2") == 0);
  const Series* ok = find_series(f, 0, "peaks");
  const Series* flagged = find_series(f, 0, "flagged peaks (merged, wide, weak, gap, edge, ambiguous, cross)");
  const Series* ticks = find_series(f, 0, "model");
  REQUIRE(ok);
  REQUIRE(flagged);
  REQUIRE(ticks);
  REQUIRE(ok->x.size() == 1);
  CHECK(ok->y[0] == Approx(prof.intensity[i1]));
  CHECK(flagged->y[0] == Approx(prof.intensity[i2]));
  CHECK(ticks->x.size() == 3);
  CHECK(ticks->style == SeriesStyle::impulses);
  CHECK(ticks->y[0] < 0);
  // --probe with no matching profile is a usage error, not an empty figure.
  o.probes = {"RRX"};
  CHECK(test::error_code([&] { build_figure(o); }) == 64);
}

TEST_CASE("separation figure: r(n) - r(n-1) only between consecutive turns, a panel per probe", "[plot]") {
  TempDir tmp;
  PlotOptions o;
  o.kind = "separation";
  o.inputs = {tmp.file("a.csv", "probe,turn,r_mm\nP,1,100\nP,2,120\nP,3,139\nP,5,170\nQ,7,10\nQ,8,15\n"),
              tmp.file("b.csv", "probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg\nP,2,121,0,0,0,0\nP,1,100,0,0,0,0\n")};
  o.labels = {"measured"};
  const Figure f = build_figure(o);
  REQUIRE(f.panels.size() == 2);
  const Series* a = find_series(f, 0, "measured");
  const Series* b = find_series(f, 0, "b");  // default label: the file stem
  REQUIRE(a);
  REQUIRE(b);
  CHECK(a->x == std::vector<double>{2, 3});
  CHECK(a->y == std::vector<double>{20, 19});
  CHECK(b->y == std::vector<double>{21});
  CHECK(find_series(f, 1, "measured")->y == std::vector<double>{5});
  o.labels = {"1", "2", "3"};
  CHECK(test::error_code([&] { build_figure(o); }) == 64);
}

TEST_CASE("residuals figure: sorted by turn, worst turn in the title, tolerance and objective groups", "[plot]") {
  TempDir tmp;
  PlotOptions o;
  o.kind = "residuals";
  o.inputs = {tmp.file("res.csv", "# delta\nprobe,turn,r_meas_mm,r_sim_mm,delta_mm\nRRL,10,0,0,1.5\nRRL,9,0,0,-2.25\n"
                                  "RRL,11,0,0,0.5\nRRI2,1,0,0,0.1\n")};
  o.tol_mm = 2;
  o.objectives = "RRL:9-10:linf,RRL:11-182:linf";
  o.probes = {"RRL"};
  const Figure f = build_figure(o);
  REQUIRE(f.panels.size() == 1);
  CHECK(f.panels[0].title == "RRL: max |dr| 2.25 mm (turn 9)");
  const Series* s = find_series(f, 0, "res");
  REQUIRE(s);
  CHECK(s->x == std::vector<double>{9, 10, 11});
  CHECK(s->y == std::vector<double>{-2.25, 1.5, 0.5});
  int vertical = 0, horizontal = 0;
  for (const auto& l : f.panels[0].lines) (l.vertical ? vertical : horizontal)++;
  CHECK(horizontal == 3);  // zero and +-tol
  CHECK(vertical == 2);    // the inner ends only: 8.5 and 182.5 lie outside the turns drawn
  CHECK(f.panels[0].lines.back().text == "RRL:11-182:linf");
  CHECK(f.panels[0].lines[3].text == "RRL:9-10:linf");  // moved from the dropped 8.5
  CHECK(f.panels[0].lines[3].text_left);
  o.inputs = {tmp.file("bad.csv", "probe,turn,r_mm\nRRL,9,1\n")};
  std::string msg;
  CHECK(test::error_code([&] { build_figure(o); }, &msg) == 65);
  CHECK(msg.find("bad.csv") != std::string::npos);
  CHECK(msg.find("delta_mm") != std::string::npos);
}

TEST_CASE("trimcoils figure: phase and field panels, bands, scans, nan beyond the scans", "[plot]") {
  TempDir tmp;
  PlotOptions o;
  o.kind = "trimcoils";
  o.inputs = {tmp.file("fit.csv",
                       "# tc-fit\ncoil,r_mm,dsinphi_fit,dsinphi_sigma,b_shape,b_shape_sigma,db_dr_shape\n"
                       "TC1,2000,0,0.001,0.2,0.01,0\nTC1,2010,-0.01,0.001,1,0.01,0\nTC1,2020,-0.02,nan,nan,nan,nan\n"
                       "TC2,2000,0,0.001,-0.3,0.01,0\n")};
  o.phase = {tmp.file("TC1.csv", "# coil=TC1 excitation_T=0.0005\nr_mm,dsinphi\n2000,0.001\n2010,-0.011\n")};
  o.coils = {"TC1"};
  const Figure f = build_figure(o);
  REQUIRE(f.panels.size() == 2);
  const Series* phase = find_series(f, 0, "TC1");
  const Series* field = find_series(f, 1, "TC1");
  REQUIRE(phase);
  REQUIRE(field);
  CHECK(field->y.size() == 3);
  CHECK(std::isnan(field->y[2]));
  int bands = 0, scans = 0;
  for (const auto& s : f.series) {
    bands += s.style == SeriesStyle::band;
    if (s.style == SeriesStyle::points) {
      ++scans;
      CHECK(s.x == std::vector<double>{2000, 2010});
      CHECK(s.color == phase->color);  // a coil's scan has its fit's colour
    }
    if (s.style == SeriesStyle::band) CHECK(s.x.size() == 2);  // no band where sigma is nan
  }
  CHECK(bands == 2);
  CHECK(scans == 1);
  CHECK(f.panels[1].ymax == Approx(1.3));
  CHECK(f.panels[1].ymin <= -0.15);
}

TEST_CASE("render: gnuplot missing or failing leaves nothing, --no-render needs no gnuplot", "[plot]") {
  TempDir tmp;
  Figure f;
  f.kind = "test";
  f.panels.resize(1);
  Series s;
  s.x = {1, 2};
  s.y = {1, 4};
  f.series = {s};
  RenderOptions r;
  r.image = tmp.path + "/fig.png";
  r.gnuplot = tmp.path + "/no-such-gnuplot";
  std::string msg;
  CHECK(test::error_code([&] { render_figure(f, r); }, &msg) == 69);
  CHECK(msg.find("gnuplot") != std::string::npos);
  r.gnuplot = "false";
  CHECK(test::error_code([&] { render_figure(f, r); }) == 70);
  CHECK(std::filesystem::is_empty(tmp.path));  // no image, data, script or temporary
  r.render = false;
  const RenderResult w = render_figure(f, r);
  CHECK(exists(tmp.path + "/fig.plot.csv"));
  CHECK(exists(tmp.path + "/fig.gp"));
  CHECK_FALSE(exists(tmp.path + "/fig.png"));
  CHECK(w.image.empty());
  // An output that is an input is refused before anything is written.
  r.render = true;
  r.gnuplot.clear();
  r.inputs = {tmp.path + "/fig.plot.csv"};
  const std::string before = slurp(tmp.path + "/fig.plot.csv");
  CHECK(test::error_code([&] { render_figure(f, r); }) == 64);
  CHECK(slurp(tmp.path + "/fig.plot.csv") == before);
}

TEST_CASE("render with gnuplot: every figure kind draws without a warning, and the script redraws it", "[plot]") {
  if (!have_gnuplot()) {
    TURNFIT_SKIP_TEST("gnuplot", "gnuplot not on PATH");
    return;
  }
  TempDir tmp;
  const std::string peaks = tmp.file("peaks.csv", "probe,turn,r_mm,height,area,width_mm,flag\nRRI2,1,2094.9,1,1,2,ok\n");
  PlotOptions o;
  o.common.quiet = true;
  o.kind = "profile";
  o.inputs = {kRing8 + "/measured/RRI2.csv", kRing8 + "/measured/RRL.csv"};
  o.peaks = {peaks};
  o.turns = {kRing8 + "/turns.csv"};
  RenderOptions r;
  r.image = tmp.path + "/profile.png";
  RenderResult res = render_figure(build_figure(o), r);
  CHECK(res.log.empty());
  const std::string png = slurp(res.image);
  REQUIRE(png.size() > 1000);
  CHECK(png.compare(0, 8, "\x89PNG\r\n\x1a\n") == 0);

  // The kept script redraws the figure from another folder.
  std::filesystem::remove(res.image);
  const std::string cmd = "cd / && gnuplot '" + res.script + "' 2>&1";
  CHECK(std::system(cmd.c_str()) == 0);
  CHECK(exists(res.image));

  PlotOptions t;
  t.kind = "trimcoils";
  t.inputs = {tmp.file("fit.csv", "coil,r_mm,dsinphi_fit,dsinphi_sigma,b_shape,b_shape_sigma\n"
                                  "TC1,2000,0,0.001,0.2,0.01\nTC1,2010,-0.01,0.001,1,0.01\n")};
  r.image = tmp.path + "/tc.svg";
  r.format = ImageFormat::svg;
  res = render_figure(build_figure(t), r);
  CHECK(res.log.empty());
  CHECK(slurp(res.image).find("<svg") != std::string::npos);

  PlotOptions s;
  s.kind = "residuals";
  s.inputs = {tmp.file("res.csv", "probe,turn,r_meas_mm,r_sim_mm,delta_mm\nRRL,9,0,0,1\nRRL,10,0,0,-1\n")};
  s.objectives = "RRL:9-10:linf";
  s.tol_mm = 0.5;
  r.image = tmp.path + "/res.png";
  r.format = ImageFormat::png;
  res = render_figure(build_figure(s), r);
  CHECK(res.log.empty());
  s.kind = "separation";
  s.inputs = {kRing8 + "/turns.csv"};
  r.image = tmp.path + "/sep.png";
  res = render_figure(build_figure(s), r);
  CHECK(res.log.empty());
  for (const auto& e : std::filesystem::directory_iterator(tmp.path))
    CHECK(e.path().string().find(".tmp.") == std::string::npos);
}

TEST_CASE("front figure: two chosen objectives of each front, a built-in's true front beneath", "[plot]") {
  TempDir tmp;
  PlotOptions o;
  o.kind = "front";
  o.inputs = {tmp.file("a.json", R"([{"id": 3, "x": [0.1], "f": [0.1, 0.7, 5], "violation": 0},
                                     {"id": 9, "x": [0.4], "f": [0.4, 0.3, 6], "violation": 0}])")};
  o.axes = "1,3";
  o.true_front = "dtlz2";
  Figure f = build_figure(o);
  REQUIRE(f.series.size() == 2);
  CHECK(f.series[0].name == "DTLZ2 true front");
  CHECK(f.series[0].x.size() > 100);
  CHECK(f.series[1].x == std::vector<double>{0.1, 0.4});
  CHECK(f.series[1].y == std::vector<double>{5, 6});
  o.true_front = "zdt1";  // two objectives: axis 3 does not exist
  CHECK(test::error_code([&] { build_figure(o); }) == 64);
  o.true_front.clear();
  o.axes = "2,2";
  CHECK(test::error_code([&] { build_figure(o); }) == 64);
  o.axes = "1,2";
  o.inputs = {tmp.file("b.json", R"({"f": [1, 2]})")};
  std::string msg;
  CHECK(test::error_code([&] { build_figure(o); }, &msg) == 65);
  CHECK(msg.find("b.json") != std::string::npos);
}
