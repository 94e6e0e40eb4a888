// Tracking: injection state, kinetic energy, dispatch to the integrators.
#include "turnfit/track/tracker.hpp"

#include <algorithm>
#include <cmath>

#include "turnfit/io/error.hpp"
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

TrackSettings machine_track_settings(const Machine& m, const std::string& integrator) {
  TrackSettings st;
  st.integrator = !integrator.empty() ? integrator : !m.tracking.integrator.empty() ? m.tracking.integrator : "azimuth";
  if (st.integrator != "azimuth" && st.integrator != "rk4")
    throw data_error(m.path, 0, "/tracking/integrator: unknown integrator '" + st.integrator + "'");
  st.steps_per_turn = m.tracking.steps_per_turn > 0 ? m.tracking.steps_per_turn : 2880;
  st.step_deg = m.tracking.step_deg;
  st.turns = m.tracking.turns;
  return st;
}

Injection effective_injection(const Machine& m) {
  if (!m.injection) throw data_error(m.path, 0, "/injection: the machine has no injection block to track from");
  Injection in = *m.injection;
  if (!m.effect_set.injection_offset) return in;
  const InjectionOffsetEffect& o = *m.effect_set.injection_offset;
  const Injection& in0 = *m.injection;
  // The loader checked that these stay physical (r, E > 0, an azimuthal momentum left).
  auto betagamma = [&](double e_MeV) {
    const double g = 1 + e_MeV / m.particle.mass_MeV;
    return std::sqrt(g * g - 1);
  };
  const double P0 = betagamma(in0.energy_MeV);
  in.energy_MeV += o.dE_MeV;
  const double P = betagamma(in.energy_MeV);
  in.r_mm += o.dr_mm;
  in.z_mm += o.dz_mm;
  // Angles p_r / p and p_z / p move by the offsets; the momentum is that of the new energy.
  in.pr_betagamma = P * (in0.pr_betagamma / P0 + o.dpr_mrad * 1e-3);
  in.pz_betagamma = P * (in0.pz_betagamma / P0 + o.dpz_mrad * 1e-3);
  if (o.dphase_deg != 0) in.t_ns += o.dphase_deg / (360 * m.rf.frequency_MHz * 1e6) * 1e9;
  return in;
}

double kinetic_energy(const ParticleState& s, double mass_MeV) {
  return (std::sqrt(1 + s.px * s.px + s.py * s.py + s.pz * s.pz) - 1) * mass_MeV;
}

TrackEnd track_particle(const TrackModel& model, const ParticleState& start, const TrackSettings& settings,
                        std::vector<TurnRecord>& turns, std::vector<KickRecord>* kicks,
                        std::vector<PathPoint>* path) {
  if (settings.integrator == "rk4") return detail::track_time(model, start, settings, turns, kicks, path);
  if (settings.reference_stepper) return detail::track_azimuth(model, start, settings, turns, kicks, path);
  TrackEnd end;
  detail::GroupOutput out{&turns, kicks, path, &end};
  detail::track_azimuth_group(model, &start, 1, settings, &out);
  return end;
}

void track_particles(const TrackModel& model, const ParticleState* starts, size_t n, const TrackSettings& settings,
                     std::vector<TurnRecord>* turns, TrackEnd* ends) {
  if (settings.integrator == "rk4" || settings.reference_stepper) {
    for (size_t i = 0; i < n; ++i) ends[i] = track_particle(model, starts[i], settings, turns[i]);
    return;
  }
  std::vector<detail::GroupOutput> out(n);
  for (size_t i = 0; i < n; ++i) out[i] = {&turns[i], nullptr, nullptr, &ends[i]};
  detail::track_azimuth_group(model, starts, n, settings, out.data());
}

void track_particles(const TrackModel* const* models, const ParticleState* starts, size_t n,
                     const TrackSettings& settings, std::vector<TurnRecord>* turns, TrackEnd* ends) {
  if (settings.integrator == "rk4" || settings.reference_stepper) {
    for (size_t i = 0; i < n; ++i) ends[i] = track_particle(*models[i], starts[i], settings, turns[i]);
    return;
  }
  std::vector<detail::GroupOutput> out(n);
  for (size_t i = 0; i < n; ++i) out[i] = {&turns[i], nullptr, nullptr, &ends[i]};
  detail::track_azimuth_group(models, starts, n, settings, out.data());
}

}  // namespace turnfit
