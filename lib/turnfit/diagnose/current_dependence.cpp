// The space-charge candidate: the current-dependent part of the residuals of measurements at
// several beam currents, against the change of the bunch's centroids with space charge.
#include "turnfit/diagnose/current_dependence.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <set>

#include "turnfit/cli/common.hpp"
#include "turnfit/diagnose/diagnose.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/spacecharge/space_charge.hpp"
#include "turnfit/track/bunch.hpp"

namespace turnfit {

CurrentFit fit_current_dependence(const std::vector<std::vector<double>>& y,
                                  const std::vector<std::vector<double>>& sigma,
                                  const std::vector<std::vector<std::vector<double>>>& J,
                                  const std::vector<std::vector<double>>& sig) {
  CurrentFit f;
  const size_t K = y.size(), M = K ? y[0].size() : 0, nv = (K && M) ? J[0][0].size() : 0;
  f.points = M;
  if (K < 2 || M == 0) return f;
  // A per-point error common to every measurement (m_i) is profiled out: for each point the
  // rows are centred on their weighted mean over the measurements, which leaves the chi2 of the
  // best m_i. The design variables move by their own amounts in each measurement (delta_k; the
  // first one's goes into m_i with the rest of what the measurements share).
  const size_t rows = K * M, ncol = (K - 1) * nv;
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(rows), static_cast<Eigen::Index>(ncol));
  Eigen::VectorXd b(static_cast<Eigen::Index>(rows)), s(static_cast<Eigen::Index>(rows));
  for (size_t i = 0; i < M; ++i) {
    double W = 0, ym = 0, sm = 0;
    for (size_t k = 0; k < K; ++k) {
      const double w = 1 / (sigma[k][i] * sigma[k][i]);
      W += w;
      ym += w * y[k][i];
      sm += w * sig[k][i];
    }
    ym /= W;
    sm /= W;
    for (size_t k = 0; k < K; ++k) {
      const double sw = 1 / sigma[k][i];
      const auto r = static_cast<Eigen::Index>(k * M + i);
      b(r) = sw * (y[k][i] - ym);
      s(r) = sw * (sig[k][i] - sm);
      for (size_t j = 1; j < K; ++j) {
        const double wj = 1 / (sigma[j][i] * sigma[j][i]);
        const double c = (k == j ? 1.0 : 0.0) - wj / W;
        for (size_t v = 0; v < nv; ++v) A(r, static_cast<Eigen::Index>((j - 1) * nv + v)) = sw * c * J[j][i][v];
      }
    }
  }
  // Residuals of b and s after the design variables' columns (a rank-revealing QR: the columns
  // of a variable the measurements do not see are dependent).
  Eigen::VectorXd rb = b, rs = s;
  size_t rank = 0;
  if (ncol > 0) {
    Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(A);
    qr.setThreshold(1e-10);
    rank = static_cast<size_t>(qr.rank());
    rb = b - A * qr.solve(b);
    rs = s - A * qr.solve(s);
  }
  const double ss = rs.squaredNorm(), sb = rs.dot(rb);
  f.chi2_without = rb.squaredNorm();
  f.gain_at_one = ss;
  const size_t dof_rows = (K - 1) * M;
  f.dof = dof_rows > rank + 1 ? dof_rows - rank - 1 : 0;
  if (!(ss > 0)) {
    f.chi2_with = f.chi2_without;
    return f;
  }
  f.alpha = sb / ss;
  f.gain = sb * sb / ss;
  f.chi2_with = f.chi2_without - f.gain;
  // The error of alpha, inflated by the fit's chi2 per degree of freedom when that exceeds 1
  // (the noise estimate was too small, or something else changes with the current).
  const double scale = f.dof > 0 ? std::max(1.0, f.chi2_with / static_cast<double>(f.dof)) : 1.0;
  f.alpha_sigma = std::sqrt(scale / ss);
  return f;
}

