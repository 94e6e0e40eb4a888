// turnfit-tc-fit: trim coil phase-shift scans in, rational field profiles out.
#include "turnfit/trimcoil/tcfit_app.hpp"

int main(int argc, char** argv) {
  turnfit::TcFitOptions opts;
  CLI::App app;
  turnfit::add_tcfit_options(app, opts);
  return turnfit::cli::run_tool("tc-fit", app, argc, argv, [&] { return turnfit::run_tcfit(opts); });
}
