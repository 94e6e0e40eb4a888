// turnfit-diagnose: what physics the model lacks, where the residual says so, and the refit with it.
#include "turnfit/diagnose/diagnose_app.hpp"

int main(int argc, char** argv) {
  turnfit::DiagnoseOptions opts;
  CLI::App app;
  turnfit::add_diagnose_options(app, opts);
  return turnfit::cli::run_tool("diagnose", app, argc, argv, [&] { return turnfit::run_diagnose(opts); });
}
