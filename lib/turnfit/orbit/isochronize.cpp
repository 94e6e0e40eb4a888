// Isochronization by Levenberg-Marquardt on the hill-field nodes of a sector field.
#include "turnfit/orbit/isochronize.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "turnfit/io/error.hpp"

namespace turnfit {
namespace {
constexpr double kC = 299792458.0;
constexpr double kPi = 3.14159265358979323846;

struct Evaluation {
  std::vector<OrbitRow> rows;
  Eigen::VectorXd rel;  ///< f_rev h / f_rf - 1 per energy
  std::string failure;  ///< the first energy without a closed orbit, if any
  double max_abs() const { return rel.size() ? rel.cwiseAbs().maxCoeff() : 0.0; }
  double rms() const { return rel.size() ? std::sqrt(rel.squaredNorm() / rel.size()) : 0.0; }
};

Evaluation evaluate(const SectorFieldSpec& spec, const OrbitSettings& s, const std::vector<double>& energies,
                    unsigned threads) {
  Evaluation e;
  e.rows = orbit_table(make_sector_field(spec), s, energies, threads);
  const double f_target = s.rf_MHz / s.harmonic;
  e.rel.resize(static_cast<Eigen::Index>(e.rows.size()));
  for (size_t k = 0; k < e.rows.size(); ++k) {
    const OrbitRow& row = e.rows[k];
    // Only the frequency matters here: an orbit with unstable betatron motion still has one.
    if (!std::isfinite(row.f_rev_MHz)) {
      if (e.failure.empty()) e.failure = std::to_string(row.energy_MeV) + " MeV: " + row.status;
      e.rel[static_cast<Eigen::Index>(k)] = 0;
      continue;
    }
    e.rel[static_cast<Eigen::Index>(k)] = row.f_rev_MHz / f_target - 1;
  }
  return e;
}

std::string fmt_line(const char* f, int it, double max_rel, double rms, double slip, double lambda) {
  char buf[200];
  std::snprintf(buf, sizeof buf, f, it, max_rel, rms, slip, lambda);
  return buf;
}

double max_slip(const std::vector<OrbitRow>& rows) {
  double m = 0;
  for (const auto& r : rows)
    if (std::isfinite(r.phase_slip_deg)) m = std::max(m, std::fabs(r.phase_slip_deg));
  return m;
}
}  // namespace

double mean_field_hill_T(const SectorFieldSpec& spec, const OrbitSettings& s, double r_mm) {
  const double omega = 2 * kPi * s.rf_MHz * 1e6 / s.harmonic;
  const double beta = omega * r_mm * 1e-3 / kC;
  if (!(beta < 1)) throw usage_error("isochronize: r = " + std::to_string(r_mm) + " mm is beyond c / omega");
  const double gamma = 1 / std::sqrt(1 - beta * beta);
  const double b0 = s.mass_MeV * 1e6 * omega / (kC * kC) / std::fabs(s.charge_e);
  // The azimuthal mean of the shape, numerically (exact for any edge and valley).
  const int n = 1440;
  const double period = 360.0 / spec.sectors;
  double sum = 0;
  for (int j = 0; j < n; ++j) sum += sector_shape(spec, r_mm, period * (j + 0.5) / n);
  const double mean_shape = spec.valley_fraction + (1 - spec.valley_fraction) * sum / n;
  return gamma * b0 / mean_shape;
}

IsochronizeResult isochronize(const SectorFieldSpec& start, const OrbitSettings& s, const IsochronizeSettings& iso,
                              unsigned threads, const std::function<void(const std::string&)>& log) {
  if (!(s.harmonic > 0 && s.rf_MHz > 0)) throw usage_error("isochronize: needs the RF harmonic and frequency");
  if (iso.energies_MeV.empty()) throw usage_error("isochronize: needs energies");
  if (!(iso.tolerance > 0)) throw usage_error("isochronize: tolerance must be > 0");
  validate_sector_spec(start);
  auto say = [&](const std::string& line) {
    if (log) log(line);
  };

  IsochronizeResult res;
  SectorFieldSpec spec = start;
  const PolarGrid& g = spec.grid;
  if (iso.node_spacing_mm > 0) {  // new nodes over the grid, values from the current table
    const double r0 = g.r_min_mm, r1 = g.r_min_mm + (g.nr - 1) * g.dr_mm;
    const int n = std::max(2, static_cast<int>(std::ceil((r1 - r0) / iso.node_spacing_mm)) + 1);
    RadialTable t;
    for (int j = 0; j < n; ++j) {
      const double r = r0 + (r1 - r0) * j / (n - 1);
      t.r_mm.push_back(r);
      t.value.push_back(spec.hill_T.at(r));
    }
    spec.hill_T = t;
  }
  if (iso.start_from_mean_field)
    for (size_t j = 0; j < spec.hill_T.r_mm.size(); ++j) spec.hill_T.value[j] = mean_field_hill_T(spec, s, spec.hill_T.r_mm[j]);

  const std::vector<double>& E = iso.energies_MeV;
  Evaluation cur = evaluate(spec, s, E, threads);
  if (!cur.failure.empty())
    throw Error(ExitCode::data, "isochronize: the starting field has no closed orbit at " + cur.failure);
  res.history.push_back({0, cur.max_abs(), cur.rms(), max_slip(cur.rows), 0});
  say(fmt_line("isochronize: start     max |df/f| %9.3e  rms %9.3e  max slip %8.4f deg/turn", 0, cur.max_abs(),
               cur.rms(), max_slip(cur.rows), 0));

  const int n = static_cast<int>(spec.hill_T.value.size());
  const int m = static_cast<int>(E.size());
  // Smoothness rows: second differences of the correction in ln B_hill, scaled to the node
  // spacing so the penalty means the same for any spacing.
  const int nd = std::max(0, n - 2);
  Eigen::MatrixXd D = Eigen::MatrixXd::Zero(nd, n);
  for (int j = 0; j < nd; ++j) D(j, j) = 1, D(j, j + 1) = -2, D(j, j + 2) = 1;
  const double w_smooth = std::sqrt(iso.smoothing);
  double lambda = 1e-3;
  for (int it = 1; it <= iso.max_iterations && cur.max_abs() > iso.tolerance; ++it) {
    // Jacobian d rel_k / d ln B_j by forward differences.
    Eigen::MatrixXd J(m, n);
    const double h = 1e-5;
    for (int j = 0; j < n; ++j) {
      SectorFieldSpec p = spec;
      p.hill_T.value[static_cast<size_t>(j)] *= std::exp(h);
      Evaluation e = evaluate(p, s, E, threads);
      if (!e.failure.empty())
        throw Error(ExitCode::data, "isochronize: a node change of 1e-5 lost the closed orbit at " + e.failure);
      J.col(j) = (e.rel - cur.rel) / h;
    }
    const Eigen::MatrixXd JtJ = J.transpose() * J;
    const Eigen::VectorXd g_vec = J.transpose() * cur.rel;
    const double scale = JtJ.diagonal().maxCoeff();
    const Eigen::MatrixXd R = w_smooth * w_smooth * scale * (D.transpose() * D);
    bool accepted = false;
    for (int tries = 0; tries < 12 && !accepted; ++tries) {
      Eigen::MatrixXd A = JtJ + R;
      A.diagonal() += lambda * (JtJ.diagonal().array() + 1e-12 * scale).matrix();
      const Eigen::VectorXd step = -A.ldlt().solve(g_vec);
      SectorFieldSpec trial = spec;
      for (int j = 0; j < n; ++j) trial.hill_T.value[static_cast<size_t>(j)] *= std::exp(step[j]);
      Evaluation e;
      bool usable = true;
      try {  // make_sector_field validates the trial (a width gone out of range is no step)
        e = evaluate(trial, s, E, threads);
        usable = e.failure.empty();
      } catch (const Error&) {
        usable = false;
      }
      if (usable && e.rel.squaredNorm() < cur.rel.squaredNorm()) {
        spec = trial;
        cur = std::move(e);
        lambda = std::max(lambda / 10, 1e-9);
        accepted = true;
      } else {
        lambda *= 10;
      }
    }
    if (!accepted) {
      say("isochronize: no step reduces the frequency error any more");
      break;
    }
    res.history.push_back({it, cur.max_abs(), cur.rms(), max_slip(cur.rows), lambda});
    say(fmt_line("isochronize: iter %3d  max |df/f| %9.3e  rms %9.3e  max slip %8.4f deg/turn  (lambda %.0e)", it,
                 cur.max_abs(), cur.rms(), max_slip(cur.rows), lambda));
  }
  res.converged = cur.max_abs() <= iso.tolerance;
  res.spec = spec;
  res.rows = std::move(cur.rows);
  return res;
}

}  // namespace turnfit
