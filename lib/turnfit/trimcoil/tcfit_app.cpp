// turnfit-tc-fit: rational fits of trim coil phase-shift scans (paper Sec. II.C, Eq. 2-3) and the
// normalized field profiles they imply, as machine-file entries, OPAL commands or tables.
#include "turnfit/trimcoil/tcfit_app.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <map>
#include <numeric>
#include <optional>
#include <sstream>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/synth/synth.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

namespace turnfit {

void add_tcfit_options(CLI::App& app, TcFitOptions& o) {
  app.description(
      "Fits each trim coil's phase-shift scan delta sin(phi)(r) by a rational function f/g (Ceres\n"
      "Levenberg-Marquardt, denominator kept free of roots on the window) and writes the coil's\n"
      "field profile B ~ -d/dr (f/g), normalized to a peak of +1, so that bmax_T is the coil's peak\n"
      "field (paper Sec. II.C). Input: CSV r_mm,dsinphi per coil (coil from '# coil=' or the file\n"
      "name) or one file with a coil column, as turnfit-synth writes them.");
  app.add_option("inputs", o.inputs, "Phase-shift CSV files ('-' or none: stdin)");
  app.add_option("--degrees", o.degrees,
                 "Numerator/denominator degrees N/M (the paper: 2/4, and 4/5 for TC1, TC16-18), or 'auto'")
      ->capture_default_str();
  app.add_option("--criterion", o.criterion, "auto: the information criterion that picks the degrees")
      ->check(CLI::IsMember({"aicc", "bic"}))
      ->capture_default_str();
  app.add_option("--max-degrees", [&o](const std::vector<std::string>& v) {
    int n = -1, m = -1;
    char extra = 0;
    if (v.size() != 1 || std::sscanf(v[0].c_str(), "%d/%d%c", &n, &m, &extra) != 2 || n < 0 || m < 0 || n > 12 || m > 12)
      return false;
    o.max_numerator = n;
    o.max_denominator = m;
    return true;
  }, "auto: largest degrees tried, N/M (default 5/6)");
  app.add_option("--rmin", o.rmin_mm, "Window start [mm] (default: the machine's coil rmin, else the data's first radius)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_option("--rmax", o.rmax_mm, "Window end [mm] (default: the machine's coil rmax, else the data's last radius)")
      ->check(CLI::Range(0.0, 1e6));
  app.add_option("--model", o.model,
                 "What the rational f/g describes. paper: the phase shift itself (paper Eq. 2; field = -d/dr); "
                 "local: the field, fitted through the phase it integrates to (B ~ -d delta sin(phi)/dr, optionally "
                 "with --turns); tracked: the field, fitted through the phase shifts the --machine predicts by "
                 "tracking (the lag of the phase behind the field, the oscillation a coil starts, the trim coil "
                 "threshold; the fitted peak is the scan's test excitation in tesla)")
      ->check(CLI::IsMember({"paper", "local", "tracked"}))
      ->capture_default_str();
  app.add_option("--type", o.type,
                 "Machine-file description: psi-phase (f/g of the phase; paper model only) or psi-bfield (the field's "
                 "rational; from the paper model, its exact derivative). Default: psi-phase for --model paper, else "
                 "psi-bfield")
      ->check(CLI::IsMember({"psi-phase", "psi-bfield"}));
  app.add_option("--report", o.report, "Write the fit report (JSON) here ('-' for stdout)");
  app.add_option("--machine", o.machine,
                 "Take each coil's window (and bmax_T) from this machine file; with --format json, write the machine with its coils "
                 "replaced by name (sectors, azimuth window, bmax_T kept)");
  app.add_option("--grid-mm", o.grid_mm, "csv: spacing of the fine grid [mm]")->check(CLI::Range(1e-3, 1e4))->capture_default_str();
  app.add_option("--max-iterations", o.max_iterations, "Levenberg-Marquardt iterations per start")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--turns", o.turns,
                 "Turns table of the machine (turnfit-track's output): correct each scan by V_turn/beta, the factor "
                 "between phase slope and field, before fitting");
  app.add_option("--mass-MeV", o.mass_MeV, "Rest mass for beta with --turns (default: the machine's particle, else proton)")
      ->check(CLI::Range(1e-3, 1e6));
  app.add_option("--response-step-mm", o.response_step_mm, "--model tracked: knot spacing of the cubic B-spline field basis [mm]")
      ->check(CLI::Range(1.0, 1000.0))
      ->capture_default_str();
  app.add_option("--phase-azimuth-deg", [&o](const std::vector<std::string>& v) {
    if (v.size() != 1 || !parse_decimal(v[0], o.phase_azimuth_deg)) return false;
    o.phase_azimuth_given = true;
    return true;
  }, "--model tracked: azimuth of the phase probes [deg] (default: the scan's '# azimuth_deg=', else 0)");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kFormat | cli::kThreads, {"json", "opal", "csv"});
}

double SlopeWeight::at(double r) const {
  if (r <= r_mm.front()) return w.front();
  if (r >= r_mm.back()) return w.back();
  const size_t i = static_cast<size_t>(std::upper_bound(r_mm.begin(), r_mm.end(), r) - r_mm.begin()) - 1;
  const double t = (r - r_mm[i]) / (r_mm[i + 1] - r_mm[i]);
  return w[i] + t * (w[i + 1] - w[i]);
}

