// Benchmark: turnfit's rational fits of ring8's 18 trim coil phase scans at the paper's degrees
// (2/4 for TC2-TC15, 4/5 for TC1 and TC16-TC18), each coil's window the machine coil's
// [rmin_mm, rmax_mm] clipped to the data (as turnfit-tc-fit --machine). Times fit_rational per
// coil (repeated until --min-time, median per fit) and prints CSV; bench_tcfit_scipy.py runs it
// and compares SciPy's least_squares on the same points (bench/RESULTS.md).
//
//   bench_tcfit [--machine machine.json] [--phase DIR] [--min-time S] [--detail]
//
// --detail appends r_lo,r_hi,iterations,a,b (coefficients in x = (r - centre)/half_width,
// space separated) for the comparison script. A coil fit_rational refuses (EX_DATAERR) gets a
// row with rss nan and start "refused: <message>"; if it was refused for having fewer points
// than parameters (TC18 at 4/5), a second row fits it at 2/4 (start "fallback 2/4: ...").
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
  double median_ms = 0;
  size_t reps = 0;
};

/// Times fit_rational until min_time seconds have passed (at least 3 runs); median per fit.
Timed time_fit(const Scan& s, int n, int m, double min_time) {
  Timed t;
  std::vector<double> ms;
  const auto t0 = Clock::now();
  do {
    const auto a = Clock::now();
    RationalFit f = fit_rational(s.r, s.y, s.lo, s.hi, n, m);
    ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - a).count());
    if (ms.size() == 1) t.fit = f;
    else if (f.rss != t.fit.rss) throw Error(ExitCode::software, s.name + ": fit_rational is not deterministic");
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
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--machine" && i + 1 < argc) machine = argv[++i];
    else if (a == "--phase" && i + 1 < argc) phase = argv[++i];
    else if (a == "--min-time" && i + 1 < argc) min_time = std::atof(argv[++i]);
    else if (a == "--detail") detail = true;
    else {
      std::fprintf(stderr, "usage: bench_tcfit [--machine machine.json] [--phase DIR] [--min-time S] [--detail]\n");
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
    std::printf("# bench_tcfit: %s, scans %s, min time %.3g s per coil, median time per fit_rational call\n",
                machine.c_str(), phase.c_str(), min_time);
    std::printf("coil,n,m,points,rss,rms,time_ms,start%s\n", detail ? ",r_lo,r_hi,iterations,reps,a,b" : "");
    size_t fits = 0, points = 0;
    double rss = 0, ms = 0;
    auto row = [&](const std::string& name, const Timed& t, const std::string& start, double lo, double hi) {
      const RationalFit& f = t.fit;
      std::printf("%s,%d,%d,%zu,%.17g,%.17g,%.6g,%s", name.c_str(), f.n, f.m, f.points, f.rss, f.rms, t.median_ms,
                  csv_quote(start).c_str());
      if (detail) std::printf(",%.17g,%.17g,%d,%zu,%s,%s", lo, hi, f.iterations, t.reps, join(f.a).c_str(), join(f.b).c_str());
      std::printf("\n");
      ++fits;
      points += f.points;
      rss += f.rss;
      ms += t.median_ms;
    };
    auto refused = [&](const Scan& s, int n, int m, size_t in_window, const Error& e) {
      std::printf("%s,%d,%d,%zu,nan,nan,nan,%s", s.name.c_str(), n, m, in_window,
                  csv_quote(std::string("refused: ") + e.what()).c_str());
      if (detail) std::printf(",%.17g,%.17g,,,,", s.lo, s.hi);
      std::printf("\n");
    };
    for (const Scan& s : scans) {
      size_t in_window = 0;
      for (double r : s.r) in_window += r >= s.lo && r <= s.hi;
      try {
        const Timed t = time_fit(s, s.n, s.m, min_time);
        row(s.name, t, t.fit.start, s.lo, s.hi);
      } catch (const Error& e) {
        if (e.code() != ExitCode::data) throw;
        refused(s, s.n, s.m, in_window, e);
        if (in_window >= static_cast<size_t>(s.n + 1 + s.m)) continue;  // refused for another reason
        try {  // too few points for the paper's degrees: the 2/4 of the other coils
          const Timed t = time_fit(s, 2, 4, min_time);
          row(s.name, t, "fallback 2/4: " + t.fit.start, s.lo, s.hi);
        } catch (const Error& e2) {
          if (e2.code() != ExitCode::data) throw;
          refused(s, 2, 4, in_window, e2);
        }
      }
    }
    std::printf("total,,,%zu,%.17g,,%.6g,%zu fits%s\n", points, rss, ms, fits, detail ? ",,,,,," : "");
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_tcfit: %s\n", e.what());
    return 65;
  }
  return 0;
}
