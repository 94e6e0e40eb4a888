// turnfit-localsearch: fit a turn-pattern problem's design variables to the measured turns.
#include "turnfit/optimize/localsearch_app.hpp"

int main(int argc, char** argv) {
  turnfit::LocalSearchOptions opts;
  CLI::App app;
  turnfit::add_localsearch_options(app, opts);
  return turnfit::cli::run_tool("localsearch", app, argc, argv, [&] { return turnfit::run_localsearch(opts); });
}