SlopeWeight read_slope_weight(const std::string& path, double mass_MeV) {
  const CsvTable t = CsvTable::read(path);
  t.require_columns({"turn", "r_mm", "energy_MeV"});
  const size_t ct = t.column("turn"), cr = t.column("r_mm"), ce = t.column("energy_MeV");
  // The probe with most turns (its turns are consecutive crossings of one radial line).
  std::map<std::string, std::vector<size_t>> rows;
  const bool has_probe = t.has_column("probe");
  for (size_t i = 0; i < t.rows(); ++i) rows[has_probe ? t.cell(i, t.column("probe")) : std::string()].push_back(i);
  const std::vector<size_t>* best = nullptr;
  for (const auto& kv : rows)
    if (!best || kv.second.size() > best->size()) best = &kv.second;
  struct Turn {
    double n, r, e;
    long line;
  };
  std::vector<Turn> turns;
  for (size_t i : *best) turns.push_back({t.number(i, ct), t.number(i, cr), t.number(i, ce), t.line(i)});
  std::sort(turns.begin(), turns.end(), [](const Turn& a, const Turn& b) { return a.n < b.n; });
  if (turns.size() < 3) throw data_error(t.name(), 0, "--turns needs at least 3 turns of one probe");
  SlopeWeight sw;
  for (size_t k = 0; k + 1 < turns.size(); ++k) {
    const Turn &a = turns[k], &b = turns[k + 1];
    if (!(b.n > a.n) || !(b.e > a.e) || !(b.r > a.r))
      throw data_error(t.name(), b.line, "turn number, radius and energy must increase from turn to turn");
    const double e = 0.5 * (a.e + b.e), gamma = 1 + e / mass_MeV;
    const double beta = std::sqrt(1 - 1 / (gamma * gamma));
    sw.r_mm.push_back(0.5 * (a.r + b.r));
    sw.w.push_back((b.e - a.e) / (b.n - a.n) / beta);
  }
  return sw;
}

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// "key=value" tokens of '#' comment lines.
std::map<std::string, std::string> metadata(const std::vector<std::string>& comments) {
  std::map<std::string, std::string> kv;
  for (const std::string& line : comments) {
    std::istringstream is(line.substr(1));
    std::string tok;
    while (is >> tok) {
      const auto eq = tok.find('=');
      if (eq != std::string::npos && eq > 0) kv.emplace(tok.substr(0, eq), tok.substr(eq + 1));
    }
  }
  return kv;
}

/// A metadata value as a finite number (0 if absent or not a number: the keys are informative).
double meta_number(const std::map<std::string, std::string>& kv, const std::string& key) {
  const auto it = kv.find(key);
  if (it == kv.end()) return 0;
  double v = 0;
  return parse_decimal(trim(it->second), v) ? v : 0;
}

bool valid_coil_name(const std::string& s) {
  return !s.empty() && s.find_first_of(",\"\r\n") == std::string::npos;
}

/// Sorts a coil's points by radius and refuses duplicate radii (naming both lines).
void sort_points(PhaseData& d) {
  std::vector<size_t> idx(d.r_mm.size());
  std::iota(idx.begin(), idx.end(), size_t{0});
  std::stable_sort(idx.begin(), idx.end(), [&](size_t i, size_t j) { return d.r_mm[i] < d.r_mm[j]; });
  PhaseData s = d;
  for (size_t k = 0; k < idx.size(); ++k) {
    s.r_mm[k] = d.r_mm[idx[k]];
    s.dsinphi[k] = d.dsinphi[idx[k]];
    s.lines[k] = d.lines[idx[k]];
    if (k > 0 && s.r_mm[k] == s.r_mm[k - 1] && s.error.empty())
      s.error = d.source + ":" + std::to_string(std::max(s.lines[k], s.lines[k - 1])) + ": duplicate radius r_mm=" +
                cli::fmt(s.r_mm[k]) + " (also on line " + std::to_string(std::min(s.lines[k], s.lines[k - 1])) + ")";
  }
  d = std::move(s);
}

std::string degrees_string(int n, int m) { return std::to_string(n) + "/" + std::to_string(m); }

/// The fixed degrees of --degrees N/M (usage error if malformed).
bool parse_degrees(const std::string& s, int& n, int& m) {
  if (s == "auto") return false;
  char extra = 0;
  if (std::sscanf(s.c_str(), "%d/%d%c", &n, &m, &extra) != 2 || n < 0 || m < 0 || n > 12 || m > 12)
    throw usage_error("--degrees '" + s + "': give N/M (0 <= N, M <= 12) or auto");
  return true;
}

double criterion_of(const RationalFit& f, const std::string& c) { return c == "bic" ? f.bic : f.aicc; }

/// u(r) = -d(f/g)/dr [1/m]: the unnormalized field shape (paper Eq. 3, B ~ -d sin(phi)/dr).
double raw_shape(const RationalFit& f, double r_mm) {
  double dy, d2y;
  f.slope(r_mm, dy, d2y);
  return -dy * 1e3;
}

/// Where |u| peaks on [lo, hi]: a dense scan, then golden-section refinement.
double peak_of(const RationalFit& f, double lo, double hi) {
  const int n = 4000;
  double best_r = lo, best = -1;
  for (int i = 0; i <= n; ++i) {
    const double r = lo + (hi - lo) * i / n, v = std::fabs(raw_shape(f, r));
    if (v > best) {
      best = v;
      best_r = r;
    }
  }
  const double h = (hi - lo) / n;
  double a = std::max(lo, best_r - h), b = std::min(hi, best_r + h);
  const double gr = 0.5 * (std::sqrt(5.0) - 1);
  for (int it = 0; it < 60; ++it) {
    const double c = b - gr * (b - a), d = a + gr * (b - a);
    if (std::fabs(raw_shape(f, c)) > std::fabs(raw_shape(f, d))) b = d;
    else a = c;
  }
  const double r = 0.5 * (a + b);
  return std::fabs(raw_shape(f, r)) >= best ? r : best_r;
}

/// Coefficients of p(r - origin) as a polynomial in r itself (OPAL's form), in long double.
std::vector<double> about_zero(const std::vector<double>& c, double origin_m) {
  return polynomial_in_r(c, origin_m, 1.0);
}

/// Largest |shape of entry t - fitted shape| on the window (shape peak 1).
double representation_error(const CoilFit& c, TrimCoil t) {
  t.bmax_T = 1;
  TrimCoilField field(t, 1);
  double err = 0;
  for (int i = 0; i <= 2000; ++i) {
    const double r = c.r_lo_mm + (c.r_hi_mm - c.r_lo_mm) * i / 2000;
    double s, ds, se, dse;
    field.shape_exact(r * 1e-3, s, ds);
    fitted_shape(c, r, se, dse);
    err = std::max(err, std::fabs(s - se));
  }
  return err;
}

