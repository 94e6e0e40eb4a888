// Field map readers and writers; strict, so a truncated or garbled map is an error.
#include "turnfit/field/map_io.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {
constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;
constexpr double kKiloGauss = 0.1;  // T per kG

/// Sector count from the grid, or an error if the grid does not tile the circle.
int symmetry_from_grid(int ntheta, double dtheta_deg, const std::string& name, long line) {
  double n = 360.0 / (ntheta * dtheta_deg);
  long k = n >= 0.5 && n <= 360.5 ? std::lround(n) : 0;  // lround of a huge n is undefined
  if (k < 1 || std::fabs(n - k) > 1e-6 * n)
    throw data_error(name, line,
                     std::to_string(ntheta) + " azimuths of " + format_exact(dtheta_deg) +
                         " deg do not cover a whole sector (360/N deg for an integer N)");
  return static_cast<int>(k);
}
/// The map of a reader's grid and values; what the constructor refuses names the file.
PolarFieldMap map_named(const std::string& name, const PolarGrid& g, std::vector<double> bz, const std::string& label) {
  try {
    return PolarFieldMap(g, std::move(bz), label);
  } catch (const Error& e) {
    throw data_error(name, 0, e.what());
  }
}

}  // namespace

MapFormat parse_map_format(const std::string& name) {
  if (name == "psi-ring") return MapFormat::psi_ring;
  if (name == "turnfit") return MapFormat::turnfit;
  throw usage_error("unknown field map format '" + name + "' (expected psi-ring or turnfit)");
}

