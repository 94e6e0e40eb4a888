// turnfit-export-opal: a turnfit machine (and a fit applied to it) as an OPAL-cycl input.
#include "turnfit/opal/opal_io.hpp"

int main(int argc, char** argv) {
  turnfit::ExportOpalCliOptions opts;
  CLI::App app;
  turnfit::add_export_opal_options(app, opts);
  return turnfit::cli::run_tool("export-opal", app, argc, argv, [&] { return turnfit::run_export_opal(opts); });
}
