// turnfit-plot as a library: the figures (probe profiles with their peaks, turn separation,
// residuals per turn, trim coil fits) built from the other tools' outputs, and the tool's run.
#pragma once

#include <CLI/CLI.hpp>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/plot/figure.hpp"

namespace turnfit {

/// Everything turnfit-plot is asked to draw.
struct PlotOptions {
  cli::CommonOptions common;
  std::string kind;                     ///< profile, separation, residuals, trimcoils
  std::vector<std::string> inputs;      ///< the kind's input files ("-": stdin, once)
  std::vector<std::string> labels;      ///< --label: a name per input (default: the file stem)
  std::vector<std::string> peaks;       ///< profile: peaks tables to mark (turnfit-peakfind)
  std::vector<std::string> turns;       ///< profile: turns to tick under the profile (track, truth)
  std::vector<std::string> probes;      ///< --probe: only these probes (default: all)
  std::vector<std::string> coils;       ///< trimcoils: only these coils
  std::vector<std::string> phase;       ///< trimcoils: the phase-shift scans the fits came from
  std::string objectives;               ///< residuals: mark these turn groups (compare's spec)
  double tol_mm = 0;                    ///< residuals: draw +-tol (0: none)
  std::string xrange, yrange;           ///< "MIN:MAX" (either side may be empty)
  std::string title;                    ///< figure title (default: none)
  std::string size;                     ///< "W,H" in pixels (default: 1000 x 320 per panel)
  int label_every = 0;                  ///< profile: number every N-th turn (0: about 25 a panel)
  std::string true_front;               ///< front: a built-in problem whose true front to draw
  std::string axes = "1,2";             ///< front: the two objectives drawn (1-based)
  std::string image_format;             ///< --format: png or svg ("": by -o's extension, else png)
  bool no_render = false;               ///< write the data and script only
  std::string gnuplot;                  ///< --gnuplot program
};

/// Registers turnfit-plot's subcommands and options.
void add_plot_options(CLI::App& app, PlotOptions& o);

/// A probe profile per panel, with the peaks found (flagged ones apart, turn numbers on every
/// label_every-th) and simulated or true turns ticked beneath (paper Figs. 3-4).
Figure profile_figure(const PlotOptions& o);
/// Turn separation r(n) - r(n-1) against turn n, a panel per probe, a series per input: peaks
/// or turns tables (paper Figs. 6-7).
Figure separation_figure(const PlotOptions& o);
/// Residuals (compare's residuals.csv) per turn, a panel per probe, a series per model, with
/// zero, tolerance and objective-group boundaries (paper Figs. 18-19).
Figure residuals_figure(const PlotOptions& o);
/// Trim coil fits (tc-fit's csv): the fitted phase shift with the scans and its 1-sigma band,
/// and the normalized field shapes (paper Figs. 8-9).
Figure trimcoils_figure(const PlotOptions& o);

/// Fronts of turnfit-nsga (front.json) in the plane of two objectives, with a built-in
/// problem's true front for reference.
Figure front_figure(const PlotOptions& o);

/// The figure the options ask for (by kind).
Figure build_figure(const PlotOptions& o);

/// Runs turnfit-plot: builds the figure, renders it; returns the exit code.
int run_plot(const PlotOptions& o);

}  // namespace turnfit