namespace {

/// The bunch's centroid radius (or its rms width) per (probe name, turn), of the crossings every
/// particle made (near the end of a run a wide bunch's outer particles may not have reached the
/// probe yet: a partial turn's mean and width are another bunch's).
using CentroidMap = std::map<std::pair<std::string, int>, double>;

CentroidMap centroid_map(const TrackModel& model, const BunchResult& r, bool width = false) {
  CentroidMap m;
  for (const Centroid& c : r.centroids)
    if (c.particles == r.particles)
      m[{model.probes[static_cast<size_t>(c.probe)].name, c.turn}] = width ? c.r_rms_mm : c.r_mm;
  return m;
}

/// A peak's fitted rms width per (probe, turn) from peaks files (turnfit-peakfind's width_mm),
/// left out when flagged merged, wide, weak or at the edge (such a width is its neighbours' as
/// well, or no width at all); "cross" (deblended from an overlapping neighbour) and
/// "ambiguous" keep theirs: at mA currents on ring8 every turn of RRL overlaps its neighbours.
CentroidMap measured_widths(const std::vector<std::string>& files) {
  CentroidMap m;
  for (const auto& f : files) {
    const CsvTable t = CsvTable::read(f);
    if (!t.has_column("width_mm"))
      throw data_error(f, 0, "no width_mm column: the space-charge candidate compares the turns' widths "
                             "(turnfit-peakfind writes them)");
    t.require_columns({"probe", "turn"});
    const size_t cp = t.column("probe"), ct = t.column("turn"), cw = t.column("width_mm");
    const bool flags = t.has_column("flag");
    const size_t cf = flags ? t.column("flag") : 0;
    for (size_t i = 0; i < t.rows(); ++i) {
      if (flags) {
        const std::string& fl = t.cell(i, cf);
        bool bad = false;
        for (const char* word : {"merged", "wide", "weak", "edge"}) bad = bad || fl.find(word) != std::string::npos;
        if (bad) continue;
      }
      const double turn = t.number(i, ct), w = t.number(i, cw);
      if (turn != std::floor(turn) || !(w > 0)) continue;
      m[{t.cell(i, cp), static_cast<int>(turn)}] = w;
    }
  }
  return m;
}

/// The noise of a series taken turn by turn (per probe), from its second differences along
/// consecutive turns: for independent errors var(d) = 6 sigma^2, and the median of d^2 / var(d)
/// is chi2(1)'s, 0.4549 (robust to single bad points). Per probe name; probes with fewer than
/// 8 second differences get none.
std::map<std::string, double> series_noise(const CentroidMap& v) {
  std::map<std::string, std::vector<double>> d2;
  for (auto it = v.begin(); it != v.end(); ++it) {
    auto a = it, b = std::next(it);
    if (b == v.end()) break;
    auto c = std::next(b);
    if (c == v.end()) break;
    if (a->first.first != c->first.first || b->first.second != a->first.second + 1 ||
        c->first.second != b->first.second + 1)
      continue;
    const double d = a->second - 2 * b->second + c->second;
    d2[a->first.first].push_back(d * d);
  }
  std::map<std::string, double> out;
  for (auto& [probe, x] : d2) {
    if (x.size() < 8) continue;
    std::nth_element(x.begin(), x.begin() + static_cast<long>(x.size() / 2), x.end());
    out[probe] = std::sqrt(x[x.size() / 2] / 0.4549 / 6);
  }
  return out;
}

}  // namespace