PolarFieldMap parse_psi_ring(const std::string& text, const std::string& name, int symmetry) {
  auto lines = split_lines(text, name);
  size_t li = 0;
  auto next_nonblank = [&]() -> long {
    while (li < lines.size() && trim(lines[li]).empty()) ++li;
    if (li >= lines.size()) return -1;
    return static_cast<long>(li);
  };
  // Header: r_min [mm], dr [mm], theta_min [deg], dtheta [deg] (negative: 1/|value| deg).
  double head[4];
  long head_line[4];
  const char* what[4] = {"r_min_mm", "dr_mm", "theta_min_deg", "dtheta"};
  for (int k = 0; k < 4; ++k) {
    long l = next_nonblank();
    if (l < 0) throw data_error(name, static_cast<long>(lines.size()), "truncated header: missing " + std::string(what[k]));
    auto f = split_blanks(lines[li]);
    head_line[k] = l + 1;
    head[k] = parse_double(f.empty() ? std::string_view() : f[0], name, l + 1, what[k]);
    ++li;
  }
  // OPAL's convention for both steps: a negative value means 1/|value|.
  if (head[1] < 0) head[1] = 1.0 / -head[1];
  if (head[3] < 0) head[3] = 1.0 / -head[3];
  if (!(head[1] > 0)) throw data_error(name, head_line[1], "radial step must be non-zero");
  if (!(head[3] > 0)) throw data_error(name, head_line[3], "azimuthal step must be non-zero");
  if (head[0] < 0) throw data_error(name, head_line[0], "minimum radius must not be negative");

  // First LPAR block: integers; the 2nd and 3rd are the radius and azimuth counts.
  long lpar_line = -1;
  for (; li < lines.size(); ++li)
    if (lines[li].find("LPAR=") != std::string_view::npos) {
      lpar_line = static_cast<long>(li);
      break;
    }
  if (lpar_line < 0) throw data_error(name, 0, "no 'LPAR=' block: not an OPAL RING map");
  std::vector<long> ints;
  for (++li; li < lines.size(); ++li) {
    if (lines[li].find('=') != std::string_view::npos) break;
    for (auto tok : split_blanks(lines[li]))
      ints.push_back(parse_long(tok, name, static_cast<long>(li + 1), "grid parameter"));
  }
  if (ints.size() < 3)
    throw data_error(name, lpar_line + 1, "grid block has " + std::to_string(ints.size()) +
                                              " integers, expected at least 3 (npar, nr, ntheta)");
  const long nr = ints[1], nt = ints[2];
  if (nr < 2 || nr > 100000 || nt < 1 || nt > 100000)
    throw data_error(name, lpar_line + 2, "implausible grid size " + std::to_string(nr) + " x " +
                                              std::to_string(nt));
  check_grid_size(nr, nt, name, lpar_line + 2);
  int sym = symmetry_from_grid(static_cast<int>(nt), head[3], name, head_line[3]);
  if (symmetry > 0 && symmetry != sym)
    throw data_error(name, head_line[3], "grid covers 360/" + std::to_string(sym) +
                                  " deg but symmetry " + std::to_string(symmetry) + " was requested");

  // Records "LREC= n ... IREC= k", each followed by n fixed-width (16 character) numbers,
  // the first nt of which are Bz(theta) at this radius.
  std::vector<double> bz(static_cast<size_t>(nr) * nt);
  long rec = 0;
  for (; li < lines.size(); ++li) {
    std::string_view l = lines[li];
    if (l.find("LREC=") == std::string_view::npos) continue;
    const long rec_line = static_cast<long>(li + 1);
    auto toks = split_blanks(l);
    long lrec = toks.size() >= 2 ? parse_long(toks[1], name, rec_line, "LREC") : 0;
    if (lrec < nt)
      throw data_error(name, rec_line, "record of " + std::to_string(lrec) + " numbers, expected at least " +
                                           std::to_string(nt));
    if (rec >= nr) throw data_error(name, rec_line, "more than the " + std::to_string(nr) + " records the header announces");
    long got = 0;
    ++li;
    for (; li < lines.size() && got < lrec; ++li) {
      std::string_view d = lines[li];
      if (d.find('=') != std::string_view::npos) break;
      // Fortran E16 fields may touch ("0.28E+04-0.58E+04"): split by width.
      for (size_t p = 0; p < d.size() && got < lrec; p += 16) {
        std::string_view field = trim(d.substr(p, 16));
        if (field.empty()) continue;
        double v = parse_double(field, name, static_cast<long>(li + 1), "field value");
        if (got < nt) bz[static_cast<size_t>(rec) * nt + got] = v * kKiloGauss;
        ++got;
      }
    }
    if (got < lrec)
      throw data_error(name, static_cast<long>(li), "truncated record " + std::to_string(rec + 1) + ": " +
                                                       std::to_string(got) + " of " + std::to_string(lrec) + " numbers");
    --li;  // the for-loop increment moves past the last data line
    ++rec;
  }
  if (rec < nr)
    throw data_error(name, static_cast<long>(lines.size()), "truncated map: " + std::to_string(rec) + " of " +
                                                              std::to_string(nr) + " radius records");
  PolarGrid g;
  g.r_min_mm = head[0];
  g.dr_mm = head[1];
  g.nr = static_cast<int>(nr);
  g.theta_min_deg = head[2];
  g.ntheta = static_cast<int>(nt);
  g.symmetry = sym;
  std::string label;
  for (auto l : lines)
    if (l.find("LABEL=") != std::string_view::npos) {
      label = std::string(trim(l.substr(l.find("LABEL=") + 6)));
      break;
    }
  return map_named(name, g, std::move(bz), label);
}

