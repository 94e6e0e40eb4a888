// turnfit-peakfind: the turns in a wire-probe profile, as a peaks table.
#include "turnfit/peaks/peaks_app.hpp"

int main(int argc, char** argv) {
  turnfit::PeakfindOptions opts;
  CLI::App app;
  turnfit::add_peakfind_options(app, opts);
  return turnfit::cli::run_tool("peakfind", app, argc, argv, [&] { return turnfit::run_peakfind(opts); });
}
