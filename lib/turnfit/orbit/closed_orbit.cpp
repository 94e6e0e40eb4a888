// Closed-orbit finder: Newton on the one-sector map with its transfer matrices (RK4,
// azimuth as independent variable, steps aligned with the map grid; physics.md).
#include "turnfit/orbit/closed_orbit.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <limits>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/physics/azimuth_eom.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {
namespace {

constexpr int kN = 12;  // r, x=pr/p, t, Mr (4), Mz (4), integral of r
using State = std::array<double, kN>;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// Equations of motion in the midplane with azimuth as the independent variable, and
/// the linearized radial and vertical motion around the orbit (physics.md; the vertical
/// force uses Br = z dBz/dr and Btheta = (z/r) dBz/dtheta, first order in z).
struct SectorRhs {
  const PolarFieldMap& map;
  double inv_brho;  // sign(q) / Brho [1/(T m)]
  double inv_v;     // 1 / speed [s/m]
  double lost_r = 0;

  bool operator()(double th, const State& y, State& dy) {
    const double r = y[0], x = y[1];
    FieldSample f;
    if (!map.sample(r, th, f)) {
      lost_r = r;
      return false;
    }
    AzimuthDerivs d;
    if (!azimuth_eom(r, x, 0, 0, f, inv_brho, inv_v, d)) {  // the orbit lies in the midplane
      lost_r = r;
      return false;
    }
    const double s = d.s, b = d.b, br = d.br, bt = d.bt;
    dy[0] = d.dr;
    dy[1] = d.dx;
    dy[2] = d.dt;
    // Radial Jacobian d(dr, dx)/d(r, x).
    const double j00 = x / s, j01 = r / (s * s * s), j10 = -(b + r * br), j11 = -x / s;
    dy[3] = j00 * y[3] + j01 * y[5];
    dy[4] = j00 * y[4] + j01 * y[6];
    dy[5] = j10 * y[3] + j11 * y[5];
    dy[6] = j10 * y[4] + j11 * y[6];
    // Vertical Jacobian d(dz, dxz)/d(z, xz).
    const double k01 = r / s, k10 = r * br - (x / s) * bt;
    dy[7] = k01 * y[9];
    dy[8] = k01 * y[10];
    dy[9] = k10 * y[7];
    dy[10] = k10 * y[8];
    dy[11] = r;
    return true;
  }
};

/// Integrates one sector from theta0 with fixed RK4 steps, `per_cell` steps in each
/// map cell (partial cells at the ends), so no step straddles an azimuthal grid line
/// where the interpolant's third derivative jumps.
bool integrate_sector(SectorRhs& rhs, const PolarGrid& g, double theta0, int per_cell, State& y) {
  const double dth = g.dtheta_rad();
  const double span = 2 * kPi / g.symmetry;
  const double th_min = g.theta_min_rad();
  // Grid lines strictly inside (theta0, theta0 + span).
  double k0 = std::floor((theta0 - th_min) / dth + 1e-9) + 1;
  std::vector<double> breaks;
  breaks.reserve(static_cast<size_t>(g.ntheta) + 2);
  breaks.push_back(theta0);
  for (double k = k0;; k += 1) {
    double th = th_min + k * dth;
    if (th >= theta0 + span - 1e-9 * dth) break;
    if (th > theta0 + 1e-9 * dth) breaks.push_back(th);
  }
  breaks.push_back(theta0 + span);
  State k1, k2, k3, k4, tmp;
  for (size_t b = 0; b + 1 < breaks.size(); ++b) {
    const double h = (breaks[b + 1] - breaks[b]) / per_cell;
    for (int n = 0; n < per_cell; ++n) {
      const double th = breaks[b] + n * h;
      if (!rhs(th, y, k1)) return false;
      for (int i = 0; i < kN; ++i) tmp[i] = y[i] + 0.5 * h * k1[i];
      if (!rhs(th + 0.5 * h, tmp, k2)) return false;
      for (int i = 0; i < kN; ++i) tmp[i] = y[i] + 0.5 * h * k2[i];
      if (!rhs(th + 0.5 * h, tmp, k3)) return false;
      for (int i = 0; i < kN; ++i) tmp[i] = y[i] + h * k3[i];
      if (!rhs(th + h, tmp, k4)) return false;
      for (int i = 0; i < kN; ++i) y[i] += h / 6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]);
    }
  }
  return true;
}

