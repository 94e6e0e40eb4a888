// Analytic separated-sector fields sampled onto polar grids, and their JSON description.
#include "turnfit/field/sector_field.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <optional>
#include <string>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {
using nlohmann::json;
constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180;
const char* const kSpecFormat = "turnfit-sector-field/1";

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

/// The shape at one radius, given that radius's centre line and half width [deg].
double shape_at(int sectors, double r_mm, double theta_deg, double centre_deg, double hw_deg, double lambda_mm) {
  const double period = 360.0 / sectors;
  double delta = theta_deg - centre_deg;
  delta -= period * std::floor(delta / period + 0.5);  // nearest magnet: delta in [-P/2, P/2)
  // The magnet and its two neighbours: their tails make the shape periodic and smooth.
  return one_magnet(r_mm, delta, hw_deg, lambda_mm) + one_magnet(r_mm, delta - period, hw_deg, lambda_mm) +
         one_magnet(r_mm, delta + period, hw_deg, lambda_mm);
}

/// 8-point Gauss-Legendre integral of tan(xi(r)) / r over [a, b] (one smooth piece) [rad].
double spiral_piece(const RadialTable& xi, double a, double b) {
  static const double x[4] = {0.1834346424956498, 0.5255324099163290, 0.7966664774136267, 0.9602898564975363};
  static const double w[4] = {0.3626837833783620, 0.3137066458778873, 0.2223810344533745, 0.1012285362903763};
  const double c = 0.5 * (a + b), h = 0.5 * (b - a);
  double sum = 0;
  for (int k = 0; k < 4; ++k)
    for (double r : {c - h * x[k], c + h * x[k]}) sum += w[k] * std::tan(xi.at(r) * kDeg) / r;
  return sum * h;
}
}  // namespace

// Natural cubic spline: second derivatives M with M_0 = M_{n-1} = 0 and C2 continuity inside
// (any numerical-analysis text, e.g. Press et al., Numerical Recipes, sec. 3.3).
// Recomputed on every call (a tridiagonal solve over a few dozen nodes), so the table stays a
// plain aggregate that is safe to share between threads.
std::vector<double> RadialTable::curvatures() const {
  const size_t n = r_mm.size();
  std::vector<double> m2(n, 0.0);
  if (n < 3) return m2;
  std::vector<double> c(n, 0.0), d(n, 0.0);  // Thomas algorithm on the interior rows
  for (size_t i = 1; i + 1 < n; ++i) {
    const double h0 = r_mm[i] - r_mm[i - 1], h1 = r_mm[i + 1] - r_mm[i];
    const double rhs = 6 * ((value[i + 1] - value[i]) / h1 - (value[i] - value[i - 1]) / h0);
    const double diag = 2 * (h0 + h1) - h0 * c[i - 1];
    c[i] = h1 / diag;
    d[i] = (rhs - h0 * d[i - 1]) / diag;
  }
  for (size_t i = n - 2; i >= 1; --i) m2[i] = d[i] - c[i] * m2[i + 1];
  return m2;
}

double RadialTable::at(double r) const {
  const size_t n = r_mm.size();
  if (n == 1) return value[0];
  if (r <= r_mm.front()) return value.front() + slope(r_mm.front()) * (r - r_mm.front());
  if (r >= r_mm.back()) return value.back() + slope(r_mm.back()) * (r - r_mm.back());
  const size_t i = static_cast<size_t>(std::upper_bound(r_mm.begin(), r_mm.end(), r) - r_mm.begin()) - 1;
  const std::vector<double> m2 = curvatures();
  const double h = r_mm[i + 1] - r_mm[i], a = (r_mm[i + 1] - r) / h, b = 1 - a;
  return a * value[i] + b * value[i + 1] + ((a * a * a - a) * m2[i] + (b * b * b - b) * m2[i + 1]) * h * h / 6;
}

double RadialTable::slope(double r) const {
  const size_t n = r_mm.size();
  if (n == 1) return 0;
  const std::vector<double> m2 = curvatures();
  const double rc = std::min(std::max(r, r_mm.front()), r_mm.back());  // straight beyond the ends
  size_t i = static_cast<size_t>(std::upper_bound(r_mm.begin(), r_mm.end(), rc) - r_mm.begin());
  i = std::min(std::max<size_t>(i, 1), n - 1) - 1;
  const double h = r_mm[i + 1] - r_mm[i], a = (r_mm[i + 1] - rc) / h, b = 1 - a;
  return (value[i + 1] - value[i]) / h + ((1 - 3 * a * a) * m2[i] + (3 * b * b - 1) * m2[i + 1]) * h / 6;
}