CurrentTest space_charge_candidate(const TurnPatternProblem& p, const nlohmann::json& problem_json,
                                   const std::string& dir, const std::vector<double>& x,
                                   const std::vector<CurrentMeasurement>& ms, const CurrentTestSettings& s) {
  using nlohmann::json;
  if (ms.size() < 2)
    throw usage_error("the space-charge candidate needs measurements at two or more currents (--measured-at "
                      "I=PEAKS, at least twice)");
  {
    std::set<double> seen;
    for (const auto& m : ms) {
      if (!(m.current_uA >= 0)) throw usage_error("--measured-at: a current must be >= 0 uA");
      if (!seen.insert(m.current_uA).second)
        throw usage_error("--measured-at: two measurements at " + cli::fmt(m.current_uA) +
                          " uA (the candidate compares different currents)");
    }
  }
  const size_t K = ms.size(), nv = x.size();
  // Each measurement as a problem of its own: the same machine, variables and objectives.
  std::vector<std::unique_ptr<TurnPatternProblem>> probs;
  for (const auto& m : ms) {
    json j = problem_json;
    j["peaks"] = json::array();
    for (const auto& f : m.peaks) j["peaks"].push_back(std::filesystem::absolute(f).string());
    probs.push_back(TurnPatternProblem::from_json(j, m.peaks[0], dir));
    probs.back()->set_centroid_shift(p.current_centroid_shift());
  }
  // Residuals (measured minus model) at x and their derivatives, by central differences.
  std::vector<TurnPatternResult> at(K);
  std::vector<std::vector<std::vector<double>>> jac(K);  // [k][point][variable]
  std::vector<NoiseEstimate> noise(K);
  const auto& vars = p.variables();
  for (size_t k = 0; k < K; ++k) {
    std::vector<std::vector<double>> xs{x};
    std::vector<double> h(nv);
    for (size_t v = 0; v < nv; ++v) {
      const double step = std::max(1e-4 * (vars[v].upper - vars[v].lower), 1e-9);
      // Inside the bounds (a fit may end on one): one-sided there, h the span taken.
      std::vector<double> up = x, dn = x;
      up[v] = std::min(x[v] + step, vars[v].upper);
      dn[v] = std::max(x[v] - step, vars[v].lower);
      h[v] = 0.5 * (up[v] - dn[v]);
      xs.push_back(up);
      xs.push_back(dn);
    }
    const std::vector<TurnPatternResult> r = probs[k]->simulate_many(xs, s.threads);
    if (!r[0].ok) throw data_error(ms[k].peaks[0], 0, "the design cannot be simulated: " + r[0].reason);
    at[k] = r[0];
    const size_t n = r[0].delta_mm.size();
    jac[k].resize(n);
    for (auto& row : jac[k]) row.assign(nv, 0.0);
    for (size_t v = 0; v < nv; ++v) {
      const TurnPatternResult &u = r[1 + 2 * v], &d = r[2 + 2 * v];
      for (size_t i = 0; i < n; ++i)
        if (h[v] > 0 && u.ok && d.ok && u.matched[i] && d.matched[i])
          jac[k][i][v] = -(u.delta_mm[i] - d.delta_mm[i]) / (2 * h[v]);
        else
          jac[k][i][v] = std::nan("");
    }
    std::vector<double> resid(n);
    for (size_t i = 0; i < n; ++i) resid[i] = -at[k].delta_mm[i];
    noise[k] = estimate_noise(probs[k]->measured(), resid, at[k].matched, probs[k]->scan_noise());
  }
  // The signature: the bunch's centroids with space charge at each current minus without, the
  // same particles, at design x.
  const Machine mach = p.machine_at(x);
  if (!mach.bunch || (mach.bunch->emittance_r_mm_mrad == 0 && mach.bunch->emittance_z_mm_mrad == 0 &&
                      mach.bunch->sigma_E_MeV == 0 && mach.bunch->sigma_phase_deg == 0 && mach.bunch->file.empty()))
    throw data_error(p.file(), 0, "machine: " + mach.path + ": /bunch: the space-charge candidate tracks the bunch, "
                                  "and the machine has none with spread");
  const TrackModel model = make_track_model(mach);
  const Injection inj = effective_injection(mach);
  std::vector<ParticleState> starts;
  if (!mach.bunch->file.empty()) {
    const BunchFile bf = read_bunch_file(mach.bunch->file);
    starts = offset_states(inj, mach.particle.mass_MeV, model.rf_MHz, bf, s.particles);
  } else {
    starts = offset_states(inj, mach.particle.mass_MeV, model.rf_MHz, gaussian_bunch(*mach.bunch, s.particles, s.seed));
  }
  TrackSettings st = p.track_settings();
  st.reference_stepper = false;
  st.integrator = "azimuth";
  const BunchResult plain_run = track_bunch(model, starts, st, s.threads);
  const CentroidMap plain = centroid_map(model, plain_run), plain_w = centroid_map(model, plain_run, true);
  std::vector<CentroidMap> with(K), with_w(K);
  json solves = json::array();
  for (size_t k = 0; k < K; ++k) {
    if (ms[k].current_uA == 0) {
      with[k] = plain;
      with_w[k] = plain_w;
      continue;
    }
    sc::SpaceChargeSettings scs;
    scs.current_uA = ms[k].current_uA;
    scs.grid = s.grid;
    scs.every_steps = s.every_steps;
    sc::SpaceChargeKick kick(model, scs, starts.size(), s.threads);
    CollectiveKick ck = kick.collective();
    const BunchResult r = track_bunch(model, starts, st, s.threads, {}, {}, &ck);
    with[k] = centroid_map(model, r);
    with_w[k] = centroid_map(model, r, true);
  }
  // The points every measurement has (the same probe and turn), matched, not an outlier, with
  // a finite Jacobian row and a signature at every current.
  std::vector<std::vector<double>> y(K), sigma(K), sig(K);
  std::vector<std::vector<std::vector<double>>> J(K);
  std::vector<std::map<std::pair<std::string, int>, size_t>> index(K);
  for (size_t k = 0; k < K; ++k) {
    const TurnTable& t = probs[k]->measured();
    for (size_t i = 0; i < t.points.size(); ++i)
      index[k][{t.probes[static_cast<size_t>(t.points[i].probe)], t.points[i].turn}] = i;
  }
  double sig_max = 0;
  for (const auto& [key, i0] : index[0]) {
    std::vector<size_t> idx(K);
    bool ok = true;
    for (size_t k = 0; k < K && ok; ++k) {
      auto it = index[k].find(key);
      ok = it != index[k].end();
      if (!ok) break;
      const size_t i = it->second;
      idx[k] = i;
      ok = at[k].matched[i] && !noise[k].outlier[i] && with[k].count(key) && plain.count(key) &&
           std::isfinite(noise[k].sigma_mm[i]) && noise[k].sigma_mm[i] > 0;
      for (size_t v = 0; v < nv && ok; ++v) ok = std::isfinite(jac[k][i][v]);
    }
    if (!ok) continue;
    for (size_t k = 0; k < K; ++k) {
      const size_t i = idx[k];
      y[k].push_back(-at[k].delta_mm[i]);
      sigma[k].push_back(noise[k].sigma_mm[i]);
      J[k].push_back(jac[k][i]);
      const double d = with[k].at(key) - plain.at(key);
      sig[k].push_back(d);
      sig_max = std::max(sig_max, std::fabs(d));
    }
  }
  const CurrentFit f = fit_current_dependence(y, sigma, J, sig);
  const size_t n_rows = f.points * (K - 1);
  const double threshold = s.margin + (n_rows > 1 ? std::log(static_cast<double>(n_rows)) : 0.0);

  // The widths: what space charge changes most. A turn's measured width squared is the bunch's
  // rms width squared plus what the wire and the peak fit add (the same at every current: it
  // drops out with the per-turn common term), so the widths' squares are compared with the
  // model's rms widths squared, and no design variable enters (a run's drift moves the turns,
  // it hardly widens them).
  std::vector<CentroidMap> wm(K);
  std::vector<std::map<std::string, double>> wnoise(K);
  for (size_t k = 0; k < K; ++k) {
    for (const auto& [key, w] : measured_widths(ms[k].peaks)) wm[k][key] = w * w;
    wnoise[k] = series_noise(wm[k]);
  }
  std::vector<std::vector<double>> wy(K), wsig(K), wsg(K);
  std::vector<std::vector<std::vector<double>>> wJ(K);
  double wsig_max = 0;
  for (const auto& [key, v0] : wm[0]) {
    bool ok = true;
    for (size_t k = 0; k < K && ok; ++k)
      ok = wm[k].count(key) && wnoise[k].count(key.first) && wnoise[k].at(key.first) > 0 && with_w[k].count(key);
    if (!ok) continue;
    for (size_t k = 0; k < K; ++k) {
      wy[k].push_back(wm[k].at(key));
      wsg[k].push_back(wnoise[k].at(key.first));
      wJ[k].emplace_back();
      const double model_w = with_w[k].at(key);
      wsig[k].push_back(model_w * model_w);
      wsig_max = std::max(wsig_max, std::fabs(model_w * model_w - wsig[0].back()));
    }
    (void)v0;
  }
  const CurrentFit fw = fit_current_dependence(wy, wsg, wJ, wsig);
  const size_t w_rows = fw.points * (K - 1);
  const double w_threshold = s.margin + (w_rows > 1 ? std::log(static_cast<double>(w_rows)) : 0.0);
  // Named when the widths change with the current, significantly, by the bunch's own field's
  // amount within a factor of 3 (beta: the measured change over the model's; the peak fit's
  // width is not exactly the bunch's rms).
  const bool significant = fw.points > 0 && fw.gain > w_threshold;
  const bool sized = fw.alpha > 1.0 / 3 && fw.alpha < 3;
  CurrentTest out;
  out.named = significant && sized;
  json cur = json::array();
  for (size_t k = 0; k < K; ++k) {
    double rms = 0;
    for (double v : sig[k]) rms += v * v;
    json wn = json::object();
    for (const auto& [probe, v] : wnoise[k]) wn[probe] = v;
    cur.push_back({{"current_uA", ms[k].current_uA},
                   {"peaks", ms[k].peaks},
                   {"noise_mm", noise[k].scatter_mm},
                   {"width2_noise_mm2", wn},
                   {"signature_rms_mm", sig[k].empty() ? 0.0 : std::sqrt(rms / static_cast<double>(sig[k].size()))}});
  }
  std::string why;
  if (fw.points == 0)
    why = "no turn has a usable width in every measurement";
  else if (out.named)
    why = "the turns widen with the current as the bunch's own field widens them";
  else if (significant)
    why = "the turns' widths change with the current, but by " + cli::fmt(fw.alpha, 3) +
          " times what the bunch's own field gives: something else changes with the current";
  else if (fw.gain_at_one < w_threshold)
    why = "the model's space charge at these currents is below the detection limit (its widths would gain " +
          cli::fmt(fw.gain_at_one, 3) + " against the threshold " + cli::fmt(w_threshold, 3) + ")";
  else
    why = "the turns' widths do not change with the current as the bunch's own field would change them";
  out.report = {{"type", "space-charge"},
                {"verdict", out.named ? "named" : "not-named"},
                {"reason", why},
                {"alpha", fw.alpha},
                {"alpha_sigma", fw.alpha_sigma},
                {"gain", fw.gain},
                {"threshold", w_threshold},
                {"gain_at_model", fw.gain_at_one},
                {"chi2_without", fw.chi2_without},
                {"chi2_with", fw.chi2_with},
                {"dof", fw.dof},
                {"points", fw.points},
                {"signature_max_mm2", wsig_max},
                {"centroids",
                 {{"alpha", f.alpha},
                  {"alpha_sigma", f.alpha_sigma},
                  {"gain", f.gain},
                  {"threshold", threshold},
                  {"gain_at_model", f.gain_at_one},
                  {"dof", f.dof},
                  {"points", f.points},
                  {"signature_max_mm", sig_max}}},
                {"measurements", cur},
                {"model", {{"particles", starts.size()},
                           {"grid", {s.grid.nx, s.grid.ny, s.grid.nz}},
                           {"every_steps", s.every_steps}}}};
  return out;
}

}  // namespace turnfit
