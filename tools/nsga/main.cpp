// turnfit-nsga: NSGA-II with constraints, resumable, on threads and on MPI.
#include "turnfit/optimize/nsga_app.hpp"

int main(int argc, char** argv) {
  turnfit::NsgaOptions opts;
  CLI::App app;
  turnfit::add_nsga_options(app, opts);
  return turnfit::cli::run_tool("nsga", app, argc, argv, [&] { return turnfit::run_nsga(opts); });
}