/// The machine-file entry of a fit, normalized so the field shape peaks at +1: polynomials in
/// (r - window centre) [m] (coef_origin_mm), which keep full precision; the OPAL form expands
/// them in r itself and reports what that loses.
void build_coil(CoilFit& c, const std::string& type) {
  const RationalFit& f = c.fit;
  c.peak_r_mm = peak_of(f, c.r_lo_mm, c.r_hi_mm);
  c.slope_per_m = raw_shape(f, c.peak_r_mm);
  if (!(std::fabs(c.slope_per_m) > 0))
    throw Error(ExitCode::data, "the fitted phase shift is flat on the window: it implies no field");
  const double hm = f.half_width * 1e-3, inv = 1 / c.slope_per_m;
  TrimCoil& t = c.coil;
  t.name = c.data.name;
  t.rmin_mm = c.r_lo_mm;
  t.rmax_mm = c.r_hi_mm;
  t.bmax_T = 0;
  t.coef_origin_mm = f.centre;
  std::vector<double> num = f.a;
  // paper: OPAL's PSI-PHASE field is -bmax d(f/g)/dr, so f/g itself is the phase over the divisor;
  // local and tracked: f/g is the field, -dy/dr = (f/g) / half_width.
  for (double& v : num) v *= f.model == RationalModel::value ? inv : inv / hm;
  t.type = f.model == RationalModel::value ? "psi-phase" : "psi-bfield";
  t.coefnum = polynomial_in_r(num, 0.0, hm);
  t.coefdenom = polynomial_in_r(f.b, 0.0, hm);
  if (type == "psi-bfield" && t.type == "psi-phase") t = bfield_from_phase(t);
  c.representation_error = representation_error(c, t);
  c.opal_coil = t;
  c.opal_coil.coef_origin_mm = 0;
  c.opal_coil.coefnum = about_zero(t.coefnum, f.centre * 1e-3);
  c.opal_coil.coefdenom = about_zero(t.coefdenom, f.centre * 1e-3);
  c.opal_representation_error = representation_error(c, c.opal_coil);
}

/// The fit window of a coil: --rmin/--rmax, else the machine coil's support, each clipped to the
/// data (a rational is not extrapolated).
void choose_window(CoilFit& c, const TcFitOptions& o, const TrimCoil* mc) {
  const double dlo = c.data.r_mm.front(), dhi = c.data.r_mm.back();
  double lo = o.rmin_mm > 0 ? o.rmin_mm : mc ? mc->rmin_mm : dlo;
  double hi = o.rmax_mm > 0 ? o.rmax_mm : mc ? mc->rmax_mm : dhi;
  lo = std::max(lo, dlo);
  hi = std::min(hi, dhi);
  if (!(hi > lo))
    throw Error(ExitCode::data, "the window [" + cli::fmt(o.rmin_mm > 0 ? o.rmin_mm : mc ? mc->rmin_mm : dlo) + ", " +
                                    cli::fmt(o.rmax_mm > 0 ? o.rmax_mm : mc ? mc->rmax_mm : dhi) +
                                    "] mm holds no data (data " + cli::fmt(dlo) + " to " + cli::fmt(dhi) + " mm)");
  c.r_lo_mm = lo;
  c.r_hi_mm = hi;
}

}  // namespace

std::vector<PhaseData> read_phase_data(const std::string& path) {
  const CsvTable t = CsvTable::read(path);
  t.require_columns({"r_mm", "dsinphi"});
  const auto meta = metadata(t.comments());
  const size_t cr = t.column("r_mm"), cy = t.column("dsinphi");
  const bool has_coil = t.has_column("coil");
  const double excitation = meta_number(meta, "excitation_T"), azimuth = meta_number(meta, "azimuth_deg");
  std::string file_coil;
  if (!has_coil) {
    if (auto it = meta.find("coil"); it != meta.end()) file_coil = it->second;
    else if (path != "-" && !path.empty()) file_coil = std::filesystem::path(path).stem().string();
    if (file_coil.empty())
      throw data_error(t.name(), 0, "no coil name: add a 'coil' column or a '# coil=NAME' line");
    if (!valid_coil_name(file_coil)) throw data_error(t.name(), 0, "coil name '" + file_coil + "' holds a comma or quote");
  }
  std::vector<PhaseData> out;
  std::map<std::string, size_t> index;
  for (size_t i = 0; i < t.rows(); ++i) {
    const std::string name = has_coil ? t.cell(i, t.column("coil")) : file_coil;
    if (!valid_coil_name(name)) throw data_error(t.name(), t.line(i), "coil name '" + name + "' is empty or holds a quote");
    auto [it, fresh] = index.emplace(name, out.size());
    if (fresh) {
      PhaseData d;
      d.name = name;
      d.source = t.name();
      d.excitation_T = excitation;
      d.azimuth_deg = azimuth;
      out.push_back(std::move(d));
    }
    PhaseData& d = out[it->second];
    if (!d.error.empty()) continue;
    try {
      const double r = t.number(i, cr), y = t.number(i, cy);
      d.r_mm.push_back(r);
      d.dsinphi.push_back(y);
      d.lines.push_back(t.line(i));
    } catch (const Error& e) {
      d.error = e.what();
    }
  }
  if (out.empty()) throw data_error(t.name(), 0, "no data rows");
  for (PhaseData& d : out)
    if (d.error.empty()) sort_points(d);
  return out;
}

