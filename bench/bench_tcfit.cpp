// Benchmark: turnfit's rational fits of ring8's 18 trim coil phase scans at the paper's degrees
// (2/4 for TC2-TC15, 4/5 for TC1 and TC16-TC18), each coil's window the machine coil's
// [rmin_mm, rmax_mm] clipped to the data (as turnfit-tc-fit --machine). Times fit_rational per
// coil (repeated until --min-time, median per fit) and prints CSV; bench_tcfit_scipy.py runs it
// and compares SciPy's least_squares on the same points (bench/RESULTS.md).
//
//   bench_tcfit [--machine machine.json] [--phase DIR] [--min-time S] [--detail]
//               [--extra-starts K] [--seed "COIL,N,M,A,B" ...]
//
// fit_rational is called with its default model (RationalModel::value: the paper's fit of the
// phase shift itself, Eq. 2) and its default extra_starts (64: the placed-root starts tried when
// every other start ends held at the pole bound; --extra-starts K to change it, 0 = none). Column
// rss_at_pole_bound is RationalFit::rss_at_pole_bound: the lower rss a fit held at the pole bound
// reached, when the fit returned is a resolvable optimum above it (nan if none was lower, or
// refused). --detail appends r_lo,r_hi,iterations,reps,a,b (coefficients in
// x = (r - centre)/half_width, space separated) for the comparison script. A coil fit_rational
// refuses (EX_DATAERR: too few points, or an optimum that wants a pole within one data
// spacing of the window) gets a row with rss nan, the median time to the refusal, and start
// "refused: <message>"; if it was refused for having fewer points than parameters (TC18 at 4/5),
// a second row fits it at 2/4 (start "fallback 2/4: ..." or "refused: ...").
//
// --seed (repeatable) fits only the coils named, at degrees N/M, giving fit_rational one more
// start: numerator A and denominator B (space-separated coefficients in x, in data units, B
// starting with 1), e.g. another tool's optimum: does turnfit reach it, and keep it? The row's
// start reads "seeded: <winning start>" (the seed is "lower degree") or "refused: ...".
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/trimcoil/rational_fit.hpp"

using namespace turnfit;
using Clock = std::chrono::steady_clock;

namespace {

struct Scan {
  std::string name;
  std::vector<double> r, y;
  double lo = 0, hi = 0;  // window
  int n = 2, m = 4;       // the paper's degrees
};

std::string join(const std::vector<double>& v) {
  std::string s;
  char buf[40];
  for (size_t i = 0; i < v.size(); ++i) {
    std::snprintf(buf, sizeof buf, "%s%.17g", i ? " " : "", v[i]);
    s += buf;
  }
  return s;
}

std::string csv_quote(const std::string& s) {
  if (s.find_first_of(",\"") == std::string::npos) return s;
  std::string q = "\"";
  for (char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

struct Timed {
  RationalFit fit;
  std::string refused;  // fit_rational's message if it refused the coil (EX_DATAERR)
  double median_ms = 0;
  size_t reps = 0;
};

/// Times fit_rational until min_time seconds have passed (at least 3 runs); median per call. A
/// refusal (EX_DATAERR) is timed as well: the time the library takes to give that answer.
Timed time_fit(const Scan& s, int n, int m, double min_time, int extra_starts,
               const std::vector<RationalFit>& starts = {}) {
  Timed t;
  std::vector<double> ms;
  const auto t0 = Clock::now();
  do {
    const auto a = Clock::now();
    RationalFit f;
    std::string why;
    try {
      f = fit_rational(s.r, s.y, s.lo, s.hi, n, m, starts, 400, RationalModel::value, nullptr, extra_starts);
    } catch (const Error& e) {
      if (e.code() != ExitCode::data) throw;
      why = e.what();
    }
    ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - a).count());
    if (ms.size() == 1) t.fit = f, t.refused = why;
    else if (why != t.refused || f.rss != t.fit.rss)
      throw Error(ExitCode::software, s.name + ": fit_rational is not deterministic");
  } while (ms.size() < 3 || std::chrono::duration<double>(Clock::now() - t0).count() < min_time);
  std::sort(ms.begin(), ms.end());
  const size_t k = ms.size();
  t.median_ms = k % 2 ? ms[k / 2] : 0.5 * (ms[k / 2 - 1] + ms[k / 2]);
  t.reps = k;
  return t;
}

}  // namespace

