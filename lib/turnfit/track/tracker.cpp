// Tracking: injection state, kinetic energy, dispatch to the integrators.
#include "turnfit/track/tracker.hpp"

#include <algorithm>
#include <cmath>

#include "turnfit/track/integrators.hpp"

namespace turnfit {

std::vector<std::pair<std::string, std::string>> list_integrators() {
  return {{"azimuth", "5th-order Runge-Kutta in azimuth, steps of whole map cells (--step-deg), exact gap and probe crossings (default)"},
          {"rk4", "RK4 in time with --steps-per-turn fixed steps (OPAL-cycl's scheme), crossings interpolated"}};
}

ParticleState injection_state(const Injection& inj, double mass_MeV, bool opal_single_precision) {
  ParticleState s;
  const double gamma = 1 + inj.energy_MeV / mass_MeV;
  const double P = std::sqrt(gamma * gamma - 1);
  const double pr = inj.pr_betagamma, pz = inj.pz_betagamma;
  const double pt2 = std::max(0.0, P * P - pr * pr - pz * pz);
  // OPAL keeps the radicand in a float and so takes the float square root (physics.md).
  const double pt = opal_single_precision ? static_cast<double>(std::sqrt(static_cast<float>(pt2))) : std::sqrt(pt2);
  const double th = inj.phi_deg * kPi / 180, r = inj.r_mm * 1e-3;
  s.x = r * std::cos(th);
  s.y = r * std::sin(th);
  s.z = inj.z_mm * 1e-3;
  s.px = pr * std::cos(th) - pt * std::sin(th);
  s.py = pr * std::sin(th) + pt * std::cos(th);
  s.pz = pz;
  s.t = inj.t_ns * 1e-9;
  return s;
}

double kinetic_energy(const ParticleState& s, double mass_MeV) {
  return (std::sqrt(1 + s.px * s.px + s.py * s.py + s.pz * s.pz) - 1) * mass_MeV;
}

TrackEnd track_particle(const TrackModel& model, const ParticleState& start, const TrackSettings& settings,
                        std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                        std::vector<PathPoint>* path) {
  if (settings.integrator == "rk4") return detail::track_time(model, start, settings, turns, kicks, path);
  return detail::track_azimuth(model, start, settings, turns, kicks, path);
}

}  // namespace turnfit