LinearResponse coil_response(const Machine& m, const TrimCoil* mc, const std::vector<double>& r_mm, double r_lo,
                             double r_hi, double step, double azimuth_deg, unsigned threads,
                             std::map<std::string, std::vector<double>>& cache) {
  const TrackSettings st = machine_track_settings(m);
  if (!(st.turns > 0)) throw data_error(m.path, 0, "/tracking/turns: --model tracked tracks the machine; it has no turn count");
  // The knots: multiples of the step inside the window (shared between coils, so cached).
  std::vector<long> knots;
  for (long k = static_cast<long>(std::ceil(r_lo / step - 1e-9)); static_cast<double>(k) * step <= r_hi + 1e-9; ++k)
    knots.push_back(k);
  if (knots.size() < 3)
    throw Error(ExitCode::data, "the window is narrower than 2 knots of the response basis (--response-step-mm " +
                                    cli::fmt(step) + ")");
  std::string key = "sectors";
  if (mc) {
    for (int s : mc->sectors) key += " " + std::to_string(s);
    key += " phi " + cli::fmt(mc->phimin_deg) + " " + cli::fmt(mc->phimax_deg);
  }
  key += " step " + cli::fmt(step) + " az " + cli::fmt(azimuth_deg) + " at";
  for (double r : r_mm) key += " " + cli::fmt(r);
  constexpr double kEps = 1e-4;  // T: small enough to stay linear, large against round-off
  std::vector<TrimCoil> todo;
  std::vector<std::string> todo_keys;
  for (long k : knots) {
    const std::string kk = key + " knot " + std::to_string(k);
    if (cache.count(kk)) continue;
    const double t = static_cast<double>(k) * step;
    TrimCoil b;
    b.name = "basis" + std::to_string(k);
    b.type = "table";
    b.rmin_mm = t - 2 * step;
    b.rmax_mm = t + 2 * step;
    b.bmax_T = kEps;
    if (mc) {
      b.sectors = mc->sectors;
      b.phimin_deg = mc->phimin_deg;
      b.phimax_deg = mc->phimax_deg;
    }
    // The uniform cubic B-spline: values and exact slopes at its knots, so the Hermite table
    // is the spline itself.
    for (int j = -2; j <= 2; ++j) b.table_r_mm.push_back(t + j * step);
    b.table_shape = {0, 1.0 / 6, 2.0 / 3, 1.0 / 6, 0};
    b.table_slope = {0, 0.5 / step, 0, -0.5 / step, 0};
    todo.push_back(b);
    todo_keys.push_back(kk);
  }
  if (!todo.empty()) {
    const auto cols = phase_response(m, todo, r_mm, st, azimuth_deg, threads);
    for (size_t i = 0; i < todo.size(); ++i) cache[todo_keys[i]] = cols[i];
  }
  const auto G = static_cast<Eigen::Index>(knots.size());
  Eigen::MatrixXd Kb(static_cast<Eigen::Index>(r_mm.size()), G);
  for (Eigen::Index j = 0; j < G; ++j) {
    const auto& col = cache.at(key + " knot " + std::to_string(knots[static_cast<size_t>(j)]));
    for (size_t i = 0; i < r_mm.size(); ++i) Kb(static_cast<Eigen::Index>(i), j) = col[i];
  }
  // Spline coefficients from samples: exact for cubics inside, the samples themselves at the ends.
  Eigen::MatrixXd Q = Eigen::MatrixXd::Zero(G, G);
  Q(0, 0) = 1;
  Q(G - 1, G - 1) = 1;
  for (Eigen::Index j = 1; j + 1 < G; ++j) {
    Q(j, j - 1) = -1.0 / 6;
    Q(j, j) = 8.0 / 6;
    Q(j, j + 1) = -1.0 / 6;
  }
  LinearResponse lr;
  for (long k : knots) lr.r_grid.push_back(static_cast<double>(k) * step);
  lr.K = Kb * Q;
  return lr;
}

double fitted_shape_sigma(const CoilFit& c, double r_mm) {
  if (c.fit.covariance.size() == 0 || c.slope_per_m == 0) return kNaN;
  double s, ds;
  fitted_shape(c, r_mm, s, ds);
  // s = D(r) / D(r_peak): its gradient (grad D(r) - s grad D(r_peak)) / D(r_peak).
  const double dpeak = -c.slope_per_m * 1e-3;  // dq/dr at the peak, per mm
  const Eigen::VectorXd g = (c.fit.slope_gradient(r_mm) - s * c.fit.slope_gradient(c.peak_r_mm)) / dpeak;
  const double v = g.dot(c.fit.covariance * g);
  return v > 0 ? std::sqrt(v) : 0;
}

void fitted_shape(const CoilFit& c, double r_mm, double& s, double& ds) {
  s = ds = 0;
  if (r_mm < c.r_lo_mm || r_mm > c.r_hi_mm || c.slope_per_m == 0) return;
  double dy, d2y;
  c.fit.slope(r_mm, dy, d2y);
  s = -dy * 1e3 / c.slope_per_m;
  ds = -d2y * 1e6 / c.slope_per_m;
}