double sector_centre_deg(const SectorFieldSpec& s, double r) {
  if (s.spiral_deg.empty()) return 0;
  const RadialTable& xi = s.spiral_deg;
  if (xi.r_mm.size() == 1) return std::tan(xi.value[0] * kDeg) * std::log(r / s.spiral_r0_mm) / kDeg;
  // Integrate piece by piece between the spline's nodes (smooth inside each), in chunks of at
  // most 100 mm so the quadrature error stays at rounding level.
  const double lo = std::min(r, s.spiral_r0_mm), hi = std::max(r, s.spiral_r0_mm);
  std::vector<double> cuts{lo};
  for (double node : xi.r_mm)
    if (node > lo && node < hi) cuts.push_back(node);
  cuts.push_back(hi);
  double sum = 0;
  for (size_t k = 0; k + 1 < cuts.size(); ++k) {
    const int chunks = std::max(1, static_cast<int>(std::ceil((cuts[k + 1] - cuts[k]) / 100.0)));
    const double step = (cuts[k + 1] - cuts[k]) / chunks;
    for (int c = 0; c < chunks; ++c) sum += spiral_piece(xi, cuts[k] + c * step, cuts[k] + (c + 1) * step);
  }
  return (r >= s.spiral_r0_mm ? sum : -sum) / kDeg;
}

double sector_shape(const SectorFieldSpec& s, double r_mm, double theta_deg) {
  return shape_at(s.sectors, r_mm, theta_deg, sector_centre_deg(s, r_mm), 0.5 * s.width_deg.at(r_mm), s.fringe_mm);
}

void validate_sector_spec(const SectorFieldSpec& s) {
  if (s.sectors < 1) throw spec_error("sectors must be >= 1");
  validate_table(s.width_deg, "width_deg");
  validate_table(s.hill_T, "hill_T");
  if (!s.spiral_deg.empty()) {
    validate_table(s.spiral_deg, "spiral_deg");
    for (double xi : s.spiral_deg.value)
      if (!(std::fabs(xi) < 89)) throw spec_error("spiral_deg must be within (-89, 89)");
  }
  if (!(s.fringe_mm > 0)) throw spec_error("fringe_mm must be > 0");
  if (!(s.valley_fraction >= 0 && s.valley_fraction <= 1)) throw spec_error("valley_fraction must be in [0, 1]");
  if (!(s.spiral_r0_mm > 0)) throw spec_error("spiral_r0_mm must be > 0");
  if (!(s.grid.r_min_mm > 0)) throw spec_error("the grid must start at r > 0 (the shape needs ln r)");
  if (s.grid.symmetry != s.sectors) throw spec_error("the grid's symmetry must equal the number of sectors");
  if (s.grid.nr < 2 || s.grid.ntheta < 1 || !(s.grid.dr_mm > 0))
    throw spec_error("the grid needs nr >= 2, ntheta >= 1 and dr_mm > 0");
  // The spline between and beyond the nodes must keep the width inside the sector everywhere
  // the field is sampled, not only at the nodes.
  const double period = 360.0 / s.sectors;
  for (int i = 0; i < s.grid.nr; ++i) {
    const double r = s.grid.r_min_mm + i * s.grid.dr_mm, w = s.width_deg.at(r);
    if (!(w > 0 && w < period))
      throw spec_error("width_deg " + std::to_string(w) + " at r = " + std::to_string(r) + " mm outside (0, " +
                       std::to_string(period) + ")");
  }
}