/// Radius where Brho = r <Bz>(r) (the orbit of the azimuthally averaged field), by
/// scanning the grid radii; NaN if the averaged field never bends the particle there.
double average_field_radius(const PolarFieldMap& map, double brho_signed) {
  const PolarGrid& g = map.grid();
  double prev = kNaN, prev_r = kNaN;
  for (int i = 0; i < g.nr; ++i) {
    const double r = g.r_min_m() + i * g.dr_m();
    const double val = r * map.average(i) - brho_signed;
    if (i > 0 && prev < 0 && val >= 0) return prev_r + (r - prev_r) * (-prev) / (val - prev);
    prev = val;
    prev_r = r;
  }
  return kNaN;
}

std::string mm_text(double r_m) { return std::to_string(static_cast<long long>(std::llround(r_m * 1e3))); }

std::string cli_text(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.5g", v);
  return buf;
}

}  // namespace

namespace {

/// Newton iteration for the fixed point of the one-sector map from (r0, x0).
OrbitRow solve_orbit(const PolarFieldMap& map, const OrbitSettings& s, double energy_MeV, double r0, double x0) {
  OrbitRow row;
  row.energy_MeV = energy_MeV;
  row.r_mm = row.pr_mrad = row.nu_r = row.nu_z = row.f_rev_MHz = row.phase_slip_deg = row.r_avg_mm = kNaN;
  const Kinematics kin = kinematics(s.mass_MeV, s.charge_e, energy_MeV);
  const double sign = s.charge_e >= 0 ? 1.0 : -1.0;
  const PolarGrid& g = map.grid();
  const double theta0 = s.azimuth_deg * kPi / 180;
  SectorRhs rhs{map, sign / kin.brho_Tm, 1 / kin.v_m_s};
  const double span = 2 * kPi / g.symmetry;
  const double tol = s.tolerance_mm * 1e-3;
  State y{};
  bool converged = false;
  for (int it = 0; it < s.max_iterations; ++it) {
    y = State{r0, x0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
    if (!integrate_sector(rhs, g, theta0, s.steps_per_cell, y)) {
      row.status = "lost: the orbit leaves the map at r = " + mm_text(rhs.lost_r) + " mm";
      return row;
    }
    // Newton on F(r0, x0) = end - start with Jacobian M - I.
    const double f0 = y[0] - r0, f1 = y[1] - x0;
    const double a = y[3] - 1, b = y[4], c = y[5], d = y[6] - 1;
    const double det = a * d - b * c;
    if (!(std::fabs(det) > 1e-14)) {
      row.status = "no closed orbit: singular one-sector matrix (integer resonance)";
      return row;
    }
    double dr = -(d * f0 - b * f1) / det;
    double dx = -(-c * f0 + a * f1) / det;
    // Damp large steps: far from the orbit the linearization is poor.
    const double max_dr = 0.05;
    if (std::fabs(dr) > max_dr) {
      const double k = max_dr / std::fabs(dr);
      dr *= k;
      dx *= k;
    }
    if (std::fabs(dr) < tol && std::fabs(dx) < tol) {
      // Converged: the optics of this pass belong to an orbit within tol of the fixed
      // point, closer than any effect they could show, so no extra pass is needed.
      r0 += dr;
      x0 += dx;
      converged = true;
      break;
    }
    r0 += dr;
    x0 += dx;
  }
  if (!converged) {
    row.status = "no closed orbit: Newton did not converge in " + std::to_string(s.max_iterations) + " iterations";
    return row;
  }
  row.r_mm = r0 * 1e3;
  row.pr_mrad = x0 * 1e3;
  row.r_avg_mm = y[11] / span * 1e3;
  const double t_rev = y[2] * g.symmetry;
  row.f_rev_MHz = 1e-6 / t_rev;
  if (s.harmonic > 0 && s.rf_MHz > 0) row.phase_slip_deg = 360.0 * (s.rf_MHz * 1e6 * t_rev - s.harmonic);
  // nu = (N / 2 pi) acos(trace(M) / 2), valid for nu < N / 2 (physics.md).
  const double half_tr_r = 0.5 * (y[3] + y[6]);
  const double half_tr_z = 0.5 * (y[7] + y[10]);
  // |trace/2| = 1 within round-off is marginal stability (nu = 0 or N/2, e.g. the
  // vertical drift in a uniform field), not instability.
  auto tune = [&](double half_tr) {
    if (std::fabs(half_tr) > 1 + 1e-9) return kNaN;
    return g.symmetry / (2 * kPi) * std::acos(std::clamp(half_tr, -1.0, 1.0));
  };
  row.nu_r = tune(half_tr_r);
  row.nu_z = tune(half_tr_z);
  std::string unstable;
  if (std::isnan(row.nu_r)) unstable = "radial";
  if (std::isnan(row.nu_z)) unstable += unstable.empty() ? "vertical" : " and vertical";
  if (!unstable.empty()) row.status = "unstable " + unstable + " motion (|trace/2| > 1)";
  return row;
}

/// Kinetic energy [MeV] with rigidity brho [T m].
double energy_for_brho(const OrbitSettings& s, double brho) {
  const double p_MeV = brho * kSpeedOfLight * std::fabs(s.charge_e) * 1e-6;
  return std::sqrt(p_MeV * p_MeV + s.mass_MeV * s.mass_MeV) - s.mass_MeV;
}

}  // namespace

OrbitRow closed_orbit(const PolarFieldMap& map, const OrbitSettings& s, double energy_MeV,
                      std::optional<std::pair<double, double>> guess) {
  if (guess) return solve_orbit(map, s, energy_MeV, guess->first, guess->second);
  const Kinematics kin = kinematics(s.mass_MeV, s.charge_e, energy_MeV);
  const double sign = s.charge_e >= 0 ? 1.0 : -1.0;
  const PolarGrid& g = map.grid();
  const double r_avg = average_field_radius(map, sign * kin.brho_Tm);
  OrbitRow row;
  if (std::isnan(r_avg)) {
    row.energy_MeV = energy_MeV;
    row.r_mm = row.pr_mrad = row.nu_r = row.nu_z = row.f_rev_MHz = row.phase_slip_deg = row.r_avg_mm = kNaN;
    row.status = "no closed orbit: Brho = " + cli_text(kin.brho_Tm) + " T m is beyond r <Bz> of the map between r = " +
                 mm_text(g.r_min_m()) + " and " + mm_text(g.r_max_m()) + " mm" +
                 (sign * map.average(g.nr / 2) < 0 ? " (the field bends the other way: flip its sign)" : "");
  } else {
    row = solve_orbit(map, s, energy_MeV, r_avg, 0);
    if (std::isfinite(row.r_mm) || row.status.rfind("lost", 0) != 0) return row;
  }
  // Near the edge of the map the scalloped orbit started from the average radius can
  // leave the map before Newton gets going, and where the field falls off the averaged
  // field is a poor guide (closed orbits exist beyond max r<Bz>): continue in energy
  // from an orbit well inside the map instead, one small rigidity step at a time.
  const double r_lo = g.r_min_m() + 0.3 * (g.r_max_m() - g.r_min_m());
  const double brho_lo = r_lo * sign * map.average_at(r_lo);
  if (!(brho_lo > 0) || !(brho_lo < kin.brho_Tm)) return row;
  const int steps = 60;
  std::optional<std::pair<double, double>> prev, prev2;
  OrbitRow cur;
  for (int k = 0; k <= steps; ++k) {
    const double e = k == steps ? energy_MeV : energy_for_brho(s, brho_lo + (kin.brho_Tm - brho_lo) * k / steps);
    std::pair<double, double> start;
    if (prev && prev2) start = {2 * prev->first - prev2->first, 2 * prev->second - prev2->second};
    else if (prev) start = *prev;
    else start = {r_lo, 0};
    cur = solve_orbit(map, s, e, start.first, start.second);
    if (!std::isfinite(cur.r_mm)) {
      if (k == steps) return cur;
      if (std::isnan(r_avg)) row.status += "; continuation from lower energies fails at " + cli_text(e) + " MeV (" + cur.status + ")";
      return row;
    }
    prev2 = prev;
    prev = std::make_pair(cur.r_mm * 1e-3, cur.pr_mrad * 1e-3);
  }
  return cur;
}

std::vector<OrbitRow> orbit_table(const PolarFieldMap& map, const OrbitSettings& s,
                                  const std::vector<double>& energies, unsigned threads,
                                  void (*progress)(size_t, size_t)) {
  const size_t n = energies.size();
  std::vector<OrbitRow> rows(n);
  constexpr size_t kChunk = 32;  // fixed, so results do not depend on the thread count
  const size_t chunks = (n + kChunk - 1) / kChunk;
  std::atomic<size_t> done{0};
  parallel_for(chunks, threads, [&](size_t c, unsigned) {
    std::optional<std::pair<double, double>> guess;
    const OrbitRow* prev = nullptr;
    const OrbitRow* prev2 = nullptr;
    for (size_t i = c * kChunk; i < std::min(n, (c + 1) * kChunk); ++i) {
      if (prev && prev2) {  // linear extrapolation in energy along the chunk
        const double w = (energies[i] - prev->energy_MeV) / (prev->energy_MeV - prev2->energy_MeV);
        guess = std::make_pair((prev->r_mm + w * (prev->r_mm - prev2->r_mm)) * 1e-3,
                               (prev->pr_mrad + w * (prev->pr_mrad - prev2->pr_mrad)) * 1e-3);
      } else if (prev) {
        guess = std::make_pair(prev->r_mm * 1e-3, prev->pr_mrad * 1e-3);
      } else {
        guess.reset();
      }
      rows[i] = closed_orbit(map, s, energies[i], guess);
      if (!std::isfinite(rows[i].r_mm) && guess) rows[i] = closed_orbit(map, s, energies[i]);
      if (std::isfinite(rows[i].r_mm)) {
        prev2 = prev;
        prev = &rows[i];
        if (prev2 && prev2->energy_MeV == prev->energy_MeV) prev2 = nullptr;
      }
      size_t d = done.fetch_add(1) + 1;
      if (progress) progress(d, n);
    }
  });
  return rows;
}

std::vector<double> parse_energies(const std::string& spec) {
  auto bad = [&](const std::string& why) { return usage_error("--energies '" + spec + "': " + why); };
  std::vector<double> out;
  auto num = [&](std::string_view tok) {
    double v = 0;
    if (!parse_decimal(trim(tok), v)) throw bad(quote(trim(tok)) + " is not a number");
    return v;
  };
  if (spec.find(':') != std::string::npos) {
    auto f = split_fields(spec, ':');
    if (f.size() != 3) throw bad("expected FIRST:LAST:STEP");
    const double a = num(f[0]), b = num(f[1]), st = num(f[2]);
    if (!(st > 0)) throw bad("the step must be positive");
    if (b < a) throw bad("LAST is below FIRST");
    const double count = std::floor((b - a) / st + 1e-9);
    if (count > 1e7) throw bad("more than 10 million energies");
    for (long k = 0; k <= static_cast<long>(count); ++k) out.push_back(a + k * st);
  } else {
    for (auto tok : split_fields(spec, ',')) out.push_back(num(tok));
  }
  if (out.empty()) throw bad("no energies");
  for (double e : out)
    if (!(e > 0)) throw bad("energies must be positive (kinetic energy in MeV)");
  return out;
}

}  // namespace turnfit