CoilFit fit_coil(const PhaseData& input, const TcFitOptions& o, const TrimCoil* mc, const SlopeWeight* weight,
                 const LinearResponse* response) {
  CoilFit c;
  c.data = input;
  if (!input.error.empty()) {
    c.error = input.error;
    return c;
  }
  try {
    if (input.r_mm.empty()) throw Error(ExitCode::data, "no data points");
    choose_window(c, o, mc);
    PhaseData data = input;
    if (weight) {
      // Summation by parts: each step of the scan scaled by the weight at its middle, so the
      // slope of the result follows the field (see SlopeWeight).
      const double wref = weight->at(0.5 * (c.r_lo_mm + c.r_hi_mm));
      for (size_t i = 1; i < data.r_mm.size(); ++i)
        data.dsinphi[i] = data.dsinphi[i - 1] + weight->at(0.5 * (input.r_mm[i - 1] + input.r_mm[i])) / wref *
                                                    (input.dsinphi[i] - input.dsinphi[i - 1]);
      c.weighted = true;
      c.weight_lo = weight->at(c.r_lo_mm) / wref;
      c.weight_hi = weight->at(c.r_hi_mm) / wref;
      c.data = data;
    }
    // psi-phase: the paper's model, f/g through the phase shift itself; psi-bfield: f/g is the
    // field bump, fitted through the phase it integrates to (a decaying rational suits a bump far
    // better than a step, which pulls poles towards the real axis).
    const RationalModel model = o.model == "paper"   ? RationalModel::value
                                : o.model == "tracked" ? RationalModel::response
                                                       : RationalModel::integral;
    if (model == RationalModel::response && !response)
      throw Error(ExitCode::software, "fit_coil: --model tracked without a response");
    int n = 0, m = 0;
    if (parse_degrees(o.degrees, n, m)) {
      c.fit = fit_rational(data.r_mm, data.dsinphi, c.r_lo_mm, c.r_hi_mm, n, m, {}, o.max_iterations, model, response);
      c.selected_by = "--degrees";
    } else {
      // Every (n, m) up to the limits that leaves the criterion defined (N - p - 1 > 0); each
      // fit also starts from the one with a numerator degree less, so adding a parameter never
      // fits worse. The criterion picks.
      size_t npts = 0;
      for (double r : data.r_mm) npts += r >= c.r_lo_mm && r <= c.r_hi_mm;
      std::map<std::pair<int, int>, size_t> done;
      const int extra = model == RationalModel::integral ? 1 : 0;
      for (int mm = 0; mm <= o.max_denominator; ++mm) {
        for (int nn = 0; nn <= o.max_numerator; ++nn) {
          if (static_cast<size_t>(nn + 1 + mm + extra) + 1 >= npts) continue;
          // A field model must fall off away from the coil like a bump: m >= n + 2 (f/g ~ x^-2).
          if (model != RationalModel::value && mm < nn + 2) continue;
          std::vector<RationalFit> starts;
          if (auto it = done.find({nn - 1, mm}); it != done.end()) starts.push_back(c.candidates[it->second]);
          try {
            // Few extra starts per candidate: a candidate held at the pole bound is passed over.
            RationalFit f = fit_rational(data.r_mm, data.dsinphi, c.r_lo_mm, c.r_hi_mm, nn, mm, starts, o.max_iterations,
                                         model, response, 4);
            done[{nn, mm}] = c.candidates.size();
            c.candidates.push_back(std::move(f));
          } catch (const Error& e) {
            c.candidate_errors.push_back(degrees_string(nn, mm) + ": " + e.what());
          }
        }
      }
      if (c.candidates.empty())
        throw Error(ExitCode::data, c.candidate_errors.empty()
                                        ? std::to_string(npts) + " points in the window: too few for any rational fit"
                                        : "no degrees up to " + std::to_string(o.max_numerator) + "/" +
                                              std::to_string(o.max_denominator) + " give a usable fit of the " +
                                              std::to_string(npts) + " points (" +
                                              std::to_string(c.candidate_errors.size()) + " tried; e.g. " +
                                              c.candidate_errors.front() + ")");
      // The criterion picks among the candidates whose field falls off inside the window (at most
      // 0.3 of its peak at both ends: a coil's field does, and a fit whose peak sits on the
      // window's edge is fitting the step's shoulder); only if none does, among all.
      auto falls_off = [&](const RationalFit& f) {
        const double pk = std::fabs(raw_shape(f, peak_of(f, c.r_lo_mm, c.r_hi_mm)));
        return pk > 0 && std::fabs(raw_shape(f, c.r_lo_mm)) <= 0.3 * pk && std::fabs(raw_shape(f, c.r_hi_mm)) <= 0.3 * pk;
      };
      std::vector<bool> ok(c.candidates.size());
      bool any_ok = false;
      for (size_t k = 0; k < c.candidates.size(); ++k) {
        ok[k] = falls_off(c.candidates[k]);
        any_ok = any_ok || ok[k];
      }
      size_t best = c.candidates.size();
      for (size_t k = 0; k < c.candidates.size(); ++k) {
        if (any_ok && !ok[k]) continue;
        if (best == c.candidates.size() ||
            criterion_of(c.candidates[k], o.criterion) < criterion_of(c.candidates[best], o.criterion))
          best = k;
      }
      c.fit = c.candidates[best];
      c.selected_by = o.criterion + (any_ok ? " (among fits falling off inside the window)" : " (no fit falls off inside the window)");
    }
    build_coil(c, o.type.empty() ? (o.model == "paper" ? "psi-phase" : "psi-bfield") : o.type);
  } catch (const Error& e) {
    c.error = e.what();
  }
  return c;
}

namespace {

std::string num17(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

nlohmann::json coil_json(const TrimCoil& t) {
  return {{"name", t.name},       {"type", t.type},       {"rmin_mm", t.rmin_mm},     {"rmax_mm", t.rmax_mm},
          {"bmax_T", t.bmax_T},   {"coef_origin_mm", t.coef_origin_mm}, {"coefnum", t.coefnum},
          {"coefdenom", t.coefdenom}};
}

/// A JSON number or null (JSON has no NaN or infinity).
nlohmann::json finite_or_null(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); }

/// Relative paths of a machine document re-expressed for a document written into `to_dir`
/// (absolute when writing to stdout).
void rebase_paths(nlohmann::json& doc, const std::string& from_dir, const std::string& out_path) {
  namespace fs = std::filesystem;
  const bool to_stdout = out_path.empty() || out_path == "-";
  const fs::path to_dir = to_stdout ? fs::path() : fs::absolute(fs::path(out_path)).parent_path();
  auto fix = [&](nlohmann::json& v) {
    if (!v.is_string()) return;
    const fs::path p(v.get<std::string>());
    if (p.empty() || p.is_absolute()) return;
    const fs::path abs = fs::absolute(fs::path(from_dir.empty() ? "." : from_dir) / p).lexically_normal();
    v = to_stdout ? abs.string() : abs.lexically_relative(to_dir).string();
  };
  if (doc.contains("field") && doc["field"].is_object() && doc["field"].contains("map")) fix(doc["field"]["map"]);
  for (const char* arr : {"cavities", "trimcoils"})
    if (doc.contains(arr) && doc[arr].is_array())
      for (auto& e : doc[arr])
        for (const char* key : {"profile", "table"})
          if (e.is_object() && e.contains(key)) fix(e[key]);
  if (doc.contains("bunch") && doc["bunch"].is_object() && doc["bunch"].contains("file")) fix(doc["bunch"]["file"]);
}

}  // namespace

