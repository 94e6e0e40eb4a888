// Analytic separated-sector fields sampled onto polar grids.
#include "turnfit/field/sector_field.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include "turnfit/io/error.hpp"

namespace turnfit {
namespace {
constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180;

Error spec_error(const std::string& what) { return Error(ExitCode::data, "sector field: " + what); }

void validate_table(const RadialTable& t, const std::string& name) {
  if (t.r_mm.empty() || t.r_mm.size() != t.value.size())
    throw spec_error(name + ": needs as many radii as values, at least one");
  for (size_t i = 0; i < t.r_mm.size(); ++i) {
    if (!std::isfinite(t.r_mm[i]) || !std::isfinite(t.value[i]))
      throw spec_error(name + ": node " + std::to_string(i) + " is not finite");
    if (i > 0 && !(t.r_mm[i] > t.r_mm[i - 1]))
      throw spec_error(name + ": radii must increase (node " + std::to_string(i) + ")");
  }
}

/// One magnet's shape at azimuth offset delta [deg] from its centre line: the product of a
/// rising and a falling tanh edge, each in the distance along the arc.
double one_magnet(double r_mm, double delta_deg, double half_width_deg, double lambda_mm) {
  const double d_in = r_mm * (delta_deg + half_width_deg) * kDeg;
  const double d_out = r_mm * (half_width_deg - delta_deg) * kDeg;
  return 0.25 * (1 + std::tanh(d_in / lambda_mm)) * (1 + std::tanh(d_out / lambda_mm));
}
}  // namespace

double RadialTable::at(double r) const {
  if (r_mm.size() == 1 || r <= r_mm.front()) return value.front();
  if (r >= r_mm.back()) return value.back();
  const size_t i = static_cast<size_t>(std::upper_bound(r_mm.begin(), r_mm.end(), r) - r_mm.begin()) - 1;
  const double u = (r - r_mm[i]) / (r_mm[i + 1] - r_mm[i]);
  return value[i] + u * (value[i + 1] - value[i]);
}

double sector_shape(const SectorFieldSpec& s, double r_mm, double theta_deg) {
  const double period = 360.0 / s.sectors;
  const double centre = std::tan(s.spiral_deg * kDeg) * std::log(r_mm / s.spiral_r0_mm) / kDeg;
  double delta = theta_deg - centre;
  delta -= period * std::floor(delta / period + 0.5);  // nearest magnet: delta in [-P/2, P/2)
  const double hw = 0.5 * s.width_deg.at(r_mm);
  // The magnet and its two neighbours: their tails make the shape periodic and smooth.
  return one_magnet(r_mm, delta, hw, s.fringe_mm) + one_magnet(r_mm, delta - period, hw, s.fringe_mm) +
         one_magnet(r_mm, delta + period, hw, s.fringe_mm);
}

void validate_sector_spec(const SectorFieldSpec& s) {
  if (s.sectors < 1) throw spec_error("sectors must be >= 1");
  validate_table(s.width_deg, "width_deg");
  validate_table(s.hill_T, "hill_T");
  const double period = 360.0 / s.sectors;
  for (double w : s.width_deg.value)
    if (!(w > 0 && w < period))
      throw spec_error("width_deg " + std::to_string(w) + " outside (0, " + std::to_string(period) + ")");
  if (!(s.fringe_mm > 0)) throw spec_error("fringe_mm must be > 0");
  if (!(s.valley_fraction >= 0 && s.valley_fraction <= 1)) throw spec_error("valley_fraction must be in [0, 1]");
  if (!(std::fabs(s.spiral_deg) < 89)) throw spec_error("spiral_deg must be within (-89, 89)");
  if (!(s.spiral_r0_mm > 0)) throw spec_error("spiral_r0_mm must be > 0");
  if (!(s.grid.r_min_mm > 0)) throw spec_error("the grid must start at r > 0 (the shape needs ln r)");
  if (s.grid.symmetry != s.sectors) throw spec_error("the grid's symmetry must equal the number of sectors");
}

PolarFieldMap make_sector_field(const SectorFieldSpec& s) {
  validate_sector_spec(s);
  const double v = s.valley_fraction;
  return make_field_map(
      s.grid,
      [&](double r_m, double th_rad) {
        const double r = r_m * 1e3;
        return s.hill_T.at(r) * (v + (1 - v) * sector_shape(s, r, th_rad / kDeg));
      },
      "sector field");
}

}  // namespace turnfit
