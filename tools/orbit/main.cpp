// turnfit-orbit: equilibrium orbits, tunes and isochronism of a cyclotron field.
#include "turnfit/orbit/orbit_app.hpp"

int main(int argc, char** argv) {
  turnfit::OrbitOptions opts;
  CLI::App app;
  turnfit::add_orbit_options(app, opts);
  return turnfit::cli::run_tool("orbit", app, argc, argv, [&] { return turnfit::run_orbit(opts); });
}