void write_tcfit_output(std::ostream& os, const std::vector<CoilFit>& fits, const TcFitOptions& o) {
  const bool prov = !o.common.no_provenance;
  if (o.common.format == "opal") {
    if (prov) {
      std::string pc = cli::provenance_comment();  // '#' lines -> OPAL '//' comments
      std::istringstream is(pc);
      for (std::string line; std::getline(is, line);) os << "//" << line.substr(line.empty() ? 0 : 1) << "\n";
    }
    os << "// Trim coils fitted to phase-shift data by turnfit-tc-fit. OPAL: RMIN/RMAX in mm, BMAX in T,\n"
          "// coefficients for r in m. OPAL adds PSI-PHASE and PSI-BFIELD to the sign-flipped Bz, so\n"
          "// BMAX = -bmax_T (turnfit's convention: positive strengthens the field).\n";
    std::string list;
    for (const CoilFit& c : fits) {
      if (!c.error.empty()) continue;
      const TrimCoil& t = c.opal_coil;
      std::string ident = t.name;
      for (char& ch : ident)
        if (!std::isalnum(static_cast<unsigned char>(ch)) && ch != '_') ch = '_';
      if (ident.empty() || std::isdigit(static_cast<unsigned char>(ident[0]))) ident = "TC_" + ident;
      auto join = [](const std::vector<double>& v) {
        std::string s;
        for (size_t k = 0; k < v.size(); ++k) s += (k ? ", " : "") + num17(v[k]);
        return s;
      };
      std::string type = t.type == "psi-phase" ? "PSI-PHASE" : "PSI-BFIELD";
      os << ident << ": TRIMCOIL, TYPE = \"" << type << "\",\n"
         << "    RMIN = " << num17(t.rmin_mm) << ", RMAX = " << num17(t.rmax_mm) << ", BMAX = " << num17(-t.bmax_T) << ",\n"
         << "    COEFNUM = {" << join(t.coefnum) << "},\n"
         << "    COEFDENOM = {" << join(t.coefdenom) << "};\n";
      list += (list.empty() ? "" : ", ") + ident;
    }
    os << "// Ring: CYCLOTRON, TRIMCOILTHRESHOLD = ..., TRIMCOIL = {" << list << "}, ...;\n";
    return;
  }
  if (o.common.format == "csv") {
    if (prov) os << cli::provenance_comment();
    os << "# b_shape: field profile normalized to a peak of +1 (the coil's field is bmax_T * b_shape);"
          " db_dr_shape per mm; *_sigma: 1-sigma from the fit's covariance\n";
    os << "coil,r_mm,dsinphi_fit,dsinphi_sigma,b_shape,b_shape_sigma,db_dr_shape\n";
    char buf[256];
    for (const CoilFit& c : fits) {
      if (!c.error.empty()) continue;
      std::vector<double> rs;
      for (double r : c.data.r_mm)
        if (r >= c.r_lo_mm && r <= c.r_hi_mm) rs.push_back(r);
      const long steps = static_cast<long>(std::ceil((c.r_hi_mm - c.r_lo_mm) / o.grid_mm - 1e-9));
      for (long k = 0; k <= steps; ++k) rs.push_back(std::min(c.r_hi_mm, c.r_lo_mm + static_cast<double>(k) * o.grid_mm));
      std::sort(rs.begin(), rs.end());
      rs.erase(std::unique(rs.begin(), rs.end()), rs.end());
      for (double r : rs) {
        double s, ds;
        fitted_shape(c, r, s, ds);
        std::snprintf(buf, sizeof buf, "%s,%.6f,%.9g,%.4g,%.9g,%.4g,%.9g\n", c.coil.name.c_str(), r, c.fit.value(r),
                      c.fit.value_sigma(r), s, fitted_shape_sigma(c, r), ds * 1e-3);
        os << buf;
      }
    }
    return;
  }
  nlohmann::json doc;
  if (prov) doc["provenance"] = cli::provenance();
  doc["format"] = "turnfit-trimcoils/1";
  nlohmann::json arr = nlohmann::json::array();
  for (const CoilFit& c : fits)
    if (c.error.empty()) arr.push_back(coil_json(c.coil));
  doc["trimcoils"] = arr;
  os << json_text(doc, 2) << "\n";
}

