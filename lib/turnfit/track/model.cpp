// Assembling the tracking model from a machine description, and the machine's effects on it.
#include "turnfit/track/model.hpp"

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <type_traits>
#include <utility>

#include "turnfit/field/load.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/lane_clones.hpp"

namespace turnfit {

double ProbeLine::crossing_azimuth(double r_m) const {
  if (r_m < std::fabs(a_m)) return std::nan("");
  return remainder_two_pi(phi_rad - std::asin(a_m / r_m));
}

double TrackModel::sector_centre(double r_m, double& dc_dr) const {
  // (Inside a sample's dependency chain from the radius to the field: a stored inverse instead
  // of two divisions, and Estrin's scheme, two levels of products where Horner's has four.)
  const double x = (r_m - sector_r_mid_m) * sector_r_inv_half, x2 = x * x;
  const auto& a = sector_centre_coef;
  static_assert(std::tuple_size<std::decay_t<decltype(a)>>::value == 5, "a quartic");
  const double c = (a[0] + a[1] * x) + x2 * ((a[2] + a[3] * x) + x2 * a[4]);
  const double d = (a[1] + 2 * a[2] * x) + x2 * (3 * a[3] + 4 * a[4] * x);
  dc_dr = d * sector_r_inv_half;
  return c;
}

void fit_sector_centre(TrackModel& t) {
  t.sector_centre_coef.fill(0);
  const PolarGrid& g = t.map.grid();
  const int n = g.symmetry;
  const double period = 2 * kPi / n;
  t.sector_r_mid_m = 0.5 * (g.r_min_m() + g.r_max_m());
  t.sector_r_half_m = std::max(0.5 * (g.r_max_m() - g.r_min_m()), 1e-9);
  t.sector_r_inv_half = 1 / t.sector_r_half_m;
  std::vector<double> x, phase, weight;
  double amax = 0, prev = 0, total = 0;
  for (int i = 0; i < g.nr; ++i) {
    double c = 0, s = 0;
    for (int j = 0; j < g.ntheta; ++j) {
      // One sector holds exactly one period of the N-th harmonic.
      const double a = n * (g.theta_min_rad() + j * g.dtheta_rad());
      c += t.map.value(i, j) * std::cos(a);
      s += t.map.value(i, j) * std::sin(a);
      total += std::fabs(t.map.value(i, j));
    }
    const double amp = std::hypot(c, s);
    double ph = std::atan2(s, c) / n;  // the hill centre, in (-period/2, period/2]
    if (!phase.empty()) ph -= period * std::round((ph - prev) / period);  // unwrap across radii
    prev = ph;
    x.push_back((g.r_min_m() + i * g.dr_m() - t.sector_r_mid_m) / t.sector_r_half_m);
    phase.push_back(ph);
    weight.push_back(amp);
    amax = std::max(amax, amp);
  }
  // No sector structure (a harmonic at rounding level of the field): no centre line.
  if (!(amax > 1e-9 * total / g.nr)) return;
  const int deg = std::min<int>(4, static_cast<int>(x.size()) - 1);
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(deg + 1, deg + 1);
  Eigen::VectorXd b = Eigen::VectorXd::Zero(deg + 1);
  for (size_t i = 0; i < x.size(); ++i) {
    const double w = weight[i] / amax;
    if (w < 1e-6) continue;  // radii without sector structure say nothing about it
    double pk[5];
    pk[0] = 1;
    for (int k = 1; k <= deg; ++k) pk[k] = pk[k - 1] * x[i];
    for (int k = 0; k <= deg; ++k) {
      b[k] += w * pk[k] * phase[i];
      for (int l = 0; l <= deg; ++l) A(k, l) += w * pk[k] * pk[l];
    }
  }
  const Eigen::VectorXd coef = A.ldlt().solve(b);
  for (int k = 0; k <= deg; ++k) t.sector_centre_coef[static_cast<size_t>(k)] = coef[k];
}

bool TrackModel::field(double r_m, double th, FieldSample& out) const {
  // One branch per sample keeps the spline path free of indirect calls.
  if (!(opal_map ? opal_map->sample(r_m, th, out) : map.sample(r_m, th, out))) return false;
  add_to_main(r_m, th, out);
  return true;
}

void TrackModel::add_coils(double r_m, double th, const FieldSample& main, double centre, FieldSample& out,
                           CoilHints* hints) const {
  if (summed_for_ != coils.size()) {  // coils added since sum_coils(), or a model built by hand
    for (const auto& c : coils)
      c.add(r_m, th, main.bz_T, main.dbz_dr_T_m, main.dbz_dth_T, threshold_T, out.bz_T, out.dbz_dr_T_m, out.dbz_dth_T,
            centre);
    return;
  }
  // Without hints (the reference stepper), places nobody keeps: each lookup searches.
  CoilHints none;
  CoilHints& h = hints ? *hints : none;
  if (!coil_sum.empty())
    coil_sum.add_near(r_m, h.all, main.bz_T, main.dbz_dr_T_m, main.dbz_dth_T, threshold_T, out.bz_T, out.dbz_dr_T_m,
                      out.dbz_dth_T);
  for (size_t k = 0; k < window_sums.size(); ++k) {
    const WindowSum& w = window_sums[k];
    if (!coils[w.window_of].in_azimuth(th, centre)) continue;
    TrimCoilSum::Hint unkept;
    w.sum.add_near(r_m, k < kHintedWindows ? h.window[k] : unkept, main.bz_T, main.dbz_dr_T_m, main.dbz_dth_T,
                   threshold_T, out.bz_T, out.dbz_dr_T_m, out.dbz_dth_T);
  }
  for (size_t i : single_coils)
    coils[i].add(r_m, th, main.bz_T, main.dbz_dr_T_m, main.dbz_dth_T, threshold_T, out.bz_T, out.dbz_dr_T_m,
                 out.dbz_dth_T, centre);
}

void TrackModel::sum_coils(bool sum, bool windows) {
  std::vector<char> taken(coils.size(), 0);
  coil_sum = sum ? TrimCoilSum(coils, map.grid().r_min_m(), map.grid().r_max_m(), taken) : TrimCoilSum();
  window_sums.clear();
  for (size_t i = 0; sum && windows && i < coils.size(); ++i) {
    if (taken[i] || coils[i].coil().bmax_T == 0) continue;
    std::vector<size_t> same{i};
    for (size_t j = i + 1; j < coils.size(); ++j)
      if (!taken[j] && coils[j].coil().bmax_T != 0 && coils[j].same_window(coils[i])) same.push_back(j);
    if (same.size() < 2) continue;
    TrimCoilSum w(coils, same, map.grid().r_min_m(), map.grid().r_max_m());
    if (w.empty()) continue;
    for (size_t j : same) taken[j] = 1;
    window_sums.push_back({i, std::move(w)});
  }
  single_coils.clear();
  for (size_t i = 0; i < coils.size(); ++i)  // a coil at bmax 0 adds nothing
    if (!taken[i] && coils[i].coil().bmax_T != 0) single_coils.push_back(i);
  summed_for_ = coils.size();
}

void TrackModel::azimuth_terms(double th, AzimuthTerms& t) const {
  for (size_t k = 0; k < effects.harmonics.size() && k < kAzimuthHarmonics; ++k) {
    const auto& h = effects.harmonics[k];
    const double arg = h.n * (th - h.phase_rad);
    t.cos_h[k] = std::cos(arg);
    t.sin_h[k] = std::sin(arg);
  }
}

void TrackModel::harmonic_terms(size_t k, double th, const AzimuthTerms* terms, double& c, double& sn) const {
  if (terms && k < kAzimuthHarmonics) {
    c = terms->cos_h[k];
    sn = terms->sin_h[k];
    return;
  }
  const auto& h = effects.harmonics[k];
  const double arg = h.n * (th - h.phase_rad);
  c = std::cos(arg);
  sn = std::sin(arg);
}

bool TrackModel::field_with_effects(double r_m, double th, FieldSample& out, const AzimuthTerms* terms,
                                    CoilHints* hints) const {
  // A stronger sector magnet scales the map's field; the trim coils see the scaled field
  // (their threshold is on the main field), the harmonic error field comes on top of both.
  // The sector windows follow the magnets' centre line theta_c(r): the factor is a function of
  // theta - theta_c(r), so it also has an r derivative, -df theta_c'.
  double dc = 0;
  const double centre = sector_windows ? sector_centre(r_m, dc) : 0.0;
  if (!effects.sector_relative.empty()) {
    double df;
    const double f = effects.sector_factor(th - centre, df);
    out.dbz_dr_T_m = out.dbz_dr_T_m * f - out.bz_T * df * dc;
    out.dbz_dth_T = out.dbz_dth_T * f + out.bz_T * df;
    out.bz_T *= f;
  }
  const FieldSample main = out;
  add_coils(r_m, th, main, centre, out, hints);
  for (size_t k = 0; k < effects.harmonics.size(); ++k) {
    const auto& h = effects.harmonics[k];
    const double dr = r_m - h.r0_m;
    const double g = h.inv_width2 == 0 ? 1.0 : std::exp(-0.5 * dr * dr * h.inv_width2);
    double c, sn;
    harmonic_terms(k, th, terms, c, sn);
    const double b = h.amplitude_T * g * c;
    out.bz_T += b;
    out.dbz_dr_T_m -= b * dr * h.inv_width2;
    out.dbz_dth_T -= h.amplitude_T * g * h.n * sn;
  }
  return true;
}

TURNFIT_LANE_CLONES
void TrackModel::add_coils_lanes(int n, const double* r, double th, const double* centre, double* bz, double* br,
                                 double* bt, CoilHints* const* hints) const {
  if (summed_for_ != coils.size()) {  // add_coils' own fallback
    for (int l = 0; l < n; ++l) {
      const FieldSample main{bz[l], br[l], bt[l]};
      FieldSample out = main;
      add_coils(r[l], th, main, centre[l], out, hints[l]);
      bz[l] = out.bz_T;
      br[l] = out.dbz_dr_T_m;
      bt[l] = out.dbz_dth_T;
    }
    return;
  }
  // add_coils lane by lane, table by table: each lane's sums in add_coils' order, on the main
  // field as it came in (the threshold is on it).
  double mb[kMaxLanes], mbr[kMaxLanes], mbt[kMaxLanes];
  for (int l = 0; l < n; ++l) {
    mb[l] = bz[l];
    mbr[l] = br[l];
    mbt[l] = bt[l];
  }
  if (!coil_sum.empty())
    for (int l = 0; l < n; ++l)
      coil_sum.add_near(r[l], hints[l]->all, mb[l], mbr[l], mbt[l], threshold_T, bz[l], br[l], bt[l]);
  for (size_t k = 0; k < window_sums.size(); ++k) {
    const WindowSum& w = window_sums[k];
    const TrimCoilField& c = coils[w.window_of];
    for (int l = 0; l < n; ++l) {
      if (!c.in_azimuth(th, centre[l])) continue;
      TrimCoilSum::Hint unkept;
      w.sum.add_near(r[l], k < kHintedWindows ? hints[l]->window[k] : unkept, mb[l], mbr[l], mbt[l], threshold_T,
                     bz[l], br[l], bt[l]);
    }
  }
  for (size_t i : single_coils)
    for (int l = 0; l < n; ++l)
      coils[i].add(r[l], th, mb[l], mbr[l], mbt[l], threshold_T, bz[l], br[l], bt[l], centre[l]);
}

TURNFIT_LANE_CLONES
void TrackModel::add_to_main_lanes(int n, const double* r, double th, double* bz, double* br, double* bt,
                                   const AzimuthTerms* terms, CoilHints* const* hints) const {
  if (!effects.active) {
    if (coils.empty() || no_coil_field()) return;
    double centre[kMaxLanes];
    double dc;
    for (int l = 0; l < n; ++l) centre[l] = sector_windows ? sector_centre(r[l], dc) : 0.0;
    add_coils_lanes(n, r, th, centre, bz, br, bt, hints);
    return;
  }
  // field_with_effects, a stage at a time over the lanes.
  double centre[kMaxLanes], dc[kMaxLanes];
  for (int l = 0; l < n; ++l) {
    centre[l] = 0;
    dc[l] = 0;
  }
  if (sector_windows)
    for (int l = 0; l < n; ++l) centre[l] = sector_centre(r[l], dc[l]);
  if (!effects.sector_relative.empty()) {
    double f[kMaxLanes], df[kMaxLanes];
    for (int l = 0; l < n; ++l) f[l] = effects.sector_factor(th - centre[l], df[l]);
    for (int l = 0; l < n; ++l) {
      br[l] = br[l] * f[l] - bz[l] * df[l] * dc[l];
      bt[l] = bt[l] * f[l] + bz[l] * df[l];
      bz[l] *= f[l];
    }
  }
  if (!coils.empty() && !no_coil_field()) add_coils_lanes(n, r, th, centre, bz, br, bt, hints);
  for (size_t k = 0; k < effects.harmonics.size(); ++k) {
    const auto& h = effects.harmonics[k];
    double c, sn;
    harmonic_terms(k, th, terms, c, sn);
    double g[kMaxLanes];
    for (int l = 0; l < n; ++l) {
      const double dr = r[l] - h.r0_m;
      g[l] = h.inv_width2 == 0 ? 1.0 : std::exp(-0.5 * dr * dr * h.inv_width2);
    }
    for (int l = 0; l < n; ++l) {
      const double dr = r[l] - h.r0_m;
      const double b = h.amplitude_T * g[l] * c;
      bz[l] += b;
      br[l] -= b * dr * h.inv_width2;
      bt[l] -= h.amplitude_T * g[l] * h.n * sn;
    }
  }
}

TURNFIT_LANE_CLONES
void TrackModel::add_to_main_models(int n, const TrackModel* const* models, const double* r, double th, double* bz,
                                    double* br, double* bt, const AzimuthTerms* const* terms,
                                    CoilHints* const* hints) {
  // add_to_main_lanes' stages with each lane's own model (its own numbers, the same
  // expressions as field_with_effects and add_coils in the same order). (add_to_main_lanes
  // keeps its own loops: with one model its tests and tables are hoisted out of the lanes,
  // which a bunch's speed needs; here every lane looks its own up.)
  double centre[kMaxLanes] = {}, dc[kMaxLanes] = {};
  for (int l = 0; l < n; ++l)
    if (models[l]->sector_windows) centre[l] = models[l]->sector_centre(r[l], dc[l]);
  for (int l = 0; l < n; ++l) {
    const FieldEffects& e = models[l]->effects;
    if (!e.active || e.sector_relative.empty()) continue;
    double df;
    const double f = e.sector_factor(th - centre[l], df);
    br[l] = br[l] * f - bz[l] * df * dc[l];
    bt[l] = bt[l] * f + bz[l] * df;
    bz[l] *= f;
  }
  // The coils on the main field as it is now (their threshold is on it), table by table.
  double mb[kMaxLanes], mbr[kMaxLanes], mbt[kMaxLanes];
  const TrackModel* summed[kMaxLanes];  // the lane's model if its coils are summed, else nullptr
  size_t windows = 0, singles = 0;
  for (int l = 0; l < n; ++l) {
    const TrackModel& m = *models[l];
    mb[l] = bz[l];
    mbr[l] = br[l];
    mbt[l] = bt[l];
    summed[l] = nullptr;
    if (m.coils.empty() || m.no_coil_field()) continue;
    if (m.summed_for_ != m.coils.size()) {  // add_coils' own fallback
      const FieldSample main{mb[l], mbr[l], mbt[l]};
      FieldSample out = main;
      m.add_coils(r[l], th, main, centre[l], out, hints[l]);
      bz[l] = out.bz_T;
      br[l] = out.dbz_dr_T_m;
      bt[l] = out.dbz_dth_T;
      continue;
    }
    summed[l] = &m;
    windows = std::max(windows, m.window_sums.size());
    singles = std::max(singles, m.single_coils.size());
  }
  for (int l = 0; l < n; ++l)
    if (summed[l] && !summed[l]->coil_sum.empty())
      summed[l]->coil_sum.add_near(r[l], hints[l]->all, mb[l], mbr[l], mbt[l], summed[l]->threshold_T, bz[l], br[l],
                                   bt[l]);
  for (size_t k = 0; k < windows; ++k)
    for (int l = 0; l < n; ++l) {
      const TrackModel* m = summed[l];
      if (!m || k >= m->window_sums.size()) continue;
      const WindowSum& w = m->window_sums[k];
      if (!m->coils[w.window_of].in_azimuth(th, centre[l])) continue;
      TrimCoilSum::Hint unkept;
      w.sum.add_near(r[l], k < kHintedWindows ? hints[l]->window[k] : unkept, mb[l], mbr[l], mbt[l], m->threshold_T,
                     bz[l], br[l], bt[l]);
    }
  for (size_t s = 0; s < singles; ++s)
    for (int l = 0; l < n; ++l) {
      const TrackModel* m = summed[l];
      if (!m || s >= m->single_coils.size()) continue;
      m->coils[m->single_coils[s]].add(r[l], th, mb[l], mbr[l], mbt[l], m->threshold_T, bz[l], br[l], bt[l],
                                       centre[l]);
    }
  // The harmonics on top of both.
  size_t harmonics = 0;
  for (int l = 0; l < n; ++l)
    if (models[l]->effects.active) harmonics = std::max(harmonics, models[l]->effects.harmonics.size());
  for (size_t k = 0; k < harmonics; ++k) {
    double g[kMaxLanes], c[kMaxLanes], sn[kMaxLanes];
    bool on[kMaxLanes];
    for (int l = 0; l < n; ++l) {
      const FieldEffects& e = models[l]->effects;
      on[l] = e.active && k < e.harmonics.size();
      if (!on[l]) continue;
      const auto& h = e.harmonics[k];
      const double dr = r[l] - h.r0_m;
      g[l] = h.inv_width2 == 0 ? 1.0 : std::exp(-0.5 * dr * dr * h.inv_width2);
      models[l]->harmonic_terms(k, th, terms[l], c[l], sn[l]);
    }
    for (int l = 0; l < n; ++l) {
      if (!on[l]) continue;
      const auto& h = models[l]->effects.harmonics[k];
      const double dr = r[l] - h.r0_m;
      const double b = h.amplitude_T * g[l] * c[l];
      bz[l] += b;
      br[l] -= b * dr * h.inv_width2;
      bt[l] -= h.amplitude_T * g[l] * h.n * sn[l];
    }
  }
}

namespace {
std::string effect_path(size_t index, const std::string& key) {
  return "/effects/" + std::to_string(index) + (key.empty() ? "" : "/" + key);
}
}  // namespace

void apply_effects(TrackModel& t, const Effects& fx, const std::string& file, const ModelOptions& opt) {
  const int sym = t.map.grid().symmetry;
  const double pitch = 2 * kPi / sym;
  auto check_sector = [&](int k, const std::string& where) {
    if (k < 1 || k > sym)
      throw data_error(file, 0, where + ": sector " + std::to_string(k) + " out of range (1.." + std::to_string(sym) +
                                    ", the field map's sector count)");
  };
  for (const auto& h : fx.field_harmonics) {
    FieldEffects::Harmonic fh;
    fh.n = h.n;
    fh.amplitude_T = h.amplitude_T;
    fh.phase_rad = h.phase_deg * kPi / 180;
    fh.r0_m = h.r_mm * 1e-3;
    fh.inv_width2 = h.width_mm > 0 ? 1 / (h.width_mm * 1e-3 * h.width_mm * 1e-3) : 0.0;
    t.effects.harmonics.push_back(fh);
  }
  if (!fx.sector_strengths.empty()) {
    t.effects.sector_relative.assign(static_cast<size_t>(sym), 0.0);
    t.effects.pitch_rad = pitch;
    // One switch width for the whole ring: the windows must add up to 1 at every azimuth.
    double transition = 0;
    for (const auto& e : fx.sector_strengths) {
      check_sector(e.sector, effect_path(e.index, "sector"));
      if (e.transition_deg * kPi / 180 > pitch * (1 + 1e-12))
        throw data_error(file, 0, effect_path(e.index, "transition_deg") + ": must be at most the sector pitch " +
                                      std::to_string(360.0 / sym) + " deg");
      const double tr = e.transition_deg > 0 ? e.transition_deg * kPi / 180 : 0.25 * pitch;
      if (transition > 0 && std::fabs(tr - transition) > 1e-12)
        throw data_error(file, 0, effect_path(e.index, "transition_deg") +
                                      ": every sector-strength needs the same transition_deg (one switch per valley)");
      transition = tr;
      t.effects.sector_relative[static_cast<size_t>(e.sector - 1)] = e.relative;
    }
    t.effects.half_transition_rad = 0.5 * transition;
    t.effects.inv_half_transition_rad = 1 / t.effects.half_transition_rad;
    t.effects.inv_pitch_rad = 1 / pitch;
  }
  for (const auto& e : fx.trimcoil_sectors) {
    for (int k : e.sectors) check_sector(k, effect_path(e.index, "sectors"));
    for (size_t c = 0; c < e.coils.size(); ++c) {
      auto it = std::find_if(t.coils.begin(), t.coils.end(), [&](const TrimCoilField& f) { return f.name() == e.coils[c]; });
      if (it == t.coils.end())
        throw data_error(file, 0, effect_path(e.index, "coils/" + std::to_string(c)) + ": no trim coil named '" +
                                      e.coils[c] + "'");
      TrimCoil coil = it->coil();
      coil.sectors = e.sectors;
      *it = TrimCoilField(coil, sym);
      if (!opt.opal_map) it->tabulate(t.map.grid().r_min_m(), t.map.grid().r_max_m());
    }
  }
  auto gap_named = [&](const std::string& name, size_t index) -> Gap& {
    for (auto& g : t.gaps)
      if (g.name() == name) return g;
    throw data_error(file, 0, effect_path(index, "cavity") + ": no cavity named '" + name + "'");
  };
  for (const auto& e : fx.gap_bows) gap_named(e.cavity, e.index).set_bow(e.sagitta_mm * 1e-3);
  for (const auto& e : fx.voltage_tilts) gap_named(e.cavity, e.index).set_tilt(e.slope, e.pivot_rho_n);
  for (const auto& e : fx.probe_offsets) {
    auto it = std::find_if(t.probes.begin(), t.probes.end(), [&](const ProbeLine& p) { return p.name == e.probe; });
    if (it == t.probes.end())
      throw data_error(file, 0, effect_path(e.index, "probe") + ": no probe named '" + e.probe + "'");
    ProbeLine& p = *it;
    p.hidden_offset = true;
    p.a_read_m = p.a_m;
    p.shift_read_m = p.shift_m;
    const double phi1 = p.phi_rad + e.dphi_deg * kPi / 180;
    const double c1 = std::cos(phi1), s1 = std::sin(phi1);
    if (e.pivot_s_mm) {
      // Turned about its own point Q at s = pivot (paper Eq. 1 coordinates): the new line
      // passes through Q, and the scale, fixed to the probe, still reads Q as before.
      const double sq = *e.pivot_s_mm * 1e-3;
      const double qx = sq * p.cos_phi + p.a_m * p.sin_phi, qy = sq * p.sin_phi - p.a_m * p.cos_phi;
      p.a_m = qx * s1 - qy * c1;
      p.shift_m += (qx * c1 + qy * s1) - sq;
    }
    p.phi_rad = phi1;
    p.cos_phi = c1;
    p.sin_phi = s1;
    p.a_m += e.da_mm * 1e-3;
    // Moved along itself with a readout that does not know: the probe's own shift.
    p.shift_m += e.ds_mm * 1e-3;
  }
  t.effects.active = !t.effects.harmonics.empty() || !t.effects.sector_relative.empty();
}

std::vector<std::string> effects_without_opal_input(const Effects& fx) {
  std::vector<std::pair<size_t, std::string>> out;
  for (const auto& e : fx.field_harmonics)
    out.emplace_back(e.index, "field-harmonic (" + effect_path(e.index, "") + "): OPAL needs a field map with it added");
  for (const auto& e : fx.sector_strengths)
    out.emplace_back(e.index, "sector-strength (" + effect_path(e.index, "") + "): OPAL needs a field map with it applied");
  for (const auto& e : fx.gap_bows)
    out.emplace_back(e.index, "gap-bow (" + effect_path(e.index, "") + "): OPAL's single gaps are straight lines");
  for (const auto& e : fx.voltage_tilts)
    out.emplace_back(e.index, "voltage-tilt (" + effect_path(e.index, "") + "): OPAL needs a tilted profile file");
  std::sort(out.begin(), out.end());
  std::vector<std::string> lines;
  for (auto& [i, s] : out) lines.push_back(std::move(s));
  return lines;
}

namespace {

bool same_main_field(const ModelFiles& f, const Machine& m) {
  return f.map && f.map_path == m.field.map && f.map_format == m.field.format && f.map_symmetry == m.field.symmetry &&
         f.map_scale == m.field.scale;
}

/// A trim coil's field; a table coil from the files' copy of its table when they hold it.
TrimCoilField make_coil(const TrimCoil& c, const PolarFieldMap& map, const ModelFiles* files) {
  const int sym = map.grid().symmetry;
  if (files && c.type == "table" && !c.table.empty()) {
    auto it = files->coil_tables.find(c.table);
    if (it != files->coil_tables.end()) {
      TrimCoil mem = c;  // the table as read, in memory (same rows, same monotone slopes)
      mem.table.clear();
      mem.table_r_mm = it->second.r_mm;
      mem.table_shape = it->second.shape;
      return TrimCoilField(mem, sym);
    }
  }
  return TrimCoilField(c, sym);
}

}  // namespace

ModelFiles read_model_files(const Machine& m) {
  ModelFiles f;
  f.map = std::make_shared<const PolarFieldMap>(load_main_field(m));
  f.map_path = m.field.map;
  f.map_format = m.field.format;
  f.map_symmetry = m.field.symmetry;
  f.map_scale = m.field.scale;
  for (const auto& c : m.cavities)
    if (!c.profile.empty() && !f.profiles.count(c.profile)) f.profiles.emplace(c.profile, VoltageProfile::read(c.profile));
  for (const auto& c : m.trimcoils)
    if (c.type == "table" && !c.table.empty() && !f.coil_tables.count(c.table))
      f.coil_tables.emplace(c.table, read_coil_table(c.table));
  for (const auto& c : m.trimcoils) {
    f.coils.push_back(make_coil(c, *f.map, &f));
    f.coils.back().tabulate(f.map->grid().r_min_m(), f.map->grid().r_max_m());
  }
  return f;
}

TrackModel make_track_model(const Machine& m, const ModelOptions& opt, const ModelFiles* files) {
  TrackModel t;
  const bool files_map = files && same_main_field(*files, m);
  t.map = files_map ? *files->map : load_main_field(m);
  if (opt.opal_map) t.opal_map.emplace(t.map);
  for (size_t i = 0; i < m.trimcoils.size(); ++i) {
    const TrimCoil& c = m.trimcoils[i];
    // A coil the files hold already tabulated (same shape; only bmax may differ), over the same map.
    if (files_map && !opt.opal_map && i < files->coils.size() && same_shape(files->coils[i].coil(), c)) {
      t.coils.push_back(files->coils[i]);
      t.coils.back().set_bmax(c.bmax_T);
      continue;
    }
    t.coils.push_back(make_coil(c, t.map, files));
    // Lookup tables to 1e-7 of each coil's peak (1.4e-10 T for the PSI TC15), five orders
    // below the map's own precision, instead of exponentials at every field sample. The
    // OPAL-compatible model keeps OPAL's formula.
    if (!opt.opal_map) t.coils.back().tabulate(t.map.grid().r_min_m(), t.map.grid().r_max_m());
  }
  t.threshold_T = m.field.trimcoil_threshold_T;
  t.gaps = make_gaps(m, files ? &files->profiles : nullptr);
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
  if (!m.effect_set.empty()) apply_effects(t, m.effect_set, m.path.empty() ? "<machine>" : m.path, opt);
  t.sector_windows = !t.effects.sector_relative.empty();
  for (const auto& c : t.coils) t.sector_windows = t.sector_windows || !c.coil().sectors.empty();
  // A harmonic analysis of the whole map: only for models whose windows use it (an optimizer
  // builds a model per evaluation).
  if (t.sector_windows) fit_sector_centre(t);
  t.sum_coils(opt.sum_coils && !opt.opal_map, opt.sum_window_coils);
  return t;
}

}  // namespace turnfit