PolarFieldMap parse_turnfit_map(const std::string& text, const std::string& name) {
  auto lines = split_lines(text, name);
  size_t li = 0;
  auto skip = [&] {
    while (li < lines.size() && (trim(lines[li]).empty() || trim(lines[li]).front() == '#')) ++li;
  };
  skip();
  if (li >= lines.size()) throw data_error(name, 0, "empty input: no field map");
  {
    auto f = split_blanks(lines[li]);
    if (f.size() != 2 || f[0] != "turnfit-fieldmap")
      throw data_error(name, static_cast<long>(li + 1), "not a turnfit field map (first line must be 'turnfit-fieldmap 1')");
    if (f[1] != "1")
      throw data_error(name, static_cast<long>(li + 1), "unsupported turnfit-fieldmap version '" + std::string(f[1]) + "'");
    ++li;
  }
  PolarGrid g;
  double r_min_mm = NAN, dr_mm = NAN, theta_min_deg = 0;
  long nr = -1, nt = -1, sym = -1;
  std::string unit, label;
  std::vector<std::string> seen;
  for (;; ++li) {
    skip();
    if (li >= lines.size()) throw data_error(name, static_cast<long>(lines.size()), "truncated: no 'data' line");
    const long ln = static_cast<long>(li + 1);
    std::string_view l = trim(lines[li]);
    if (l == "data") {
      ++li;
      break;
    }
    size_t sp = l.find_first_of(" \t");
    std::string key(l.substr(0, sp));
    if (std::find(seen.begin(), seen.end(), key) != seen.end())
      throw data_error(name, ln, "header key '" + key + "' given twice");
    seen.push_back(key);
    std::string_view val = sp == std::string_view::npos ? std::string_view() : trim(l.substr(sp));
    if (key == "label") label = std::string(val);
    else if (key == "symmetry") sym = parse_long(val, name, ln, key);
    else if (key == "r_min_mm") r_min_mm = parse_double(val, name, ln, key);
    else if (key == "dr_mm") dr_mm = parse_double(val, name, ln, key);
    else if (key == "nr") nr = parse_long(val, name, ln, key);
    else if (key == "theta_min_deg") theta_min_deg = parse_double(val, name, ln, key);
    else if (key == "ntheta") nt = parse_long(val, name, ln, key);
    else if (key == "unit") {
      unit = std::string(val);
      if (unit != "T" && unit != "kG") throw data_error(name, ln, "unit must be T or kG, not '" + unit + "'");
    } else
      throw data_error(name, ln, "unknown header key '" + key + "'");
  }
  const char* missing = std::isnan(r_min_mm) ? "r_min_mm" : std::isnan(dr_mm) ? "dr_mm" : nr < 0 ? "nr"
                        : nt < 0 ? "ntheta" : sym < 0 ? "symmetry" : unit.empty() ? "unit" : nullptr;
  if (missing) throw data_error(name, 0, std::string("header lacks '") + missing + "'");
  if (nr < 2 || nt < 1 || sym < 1 || !(dr_mm > 0) || r_min_mm < 0)
    throw data_error(name, 0, "invalid grid (need nr >= 2, ntheta >= 1, symmetry >= 1, dr_mm > 0, r_min_mm >= 0)");
  check_grid_size(nr, nt, name);
  const double factor = unit == "kG" ? kKiloGauss : 1.0;
  std::vector<double> bz;
  bz.reserve(static_cast<size_t>(nr * nt));
  long rows = 0;
  for (; li < lines.size(); ++li) {
    std::string_view l = trim(lines[li]);
    if (l.empty() || l.front() == '#') continue;
    const long ln = static_cast<long>(li + 1);
    if (rows >= nr) throw data_error(name, ln, "more than nr = " + std::to_string(nr) + " data rows");
    auto f = split_blanks(l);
    if (static_cast<long>(f.size()) != nt)
      throw data_error(name, ln, "row " + std::to_string(rows + 1) + " has " + std::to_string(f.size()) +
                                     " values, expected ntheta = " + std::to_string(nt));
    for (auto tok : f) bz.push_back(parse_double(tok, name, ln, "field value") * factor);
    ++rows;
  }
  if (rows < nr)
    throw data_error(name, static_cast<long>(lines.size()), "truncated: " + std::to_string(rows) + " of " +
                                                              std::to_string(nr) + " data rows");
  g.r_min_mm = r_min_mm;
  g.dr_mm = dr_mm;
  g.nr = static_cast<int>(nr);
  g.theta_min_deg = theta_min_deg;
  g.ntheta = static_cast<int>(nt);
  g.symmetry = static_cast<int>(sym);
  return map_named(name, g, std::move(bz), label);
}

PolarFieldMap read_field_map(const std::string& path, MapFormat format, int symmetry) {
  InputText in = read_input(path);
  if (format == MapFormat::psi_ring) return parse_psi_ring(in.text, in.name, symmetry);
  PolarFieldMap m = parse_turnfit_map(in.text, in.name);
  if (symmetry > 0 && symmetry != m.grid().symmetry)
    throw data_error(in.name, 0, "map has symmetry " + std::to_string(m.grid().symmetry) + " but " +
                                     std::to_string(symmetry) + " was requested");
  return m;
}