int main(int argc, char** argv) {
  const std::string share = TURNFIT_SOURCE_SHARE;
  std::string machine = share + "/ring8/machine.json";
  std::string phase = share + "/ring8/measured/phase";
  double min_time = 0.2;
  bool detail = false;
  int extra_starts = 64;  // fit_rational's default
  std::vector<std::string> seeds;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--machine" && i + 1 < argc) machine = argv[++i];
    else if (a == "--phase" && i + 1 < argc) phase = argv[++i];
    else if (a == "--min-time" && i + 1 < argc) min_time = std::atof(argv[++i]);
    else if (a == "--detail") detail = true;
    else if (a == "--extra-starts" && i + 1 < argc) extra_starts = std::atoi(argv[++i]);
    else if (a == "--seed" && i + 1 < argc) seeds.push_back(argv[++i]);
    else {
      std::fprintf(stderr, "usage: bench_tcfit [--machine machine.json] [--phase DIR] [--min-time S] [--detail] "
                           "[--extra-starts K] [--seed \"COIL,N,M,A,B\" ...]\n");
      return 64;
    }
  }
  try {
    std::ifstream in(machine);
    if (!in) throw Error(ExitCode::no_input, machine + ": cannot open");
    const nlohmann::json doc = nlohmann::json::parse(in);
    std::vector<Scan> scans;
    for (const auto& c : doc.at("trimcoils")) {
      Scan s;
      s.name = c.at("name").get<std::string>();
      const CsvTable t = CsvTable::read(phase + "/" + s.name + ".csv");
      const size_t cr = t.column("r_mm"), cy = t.column("dsinphi");
      for (size_t i = 0; i < t.rows(); ++i) {
        s.r.push_back(t.number(i, cr));
        s.y.push_back(t.number(i, cy));
      }
      s.lo = std::max(c.at("rmin_mm").get<double>(), s.r.front());
      s.hi = std::min(c.at("rmax_mm").get<double>(), s.r.back());
      const int k = std::atoi(s.name.c_str() + 2);  // TC<k>
      if (k == 1 || k >= 16) s.n = 4, s.m = 5;
      scans.push_back(std::move(s));
    }
    std::printf("# bench_tcfit: %s, scans %s, min time %.3g s per coil, extra starts %d, median time per fit_rational "
                "call\n", machine.c_str(), phase.c_str(), min_time, extra_starts);
    std::printf("coil,n,m,points,rss,rms,rss_at_pole_bound,time_ms,start%s\n", detail ? ",r_lo,r_hi,iterations,reps,a,b" : "");
    size_t fits = 0, points = 0, refusals = 0;
    double rss = 0, ms = 0, ms_refused = 0;
    auto row = [&](const std::string& name, const Timed& t, const std::string& start, double lo, double hi) {
      const RationalFit& f = t.fit;
      std::printf("%s,%d,%d,%zu,%.17g,%.17g,%.17g,%.6g,%s", name.c_str(), f.n, f.m, f.points, f.rss, f.rms,
                  f.rss_at_pole_bound, t.median_ms, csv_quote(start).c_str());
      if (detail) std::printf(",%.17g,%.17g,%d,%zu,%s,%s", lo, hi, f.iterations, t.reps, join(f.a).c_str(), join(f.b).c_str());
      std::printf("\n");
      ++fits;
      points += f.points;
      rss += f.rss;
      ms += t.median_ms;
    };
    auto refused = [&](const Scan& s, int n, int m, size_t in_window, const Timed& t) {
      std::printf("%s,%d,%d,%zu,nan,nan,nan,%.6g,%s", s.name.c_str(), n, m, in_window, t.median_ms,
                  csv_quote("refused: " + t.refused).c_str());
      if (detail) std::printf(",%.17g,%.17g,,%zu,,", s.lo, s.hi, t.reps);
      std::printf("\n");
      ++refusals;
      ms_refused += t.median_ms;
    };
    auto numbers = [](const std::string& text) {
      std::vector<double> v;
      const char* p = text.c_str();
      char* end = nullptr;
      for (double d = std::strtod(p, &end); end != p; d = std::strtod(p, &end)) v.push_back(d), p = end;
      return v;
    };
    for (const std::string& seed : seeds) {  // seeded fits only
      std::vector<std::string> f;
      for (size_t b = 0, e; b <= seed.size(); b = e + 1) {
        e = seed.find(',', b);
        if (e == std::string::npos) e = seed.size();
        f.push_back(seed.substr(b, e - b));
      }
      const auto it = std::find_if(scans.begin(), scans.end(), [&](const Scan& s) { return !f.empty() && s.name == f[0]; });
      if (f.size() != 5 || it == scans.end()) throw Error(ExitCode::usage, "--seed " + seed + ": want COIL,N,M,A,B of a coil");
      const Scan& s = *it;
      RationalFit start;
      start.n = std::atoi(f[1].c_str());
      start.m = std::atoi(f[2].c_str());
      start.centre = 0.5 * (s.lo + s.hi);
      start.half_width = 0.5 * (s.hi - s.lo);
      start.a = numbers(f[3]);
      start.b = numbers(f[4]);
      if (static_cast<int>(start.a.size()) != start.n + 1 || static_cast<int>(start.b.size()) != start.m + 1)
        throw Error(ExitCode::usage, "--seed " + seed + ": want N + 1 numerator and M + 1 denominator coefficients");
      size_t in_window = 0;
      for (double r : s.r) in_window += r >= s.lo && r <= s.hi;
      const Timed t = time_fit(s, start.n, start.m, min_time, extra_starts, {start});
      if (t.refused.empty()) row(s.name, t, "seeded: " + t.fit.start, s.lo, s.hi);
      else refused(s, start.n, start.m, in_window, t);
    }
    for (const Scan& s : scans) {
      if (!seeds.empty()) break;
      size_t in_window = 0;
      for (double r : s.r) in_window += r >= s.lo && r <= s.hi;
      const Timed t = time_fit(s, s.n, s.m, min_time, extra_starts);
      if (t.refused.empty()) {
        row(s.name, t, t.fit.start, s.lo, s.hi);
        continue;
      }
      refused(s, s.n, s.m, in_window, t);
      if (in_window >= static_cast<size_t>(s.n + 1 + s.m)) continue;  // refused for another reason
      // too few points for the paper's degrees: the 2/4 of the other coils
      const Timed t2 = time_fit(s, 2, 4, min_time, extra_starts);
      if (t2.refused.empty()) row(s.name, t2, "fallback 2/4: " + t2.fit.start, s.lo, s.hi);
      else refused(s, 2, 4, in_window, t2);
    }
    std::printf("total,,,%zu,%.17g,,,%.6g,%zu fits (%zu refusals: %.6g ms more)%s\n", points, rss, ms, fits, refusals,
                ms_refused, detail ? ",,,,,," : "");
  } catch (const Error& e) {
    std::fprintf(stderr, "bench_tcfit: %s\n", e.what());
    return static_cast<int>(e.code());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_tcfit: %s\n", e.what());
    return 65;
  }
  return 0;
}