nlohmann::json tcfit_report(const std::vector<CoilFit>& fits, const TcFitOptions& o) {
  using nlohmann::json;
  json doc;
  if (!o.common.no_provenance) doc["provenance"] = cli::provenance();
  doc["format"] = "turnfit-tcfit-report/1";
  doc["model"] = o.model;
  doc["type"] = o.type.empty() ? (o.model == "paper" ? "psi-phase" : "psi-bfield") : o.type;
  doc["degrees"] = o.degrees;
  if (o.degrees == "auto") doc["criterion"] = o.criterion;
  json coils = json::array();
  for (const CoilFit& c : fits) {
    json j;
    j["name"] = c.data.name;
    j["source"] = c.data.source;
    if (c.data.excitation_T != 0) j["excitation_T"] = c.data.excitation_T;
    if (!c.error.empty()) {
      j["status"] = "failed";
      j["error"] = c.error;
      coils.push_back(j);
      continue;
    }
    const RationalFit& f = c.fit;
    j["status"] = "ok";
    j["window_mm"] = {c.r_lo_mm, c.r_hi_mm};
    j["points"] = f.points;
    j["degrees"] = {f.n, f.m};
    j["selected_by"] = c.selected_by;
    j["rms"] = f.rms;
    j["max_abs"] = f.max_abs;
    j["sigma_y"] = f.sigma_y;
    j["condition"] = finite_or_null(f.condition);
    j["min_denominator"] = f.min_denominator;
    j["start"] = f.start;
    if (std::isfinite(f.rss_at_pole_bound)) j["rss_at_pole_bound"] = f.rss_at_pole_bound;
    j["iterations"] = f.iterations;
    j["aicc"] = finite_or_null(f.aicc);
    j["bic"] = finite_or_null(f.bic);
    // The fitted parameters themselves, in the variable they were fitted in.
    json sc;
    sc["x"] = "(r_mm - centre_mm) / half_width_mm";
    sc["centre_mm"] = f.centre;
    sc["half_width_mm"] = f.half_width;
    sc["a"] = f.a;
    sc["b"] = f.b;
    sc["describes"] = f.model == RationalModel::value      ? "y = f/g"
                      : f.model == RationalModel::integral ? "y = c - integral_{-1}^{x} f/g dx'"
                                                           : "y_i = c + sum_j K_ij (f/g)(x_j)";
    if (f.model != RationalModel::value) {  // both fit a constant c, the last parameter
      sc["c"] = f.offset;
      sc["sigma_c"] = finite_or_null(f.sigma.back());
    }
    json sa = json::array(), sb = json::array({0.0});
    for (int k = 0; k <= f.n + f.m; ++k) (k <= f.n ? sa : sb).push_back(finite_or_null(f.sigma[static_cast<size_t>(k)]));
    sc["sigma_a"] = sa;
    sc["sigma_b"] = sb;
    j["scaled"] = sc;
    double s_lo, s_hi, d;
    fitted_shape(c, c.r_lo_mm, s_lo, d);
    fitted_shape(c, c.r_hi_mm, s_hi, d);
    j["peak"] = {{"r_mm", c.peak_r_mm}, {"slope_per_m", c.slope_per_m}};
    j["edge_shape"] = {s_lo, s_hi};
    j["representation_error"] = c.representation_error;
    j["opal_representation_error"] = c.opal_representation_error;
    if (f.model == RationalModel::response) {
      // f/g is the field [T] of the scan's test excitation as the model's coil would make it.
      double q, dq, d2q;
      f.eval(c.peak_r_mm, q, dq, d2q);
      j["peak_field_T"] = q;
    }
    if (c.weighted) j["weight"] = {{"what", "V_turn/beta over its window-centre value"}, {"at_window_ends", {c.weight_lo, c.weight_hi}}};
    if (!c.candidates.empty()) {
      json cand = json::array();
      for (const RationalFit& k : c.candidates)
        cand.push_back({{"degrees", {k.n, k.m}}, {"rms", k.rms}, {"aicc", finite_or_null(k.aicc)}, {"bic", finite_or_null(k.bic)}});
      j["candidates"] = cand;
      if (!c.candidate_errors.empty()) j["candidate_errors"] = c.candidate_errors;
    }
    j["trimcoil"] = coil_json(c.coil);
    coils.push_back(j);
  }
  doc["coils"] = coils;
  return doc;
}