void write_psi_ring(std::ostream& os, const PolarFieldMap& map) {
  const PolarGrid& g = map.grid();
  const double dth_deg = g.dtheta_rad() / kDeg;
  char buf[256];
  auto num = [&](double v) {
    std::snprintf(buf, sizeof buf, "%.9g", v);
    return std::string(buf);
  };
  os << num(g.r_min_mm) << "\n" << num(g.dr_mm) << "\n" << num(g.theta_min_deg) << "\n";
  // OPAL's convention: a negative step means 1/|value| degrees; use it when exact.
  double inv = 1.0 / dth_deg;
  if (std::fabs(inv - std::round(inv)) < 1e-9 && inv > 1.5) os << "-" << num(std::round(inv)) << "\n";
  else os << num(dth_deg) << "\n";
  std::string label = map.label().empty() ? "TURNFIT" : map.label();
  for (auto& c : label)
    if (c == ' ' || c == '\t') c = '_';
  os << " LABEL=" << label.substr(0, 60) << "\n";
  std::snprintf(buf, sizeof buf, " CFELD=FIELD     NREC=%6d      NPAR=    3\n", g.nr);
  os << buf;
  os << " LPAR=    7      IENT=    1      IPAR=    1\n";
  std::snprintf(buf, sizeof buf, "%16d%16d%16d%16d%16d\n%16d%16d\n", 3, g.nr, g.ntheta, 30, g.symmetry, g.symmetry, 70);
  os << buf;
  // The parameter block OPAL skips: one zero, so readers that count it find it.
  os << " LPAR=    1      IENT=    2      IPAR=    2\n";
  os << " 0.000000000E+00\n";
  os << " LPAR=   70      IENT=    3      IPAR=    3\n";
  os << " " << label.substr(0, 70) << "\n";
  auto efmt = [&](double v) {
    // Fortran E16.9: " 0.123456789E+01"
    if (v == 0) return std::string(" 0.000000000E+00");
    int e = static_cast<int>(std::floor(std::log10(std::fabs(v)))) + 1;
    double m = v / std::pow(10.0, e);
    std::snprintf(buf, sizeof buf, "%.9f", std::fabs(m));
    if (buf[0] == '1') {  // rounding reached 1.0: renormalize
      ++e;
      m = v / std::pow(10.0, e);
      std::snprintf(buf, sizeof buf, "%.9f", std::fabs(m));
    }
    char out[32];
    std::snprintf(out, sizeof out, "%s%sE%c%02d", v < 0 ? "-" : " ", buf, e < 0 ? '-' : '+', std::abs(e));
    return std::string(out);
  };
  const int nvals = 4 * g.ntheta;
  for (int i = 0; i < g.nr; ++i) {
    std::snprintf(buf, sizeof buf, " LREC= %5d     IENT=    2      IREC= %5d\n", nvals, i + 1);
    os << buf;
    for (int k = 0; k < nvals; ++k) {
      double v = k < g.ntheta ? map.value(i, k) / kKiloGauss : 0.0;
      os << efmt(v);
      if (k % 5 == 4 || k == nvals - 1) os << "\n";
    }
  }
}

void write_turnfit_map(std::ostream& os, const PolarFieldMap& map) {
  const PolarGrid& g = map.grid();
  os << "turnfit-fieldmap 1\n";
  if (!map.label().empty()) os << "label " << map.label() << "\n";
  os << "symmetry " << g.symmetry << "\n"
     << "r_min_mm " << format_exact(g.r_min_mm) << "\n"
     << "dr_mm " << format_exact(g.dr_mm) << "\n"
     << "nr " << g.nr << "\n"
     << "theta_min_deg " << format_exact(g.theta_min_deg) << "\n"
     << "ntheta " << g.ntheta << "\n"
     << "unit T\n"
     << "data\n";
  for (int i = 0; i < g.nr; ++i) {
    for (int j = 0; j < g.ntheta; ++j) os << (j ? " " : "") << format_exact(map.value(i, j));
    os << "\n";
  }
}

}  // namespace turnfit
