// Figures as data: panels of styled series, written as one CSV and a gnuplot script that draws
// them, and rendered to PNG or SVG by running gnuplot (outputs renamed into place on success).
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace turnfit {

/// How a series is drawn.
enum class SeriesStyle {
  lines,    ///< a line through the points
  points,   ///< markers
  linespoints,  ///< both
  band,     ///< a filled band between y_lo and y_hi (drawn beneath the rest)
  impulses, ///< vertical sticks from y_lo up to y (e.g. turn positions under a profile)
  labels,   ///< the label text at (x, y)
  errorbars,  ///< markers with vertical bars from y_lo to y_hi
};

/// One curve, point set or band of a panel.
struct Series {
  int panel = 0;           ///< index into Figure::panels
  std::string name;        ///< key entry and data-file name ("" = no key entry)
  SeriesStyle style = SeriesStyle::lines;
  int color = 0;           ///< palette index (0, 1, ...: a colour-blind-safe cycle); -1 grey
  int dash = 0;            ///< 0 solid, 1 dashed, 2 dotted, 3 dash-dot
  int point = 7;           ///< gnuplot point type for markers (7 filled circle, 6 open circle, ...)
  double size = 1;         ///< line width or point size factor
  std::vector<double> x, y;
  std::vector<double> y_lo, y_hi;   ///< bands, error bars, impulse bases (empty otherwise)
  std::vector<std::string> label;   ///< labels (labels style only)
};

/// A horizontal or vertical reference line (zero, tolerance, objective boundaries).
struct RefLine {
  bool vertical = false;
  double at = 0;
  std::string text;        ///< written beside the line ("" = none)
  int dash = 1;
  bool text_left = false;  ///< vertical lines: text to the left of the line (right-aligned)
};

/// One plot area; panels are stacked top to bottom and share nothing but the figure.
struct Panel {
  std::string title;
  std::string xlabel, ylabel;
  bool has_xrange = false, has_yrange = false;
  double xmin = 0, xmax = 0, ymin = 0, ymax = 0;  ///< NaN: that side automatic
  std::vector<RefLine> lines;
  bool key = true;         ///< draw a key for named series
};

/// A whole figure: panels, their series, a title and a pixel size.
struct Figure {
  std::string kind;        ///< what turnfit-plot drew ("profile", "residuals", ...), for comments
  std::string title;
  std::vector<Panel> panels;
  std::vector<Series> series;
  int width_px = 0, height_px = 0;  ///< 0: 1000 wide, 320 per panel plus 60 high
  std::string notes;       ///< '#' comment lines put atop the data and the script (provenance)
};

/// Image formats turnfit-plot writes.
enum class ImageFormat { png, svg };

/// Writes the figure's data as one CSV: k,panel,series,x,y,y_lo,y_hi,label (k = series index,
/// the column the script selects on; names and labels lose commas, quotes and line breaks).
void write_figure_csv(std::ostream& os, const Figure& fig);

/// The gnuplot script that draws fig from data_name into image_name (both names relative to
/// the script's folder, which the script finds from ARG0, so `gnuplot DIR/fig.gp` redraws it
/// from anywhere; `gnuplot -e "datafile='...'; outfile='...'" fig.gp` overrides both paths).
std::string figure_script(const Figure& fig, const std::string& data_name, const std::string& image_name,
                          ImageFormat format);

/// Where and how to render a figure.
struct RenderOptions {
  std::string image = "-";       ///< image path; "-" = stdout (the data and script are then not kept)
  ImageFormat format = ImageFormat::png;
  bool render = true;            ///< false: write the data and script only (no gnuplot needed)
  std::string gnuplot;           ///< program; "" = $TURNFIT_GNUPLOT, else "gnuplot" on PATH
  double timeout_s = 120;        ///< gnuplot is killed after this long (EX_SOFTWARE)
  bool quiet = false;            ///< drop gnuplot's warnings
  std::vector<std::string> inputs;  ///< files the figure was read from: never overwritten (EX_USAGE)
};

/// The paths a render wrote (empty when not written).
struct RenderResult {
  std::string image, data, script;
  std::string log;  ///< what gnuplot printed (warnings; empty when it had nothing to say)
};

/// Writes IMAGE, and beside it IMAGE's stem + ".plot.csv" (the data) and + ".gp" (the script), all
/// through temporaries renamed into place only when gnuplot succeeded. gnuplot missing:
/// EX_UNAVAILABLE (69) naming the program and the package; gnuplot failing: EX_SOFTWARE with
/// its message. Warnings gnuplot prints go to stderr (unless quiet).
RenderResult render_figure(const Figure& fig, const RenderOptions& opts);

/// The image format an output path asks for by its extension (.png, .svg); false if neither.
bool image_format_from_path(const std::string& path, ImageFormat* format);

}  // namespace turnfit
