// The space-charge candidate: the current-dependent part of the residuals of measurements at
// several beam currents, against the change of the bunch's centroids with space charge.
#include "turnfit/diagnose/current_dependence.hpp"

#include <Eigen/Dense>
#include <cmath>
#include <filesystem>
#include <map>
#include <set>

#include "turnfit/cli/common.hpp"
#include "turnfit/diagnose/diagnose.hpp"
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

/// The bunch's centroid radius per (probe name, turn).
using CentroidMap = std::map<std::pair<std::string, int>, double>;

CentroidMap centroid_map(const TrackModel& model, const BunchResult& r) {
  CentroidMap m;
  for (const Centroid& c : r.centroids) m[{model.probes[static_cast<size_t>(c.probe)].name, c.turn}] = c.r_mm;
  return m;
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
      h[v] = 1e-4 * (vars[v].upper - vars[v].lower);
      if (!(h[v] > 0)) h[v] = 1e-6;
      std::vector<double> up = x, dn = x;
      up[v] += h[v];
      dn[v] -= h[v];
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
        if (u.ok && d.ok && u.matched[i] && d.matched[i])
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
  const CentroidMap plain = centroid_map(model, track_bunch(model, starts, st, s.threads));
  std::vector<CentroidMap> with(K);
  json solves = json::array();
  for (size_t k = 0; k < K; ++k) {
    if (ms[k].current_uA == 0) {
      with[k] = plain;
      continue;
    }
    sc::SpaceChargeSettings scs;
    scs.current_uA = ms[k].current_uA;
    scs.grid = s.grid;
    scs.every_steps = s.every_steps;
    sc::SpaceChargeKick kick(model, scs, starts.size(), s.threads);
    CollectiveKick ck = kick.collective();
    with[k] = centroid_map(model, track_bunch(model, starts, st, s.threads, {}, {}, &ck));
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
  CurrentTest out;
  const size_t n_rows = f.points * (K - 1);
  const double threshold = s.margin + (n_rows > 1 ? std::log(static_cast<double>(n_rows)) : 0.0);
  out.named = f.points > 0 && f.gain > threshold && f.alpha > 0;
  json cur = json::array();
  for (size_t k = 0; k < K; ++k) {
    double rms = 0;
    for (double v : sig[k]) rms += v * v;
    cur.push_back({{"current_uA", ms[k].current_uA},
                   {"peaks", ms[k].peaks},
                   {"noise_mm", noise[k].scatter_mm},
                   {"signature_rms_mm", sig[k].empty() ? 0.0 : std::sqrt(rms / static_cast<double>(sig[k].size()))}});
  }
  std::string why;
  if (f.points == 0)
    why = "no turn is common to the measurements";
  else if (out.named)
    why = "the turns move with the current as the bunch's own field predicts";
  else if (f.gain_at_one < threshold)
    why = "the model's space charge at these currents is below the detection limit (it would gain " +
          cli::fmt(f.gain_at_one, 3) + " against the threshold " + cli::fmt(threshold, 3) + ")";
  else if (f.alpha <= 0)
    why = "what changes with the current goes the other way";
  else
    why = "what changes with the current is not significant";
  out.report = {{"type", "space-charge"},
                {"verdict", out.named ? "named" : "not-named"},
                {"reason", why},
                {"alpha", f.alpha},
                {"alpha_sigma", f.alpha_sigma},
                {"gain", f.gain},
                {"threshold", threshold},
                {"gain_at_model", f.gain_at_one},
                {"chi2_without", f.chi2_without},
                {"chi2_with", f.chi2_with},
                {"dof", f.dof},
                {"points", f.points},
                {"signature_max_mm", sig_max},
                {"measurements", cur},
                {"model", {{"particles", starts.size()},
                           {"grid", {s.grid.nx, s.grid.ny, s.grid.nz}},
                           {"every_steps", s.every_steps}}}};
  return out;
}

}  // namespace turnfit