PolarFieldMap make_sector_field(const SectorFieldSpec& s) {
  validate_sector_spec(s);
  const PolarGrid& g = s.grid;
  const double v = s.valley_fraction;
  std::vector<double> bz(static_cast<size_t>(g.nr) * g.ntheta);
  const double dth_deg = g.dtheta_rad() / kDeg;
  for (int i = 0; i < g.nr; ++i) {
    const double r = g.r_min_mm + i * g.dr_mm;
    const double centre = sector_centre_deg(s, r), hw = 0.5 * s.width_deg.at(r), hill = s.hill_T.at(r);
    for (int j = 0; j < g.ntheta; ++j) {
      const double th = g.theta_min_deg + j * dth_deg;
      bz[static_cast<size_t>(i) * g.ntheta + j] =
          hill * (v + (1 - v) * shape_at(s.sectors, r, th, centre, hw, s.fringe_mm));
    }
  }
  return PolarFieldMap(g, std::move(bz), s.description.empty() ? std::string("sector field") : s.description);
}

// ---- turnfit-sector-field/1 JSON ----

namespace {
/// Checks an object's keys against a list (the machine file's rules: a key in the wrong unit
/// gets a hint) and reads typed values with errors naming the key path.
class SpecReader {
 public:
  SpecReader(const json& obj, std::string file, std::string path, std::vector<std::string> known)
      : obj_(obj), file_(std::move(file)), path_(std::move(path)) {
    if (!obj_.is_object()) throw data_error(file_, 0, (path_.empty() ? "/" : path_) + ": expected a JSON object");
    for (const auto& item : obj_.items())
      if (std::find(known.begin(), known.end(), item.key()) == known.end()) {
        std::string hint;
        for (const auto& k : known)
          if (edit_distance(item.key(), k) <= 2) hint = " (did you mean '" + k + "'?)";
        throw error(item.key(), "unknown key" + hint);
      }
  }
  bool has(const std::string& k) const { return obj_.contains(k); }
  Error error(const std::string& k, const std::string& msg) const {
    return data_error(file_, 0, path_ + "/" + k + ": " + msg);
  }
  double number(const std::string& k, std::optional<double> def = std::nullopt) const {
    if (!has(k)) {
      if (def) return *def;
      throw error(k, "missing required key");
    }
    const json& j = obj_.at(k);
    if (!j.is_number()) throw error(k, "expected a number");
    const double v = j.get<double>();
    if (!std::isfinite(v)) throw error(k, "not a finite number");
    return v;
  }
  int integer(const std::string& k, std::optional<int> def = std::nullopt) const {
    const double v = number(k, def ? std::optional<double>(*def) : std::nullopt);
    if (v != std::floor(v) || std::fabs(v) > 1e9) throw error(k, "expected a whole number");
    return static_cast<int>(v);
  }
  std::vector<double> numbers(const std::string& k) const {
    if (!has(k)) throw error(k, "missing required key");
    const json& j = obj_.at(k);
    if (!j.is_array() || j.empty()) throw error(k, "expected a non-empty array of numbers");
    std::vector<double> out;
    for (size_t i = 0; i < j.size(); ++i) {
      if (!j[i].is_number() || !std::isfinite(j[i].get<double>()))
        throw error(k + "/" + std::to_string(i), "expected a finite number");
      out.push_back(j[i].get<double>());
    }
    return out;
  }
  const json& raw(const std::string& k) const { return obj_.at(k); }
  const std::string& file() const { return file_; }
  std::string at(const std::string& k) const { return path_ + "/" + k; }

 private:
  const json& obj_;
  std::string file_, path_;
};

RadialTable read_table(const SpecReader& parent, const std::string& key, const std::string& value_key,
                       std::vector<std::string> extra = {}) {
  std::vector<std::string> known{"r_mm", value_key};
  known.insert(known.end(), extra.begin(), extra.end());
  SpecReader t(parent.raw(key), parent.file(), parent.at(key), known);
  RadialTable out{t.numbers("r_mm"), t.numbers(value_key)};
  if (out.r_mm.size() != out.value.size())
    throw t.error(value_key, "has " + std::to_string(out.value.size()) + " values for " +
                                 std::to_string(out.r_mm.size()) + " radii");
  for (size_t i = 1; i < out.r_mm.size(); ++i)
    if (!(out.r_mm[i] > out.r_mm[i - 1])) throw t.error("r_mm/" + std::to_string(i), "radii must increase");
  return out;
}

json table_json(const RadialTable& t, const std::string& value_key) {
  return json{{"r_mm", t.r_mm}, {value_key, t.value}};
}
}  // namespace

