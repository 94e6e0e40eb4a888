// Single-gap cavities: the thin-gap kick of physics.md ("How OPAL-cycl treats the Ring inputs").
#include "turnfit/rf/cavity.hpp"

#include <algorithm>
#include <cmath>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/physics/hermite.hpp"
#include "turnfit/physics/particle.hpp"

namespace turnfit {

VoltageProfile VoltageProfile::parse(const std::string& text, const std::string& name) {
  auto lines = split_lines(text, name);
  std::vector<std::pair<long, std::vector<std::string_view>>> rows;
  for (size_t i = 0; i < lines.size(); ++i) {
    auto l = trim(lines[i]);
    if (l.empty() || l.front() == '#') continue;
    rows.emplace_back(static_cast<long>(i + 1), split_blanks(l));
  }
  if (rows.empty()) throw data_error(name, 0, "empty voltage profile");
  const long n = parse_long(rows[0].second.empty() ? std::string_view() : rows[0].second[0], name, rows[0].first,
                            "row count");
  if (n < 2) throw data_error(name, rows[0].first, "a voltage profile needs at least 2 rows");
  if (static_cast<long>(rows.size()) - 1 < n)
    throw data_error(name, rows.back().first, "truncated: " + std::to_string(rows.size() - 1) + " of " +
                                                  std::to_string(n) + " rows");
  VoltageProfile p;
  for (long k = 1; k <= n; ++k) {
    const auto& [line, f] = rows[static_cast<size_t>(k)];
    if (f.size() < 3) throw data_error(name, line, "expected 3 columns: rho_n V dV/drho_n");
    p.x_.push_back(parse_double(f[0], name, line, "rho_n"));
    p.v_.push_back(parse_double(f[1], name, line, "V"));
    p.d_.push_back(parse_double(f[2], name, line, "dV/drho_n"));
    if (k > 1 && !(p.x_.back() > p.x_[p.x_.size() - 2])) throw data_error(name, line, "rho_n must increase");
  }
  return p;
}

VoltageProfile VoltageProfile::read(const std::string& path) {
  InputText in = read_input(path);
  return parse(in.text, in.name);
}

double VoltageProfile::eval(double x, double& dv) const {
  if (x_.empty()) {
    dv = 0;
    return 1;
  }
  if (x < x_.front() || x > x_.back()) {  // beyond the table: held at the end value
    dv = 0;
    return x < x_.front() ? v_.front() : v_.back();
  }
  if (x == x_.back()) {
    dv = d_.back();
    return v_.back();
  }
  size_t i = static_cast<size_t>(std::upper_bound(x_.begin(), x_.end(), x) - x_.begin()) - 1;
  const double h = x_[i + 1] - x_[i];
  return hermite(v_[i], v_[i + 1], d_[i], d_[i + 1], h, (x - x_[i]) / h, dv);
}

Gap::Gap(const Cavity& c, double rf_MHz, VoltageProfile profile)
    : name_(c.name), profile_(std::move(profile)) {
  angle_rad_ = c.angle_deg * kPi / 180;
  sin_a_ = std::sin(angle_rad_);
  cos_a_ = std::cos(angle_rad_);
  pdis_m_ = c.pdis_mm * 1e-3;
  // rshift moves the gap's radial extent (and so its voltage profile) outwards.
  rmin_m_ = (c.rmin_mm + c.rshift_mm) * 1e-3;
  rmax_m_ = (c.rmax_mm + c.rshift_mm) * 1e-3;
  volt_MV_ = c.voltage_MV;
  freq_hz_ = c.harmonic_factor * rf_MHz * 1e6;
  phi0_rad_ = c.phase_deg * kPi / 180;
  gap_m_ = c.gap_width_mm * 1e-3;
  if (!(rmax_m_ > rmin_m_)) throw Error(ExitCode::data, "cavity '" + c.name + "': rmax_mm must exceed rmin_mm");
  if (!(freq_hz_ > 0)) throw Error(ExitCode::data, "cavity '" + c.name + "': the RF frequency must be positive");
}

void Gap::set_bow(double sagitta_m) {
  bow_m_ = sagitta_m;
  bow_mid_m_ = 0.5 * (rmin_m_ + rmax_m_);
  bow_inv_half_ = 2 / (rmax_m_ - rmin_m_);
}

void Gap::set_tilt(double slope, double pivot_rho_n) {
  tilt_ = slope;
  tilt_pivot_ = pivot_rho_n;
}

double Gap::bow(double rho) const {
  const double u = (rho - bow_mid_m_) * bow_inv_half_;
  return std::fabs(u) <= 1 ? bow_m_ * (1 - u * u) : 0.0;
}

double Gap::bow_slope(double rho) const {
  const double u = (rho - bow_mid_m_) * bow_inv_half_;
  return std::fabs(u) <= 1 ? -2 * bow_m_ * u * bow_inv_half_ : 0.0;
}

double Gap::crossing_azimuth(double r_m) const {
  if (r_m < std::fabs(pdis_m_)) return std::nan("");
  // r sin(A - theta) = PDIS on the half of the line where rho = x cos A + y sin A > 0.
  double psi = std::asin(pdis_m_ / r_m);
  if (bow_m_ != 0) {
    // The bowed line: with psi = A - theta the point is rho = r cos(psi) along the chord and
    // r sin(psi) across it, so F(psi) = r sin(psi) - PDIS + bow(r cos psi) = 0. Newton from the
    // straight line's root; |bow'| <= 0.4 (the loader's sagitta limit) keeps F' near r cos(psi).
    for (int it = 0; it < 30; ++it) {
      const double c = std::cos(psi), s = std::sin(psi), rho = r_m * c;
      const double f = r_m * s - pdis_m_ + bow(rho);
      const double df = r_m * c - bow_slope(rho) * r_m * s;
      const double step = f / df;
      psi -= step;
      if (std::fabs(step) < 1e-16) break;
    }
  }
  return remainder_two_pi(angle_rad_ - psi);
}

GapKick Gap::kick(double x, double y, double t_s, double mass_MeV, double charge_e, GapPhysics physics,
                  double& px, double& py, double pz) const {
  GapKick k;
  const double rho = x * cos_a_ + y * sin_a_;
  k.rho_n = (rho - rmin_m_) / (rmax_m_ - rmin_m_);
  if (!(k.rho_n >= 0 && k.rho_n <= 1)) return k;
  k.active = true;
  double dvn;
  double vn = profile_.eval(k.rho_n, dvn);
  if (tilt_ != 0) {
    // V (1 + s (rho_n - p)): its derivative feeds the RF deflection below.
    const double f = 1 + tilt_ * (k.rho_n - tilt_pivot_);
    dvn = dvn * f + vn * tilt_;
    vn *= f;
  }
  const double phi = 2 * kPi * freq_hz_ * t_s - phi0_rad_;
  k.phase_deg = std::remainder(phi, 2 * kPi) * 180 / kPi;
  const double p2 = px * px + py * py + pz * pz;
  const double gamma0 = std::sqrt(1 + p2);
  const double beta0 = std::sqrt(p2) / gamma0;
  const double omega = 2 * kPi * freq_hz_;
  const double u = omega * gap_m_ / (2 * beta0 * kSpeedOfLight);
  k.transit = u == 0 ? 1.0 : std::sin(u) / u;
  k.de_MeV = charge_e * volt_MV_ * vn * k.transit * std::cos(phi);
  const double gamma1 = gamma0 + k.de_MeV / mass_MeV;
  if (!(gamma1 > 1)) {
    k.stopped = true;
    return k;
  }
  const double p1sq = gamma1 * gamma1 - 1;
  // Keep the component along the gap line and p_z; the rest lies along the gap normal. On a
  // bowed gap, the local line at the crossing: the chord turned by atan(bow').
  double ca = cos_a_, sa = sin_a_;
  if (bow_m_ != 0) {
    const double sl = bow_slope(rho), inv = 1 / std::sqrt(1 + sl * sl);
    ca = (cos_a_ - sl * sin_a_) * inv;
    sa = (sin_a_ + sl * cos_a_) * inv;
  }
  const double p_par = px * ca + py * sa;
  const double pn2 = p1sq - p_par * p_par - pz * pz;
  const double p_n = std::sqrt(std::max(0.0, pn2));
  px = p_par * ca - p_n * sa;
  py = p_par * sa + p_n * ca;
  // RF magnetic deflection: the line integral of the gap's magnetic field follows from
  // Faraday's law, int B dn = (dV/drho) sin(phi) / omega; divided by B rho it is an angle.
  const double brho = std::sqrt(p1sq) * mass_MeV * 1e6 / (kSpeedOfLight * std::fabs(charge_e));
  const double dv_drho = volt_MV_ * 1e6 * dvn / (rmax_m_ - rmin_m_);
  double delta = -dv_drho * std::sin(phi) / (omega * brho);
  if (physics == GapPhysics::opal) delta /= 2 * kPi;
  if (charge_e < 0) delta = -delta;
  k.deflection_rad = delta;
  const double cd = std::cos(delta), sd = std::sin(delta);
  const double qx = cd * px + sd * py, qy = -sd * px + cd * py;
  px = qx;
  py = qy;
  return k;
}

std::vector<Gap> make_gaps(const Machine& m, const std::map<std::string, VoltageProfile>* profiles) {
  std::vector<Gap> gaps;
  for (const auto& c : m.cavities) {
    VoltageProfile p;
    if (!c.profile.empty()) {
      std::map<std::string, VoltageProfile>::const_iterator it;
      if (profiles && (it = profiles->find(c.profile)) != profiles->end()) p = it->second;
      else p = VoltageProfile::read(c.profile);
    }
    gaps.emplace_back(c, m.rf.frequency_MHz, std::move(p));
  }
  return gaps;
}

}  // namespace turnfit
