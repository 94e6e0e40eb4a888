// turnfit-track: accelerated orbits and turn patterns at the probes.
#include "turnfit/track/track_app.hpp"

int main(int argc, char** argv) {
  turnfit::TrackOptions opts;
  CLI::App app;
  turnfit::add_track_options(app, opts);
  return turnfit::cli::run_tool("track", app, argc, argv, [&] { return turnfit::run_track(opts); });
}
