// Assembling the tracking model from a machine description.
#include "turnfit/track/model.hpp"

#include <cmath>

#include "turnfit/field/load.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {

double ProbeLine::crossing_azimuth(double r_m) const {
  if (r_m < std::fabs(a_m)) return std::nan("");
  return std::remainder(phi_rad - std::asin(a_m / r_m), 2 * kPi);
}

bool TrackModel::field(double r_m, double th, FieldSample& out) const {
  // One branch per sample keeps the spline path free of indirect calls.
  if (!(opal_map ? opal_map->sample(r_m, th, out) : map.sample(r_m, th, out))) return false;
  if (coils.empty()) return true;
  const FieldSample main = out;
  for (const auto& c : coils)
    c.add(r_m, th, main.bz_T, main.dbz_dr_T_m, main.dbz_dth_T, threshold_T, out.bz_T, out.dbz_dr_T_m, out.dbz_dth_T);
  return true;
}

TrackModel make_track_model(const Machine& m, const ModelOptions& opt) {
  TrackModel t;
  t.map = load_main_field(m);
  if (opt.opal_map) t.opal_map.emplace(t.map);
  const int sym = t.map.grid().symmetry;
  for (const auto& c : m.trimcoils) {
    t.coils.emplace_back(c, sym);
    // Lookup tables to 1e-7 of each coil's peak (1.4e-10 T for the PSI TC15), five orders
    // below the map's own precision, instead of exponentials at every field sample. The
    // OPAL-compatible model keeps OPAL's formula.
    if (!opt.opal_map) t.coils.back().tabulate(t.map.grid().r_min_m(), t.map.grid().r_max_m());
  }
  t.threshold_T = m.field.trimcoil_threshold_T;
  t.gaps = make_gaps(m);
  for (const auto& p : m.probes) {
    ProbeLine l;
    l.name = p.name;
    l.phi_rad = p.phi_deg * kPi / 180;
    l.sin_phi = std::sin(l.phi_rad);
    l.cos_phi = std::cos(l.phi_rad);
    l.a_m = p.a_mm * 1e-3;
    l.s_min_m = p.s_min_mm * 1e-3;
    l.s_max_m = p.s_max_mm * 1e-3;
    l.shift_m = p.shift_mm * 1e-3;
    l.step_m = p.step_mm * 1e-3;
    t.probes.push_back(l);
  }
  t.mass_MeV = m.particle.mass_MeV;
  t.charge_e = m.particle.charge_e;
  t.rf_MHz = m.rf.frequency_MHz;
  t.harmonic = m.rf.harmonic;
  return t;
}

}  // namespace turnfit
