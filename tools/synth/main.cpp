// turnfit-synth: synthetic probe profiles and trim coil phase scans from a truth machine.
#include "turnfit/synth/synth_app.hpp"

int main(int argc, char** argv) {
  turnfit::SynthOptions opts;
  CLI::App app;
  turnfit::add_synth_options(app, opts);
  return turnfit::cli::run_tool("synth", app, argc, argv, [&] { return turnfit::run_synth(opts); });
}
