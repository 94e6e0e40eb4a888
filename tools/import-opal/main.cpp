// turnfit-import-opal: an OPAL-cycl input as a turnfit machine.
#include "turnfit/opal/opal_io.hpp"

int main(int argc, char** argv) {
  turnfit::ImportOpalOptions opts;
  CLI::App app;
  turnfit::add_import_opal_options(app, opts);
  return turnfit::cli::run_tool("import-opal", app, argc, argv, [&] { return turnfit::run_import_opal(opts); });
}