int run_tcfit(const TcFitOptions& o) {
  int n = 0, m = 0;
  parse_degrees(o.degrees, n, m);  // a malformed --degrees is a usage error before any work
  if (o.rmin_mm > 0 && o.rmax_mm > 0 && !(o.rmax_mm > o.rmin_mm)) throw usage_error("--rmax must exceed --rmin");
  const std::vector<std::string> inputs = o.inputs.empty() ? std::vector<std::string>{"-"} : o.inputs;
  size_t stdin_uses = 0;
  for (const std::string& p : inputs) stdin_uses += p == "-";
  auto is_stdout = [](const std::string& p) { return p.empty() || p == "-"; };
  if (!o.report.empty() && is_stdout(o.report) && is_stdout(o.common.output))
    throw usage_error("--report - and the result would both go to stdout: give -o FILE or --report FILE");
  // Both outputs are opened (as temporaries) before any work, so a result that cannot be
  // written leaves no report behind, and neither appears before both are complete.
  std::optional<OutputFile> out_result, out_report;
  out_result.emplace(o.common.output);
  if (!o.report.empty()) out_report.emplace(o.report);

  if (o.turns == "-") ++stdin_uses;
  if (stdin_uses > 1) throw usage_error("'-' (stdin) given more than once");
  std::optional<Machine> machine;
  if (!o.machine.empty()) machine = load_machine(o.machine);
  std::optional<SlopeWeight> weight;
  if (!o.turns.empty()) {
    const double mass = o.mass_MeV > 0 ? o.mass_MeV : machine ? machine->particle.mass_MeV : 938.27208816;
    weight = read_slope_weight(o.turns, mass);
  }

  // Read every input; a file that cannot be read is reported and skipped (the others still fit).
  std::vector<PhaseData> all;
  std::vector<std::string> file_errors;
  ExitCode worst = ExitCode::ok;
  for (const std::string& p : inputs) {
    try {
      for (PhaseData& d : read_phase_data(p)) all.push_back(std::move(d));
    } catch (const Error& e) {
      file_errors.push_back(e.what());
      if (worst == ExitCode::ok || e.code() == ExitCode::no_input) worst = e.code();
    }
  }
  std::map<std::string, std::string> seen;
  for (PhaseData& d : all) {
    auto [it, fresh] = seen.emplace(d.name, d.source);
    if (!fresh && d.error.empty()) d.error = "coil '" + d.name + "' also in " + it->second;
  }

  const bool tracked = o.model == "tracked";
  if (o.model != "paper" && o.type == "psi-phase")
    throw usage_error("--model " + o.model + " fits the field itself: its description is psi-bfield");
  if (tracked && !machine) throw usage_error("--model tracked tracks a machine: give --machine");
  if (tracked && weight) throw usage_error("--model tracked already holds the V_turn/beta factor: leave out --turns");
  std::map<std::string, std::vector<double>> response_cache;
  const unsigned threads = cli::resolve_threads(o.common.threads);
  std::vector<CoilFit> fits;
  for (const PhaseData& d : all) {
    const TrimCoil* mc = nullptr;
    if (machine)
      for (const TrimCoil& t : machine->trimcoils)
        if (t.name == d.name) mc = &t;
    if (machine && !mc)
      cli::warn(o.common, o.machine + ": has no trim coil '" + d.name + "': it is added with bmax_T 0");
    if (tracked && d.error.empty() && !d.r_mm.empty()) {
      // The window first (as fit_coil chooses it), then the response of this coil's scan.
      CoilFit probe;
      probe.data = d;
      try {
        choose_window(probe, o, mc);
        const double az = o.phase_azimuth_given ? o.phase_azimuth_deg : d.azimuth_deg;
        const LinearResponse lr = coil_response(*machine, mc, d.r_mm, probe.r_lo_mm, probe.r_hi_mm, o.response_step_mm,
                                                az, threads, response_cache);
        fits.push_back(fit_coil(d, o, mc, nullptr, &lr));
      } catch (const Error& e) {
        probe.error = e.what();
        fits.push_back(probe);
      }
      continue;
    }
    fits.push_back(fit_coil(d, o, mc, weight ? &*weight : nullptr));
  }
  // Keep the machine's peak field (a design variable) on the refitted coils.
  size_t ok = 0;
  for (CoilFit& c : fits) {
    if (!c.error.empty()) {
      if (worst == ExitCode::ok) worst = ExitCode::data;
      continue;
    }
    ++ok;
    if (machine)
      for (const TrimCoil& t : machine->trimcoils)
        if (t.name == c.coil.name) c.coil.bmax_T = t.bmax_T;
  }

  for (const std::string& e : file_errors) std::fprintf(stderr, "turnfit-tc-fit: %s\n", clip_message(e).c_str());
  for (const CoilFit& c : fits) {
    if (!c.error.empty()) {
      std::fprintf(stderr, "turnfit-tc-fit: %s\n",
                   clip_message("coil " + c.data.name + " (" + c.data.source + "): " + c.error).c_str());
      continue;
    }
    if (o.common.quiet) continue;
    std::fprintf(stderr,
                 "turnfit-tc-fit: %s: degrees %d/%d (%s), %zu points in %.6g-%.6g mm, rms %.3g, max %.3g, "
                 "condition %.3g, peak at %.6g mm\n",
                 clip_message(c.data.name).c_str(), c.fit.n, c.fit.m, c.selected_by.c_str(), c.fit.points, c.r_lo_mm, c.r_hi_mm,
                 c.fit.rms, c.fit.max_abs, c.fit.condition, c.peak_r_mm);
    double s_lo, s_hi, d;
    fitted_shape(c, c.r_lo_mm, s_lo, d);
    fitted_shape(c, c.r_hi_mm, s_hi, d);
    if (std::max(std::fabs(s_lo), std::fabs(s_hi)) > 0.05)
      cli::warn(o.common, c.data.name + ": the field profile is " + cli::fmt(s_lo, 3) + " and " + cli::fmt(s_hi, 3) +
                              " of its peak at the window's ends: the coil's field jumps there (widen the window)");
    if (c.representation_error > 1e-6)
      cli::warn(o.common, c.data.name + ": the coefficients reproduce the fitted profile only to " +
                              cli::fmt(c.representation_error, 3) + " of its peak");
    if (o.common.format == "opal" && c.opal_representation_error > 1e-6)
      cli::warn(o.common, c.data.name + ": OPAL's coefficients in r reproduce the fitted profile only to " +
                              cli::fmt(c.opal_representation_error, 3) + " of its peak (terms of r^k cancel at r ~ " +
                              cli::fmt(c.coil.coef_origin_mm * 1e-3, 2) + " m)");
  }

  // Outputs: the report always (it holds the failures), the result if any coil was fitted.
  if (out_report) out_report->stream() << json_text(tcfit_report(fits, o), 2) << "\n";
  if (ok == 0) {
    if (out_report) out_report->commit();
    if (worst == ExitCode::ok) worst = ExitCode::data;
    throw Error(worst, "no coil could be fitted");
  }
  std::ostringstream os;
  if (machine && o.common.format == "json") {
    nlohmann::json doc = machine->doc;
    for (const CoilFit& c : fits) {
      if (!c.error.empty()) continue;
      nlohmann::json* slot = nullptr;
      for (auto& e : doc["trimcoils"])
        if (e.value("name", std::string()) == c.coil.name) slot = &e;
      if (!slot) {
        doc["trimcoils"].push_back(nlohmann::json::object({{"name", c.coil.name}}));
        slot = &doc["trimcoils"].back();
      }
      for (const char* k : {"slope_per_mm", "table"}) slot->erase(k);
      (*slot)["type"] = c.coil.type;
      (*slot)["rmin_mm"] = c.coil.rmin_mm;
      (*slot)["rmax_mm"] = c.coil.rmax_mm;
      (*slot)["bmax_T"] = c.coil.bmax_T;
      (*slot)["coefnum"] = c.coil.coefnum;
      (*slot)["coefdenom"] = c.coil.coefdenom;
      (*slot)["coef_origin_mm"] = c.coil.coef_origin_mm;
    }
    rebase_paths(doc, machine->dir, o.common.output);
    // The written machine must load: validate it where it will live.
    const std::string out_dir = o.common.output.empty() || o.common.output == "-"
                                    ? std::string()
                                    : std::filesystem::absolute(o.common.output).parent_path().string();
    machine_from_json(doc, o.common.output.empty() ? "-" : o.common.output, out_dir);
    os << json_text(doc, 2) << "\n";
  } else {
    write_tcfit_output(os, fits, o);
  }
  out_result->stream() << os.str();
  out_result->commit();
  if (out_report) out_report->commit();
  return static_cast<int>(worst);
}

}  // namespace turnfit
