// turnfit-compare: measured against simulated turn radii (errors, objectives, exit 0/1 like diff).
#include "turnfit/metrics/compare_app.hpp"

int main(int argc, char** argv) {
  turnfit::CompareOptions opts;
  CLI::App app;
  turnfit::add_compare_options(app, opts);
  return turnfit::cli::run_tool("compare", app, argc, argv, [&] { return turnfit::run_compare(opts); });
}
