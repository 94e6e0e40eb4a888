// turnfit-plot: figures from turnfit's tables through gnuplot, with their data and script kept.
#include "turnfit/plot/plot_app.hpp"

int main(int argc, char** argv) {
  turnfit::PlotOptions opts;
  CLI::App app;
  turnfit::add_plot_options(app, opts);
  return turnfit::cli::run_tool("plot", app, argc, argv, [&] { return turnfit::run_plot(opts); });
}