SectorFieldSpec sector_spec_from_json(const json& doc, const std::string& name) {
  SpecReader top(doc, name, "",
                 {"format", "description", "sectors", "grid", "fringe_mm", "valley_fraction", "width", "hill",
                  "spiral", "isochronize", "provenance"});
  if (!top.has("format") || !doc.at("format").is_string() || doc.at("format").get<std::string>() != kSpecFormat)
    throw top.error("format", std::string("expected \"") + kSpecFormat + "\"");
  SectorFieldSpec s;
  if (top.has("description")) {
    if (!doc.at("description").is_string()) throw top.error("description", "expected a string");
    s.description = doc.at("description").get<std::string>();
  }
  s.sectors = top.integer("sectors");
  if (s.sectors < 1 || s.sectors > 360) throw top.error("sectors", "must be in [1, 360]");
  if (!top.has("grid")) throw top.error("grid", "missing required key");
  SpecReader g(top.raw("grid"), name, "/grid", {"r_min_mm", "dr_mm", "nr", "theta_min_deg", "ntheta"});
  s.grid.r_min_mm = g.number("r_min_mm");
  s.grid.dr_mm = g.number("dr_mm");
  s.grid.nr = g.integer("nr");
  s.grid.theta_min_deg = g.number("theta_min_deg", 0.0);
  s.grid.ntheta = g.integer("ntheta");
  s.grid.symmetry = s.sectors;
  if (!(s.grid.r_min_mm > 0)) throw g.error("r_min_mm", "must be > 0");
  if (!(s.grid.dr_mm > 0)) throw g.error("dr_mm", "must be > 0");
  if (s.grid.nr < 4 || s.grid.nr > 100000) throw g.error("nr", "must be in [4, 100000]");
  if (s.grid.ntheta < 4 || s.grid.ntheta > 100000) throw g.error("ntheta", "must be in [4, 100000]");
  try {
    check_grid_size(s.grid.nr, s.grid.ntheta);  // before make_sector_field allocates the samples
  } catch (const Error& e) {
    throw g.error("nr", e.what());
  }
  s.fringe_mm = top.number("fringe_mm");
  s.valley_fraction = top.number("valley_fraction", 0.0);
  if (!top.has("width")) throw top.error("width", "missing required key");
  if (!top.has("hill")) throw top.error("hill", "missing required key");
  s.width_deg = read_table(top, "width", "width_deg");
  s.hill_T = read_table(top, "hill", "field_T");
  if (top.has("spiral")) {
    s.spiral_deg = read_table(top, "spiral", "angle_deg", {"r0_mm"});
    SpecReader sp(top.raw("spiral"), name, "/spiral", {"r_mm", "angle_deg", "r0_mm"});
    s.spiral_r0_mm = sp.number("r0_mm");
  }
  if (top.has("isochronize")) {
    if (!doc.at("isochronize").is_object()) throw top.error("isochronize", "expected a JSON object");
    s.isochronize = doc.at("isochronize");
  }
  try {
    validate_sector_spec(s);
  } catch (const Error& e) {
    throw data_error(name, 0, e.what());
  }
  return s;
}

SectorFieldSpec read_sector_spec(const std::string& path) { return sector_spec_from_json(read_json(path), path); }

json sector_spec_to_json(const SectorFieldSpec& s) {
  json doc = json::object();
  doc["format"] = kSpecFormat;
  if (!s.description.empty()) doc["description"] = s.description;
  doc["sectors"] = s.sectors;
  doc["grid"] = {{"r_min_mm", s.grid.r_min_mm}, {"dr_mm", s.grid.dr_mm}, {"nr", s.grid.nr},
                 {"theta_min_deg", s.grid.theta_min_deg}, {"ntheta", s.grid.ntheta}};
  doc["fringe_mm"] = s.fringe_mm;
  doc["valley_fraction"] = s.valley_fraction;
  doc["width"] = table_json(s.width_deg, "width_deg");
  if (!s.spiral_deg.empty()) {
    doc["spiral"] = table_json(s.spiral_deg, "angle_deg");
    doc["spiral"]["r0_mm"] = s.spiral_r0_mm;
  }
  doc["hill"] = table_json(s.hill_T, "field_T");
  if (!s.isochronize.is_null()) doc["isochronize"] = s.isochronize;
  return doc;
}

}  // namespace turnfit
