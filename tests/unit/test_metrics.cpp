// Unit tests of lib/turnfit/metrics: norms against independent calculations, the paper's
// objective grouping, matching with missing and extra turns, input errors, the report writers.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <limits>
#include <numeric>
#include <random>
#include <sstream>

#include "../support.hpp"
#include "turnfit/io/csv.hpp"
#include "turnfit/metrics/compare_app.hpp"
#include "turnfit/metrics/metrics.hpp"

using namespace turnfit;

namespace {

const double kNaN = std::numeric_limits<double>::quiet_NaN();

/// A table built in memory: (probe, turn, r) triples in any order.
TurnTable table(const std::vector<std::tuple<std::string, int, double>>& rows, const std::string& source = "mem") {
  TurnTable t;
  t.source = source;
  long line = 1;
  for (const auto& [probe, turn, r] : rows) {
    int p = t.probe_index(probe);
    if (p < 0) {
      p = static_cast<int>(t.probes.size());
      t.probes.push_back(probe);
    }
    TurnPoint pt;
    pt.probe = p;
    pt.turn = turn;
    pt.r_mm = r;
    pt.line = ++line;
    t.points.push_back(pt);
  }
  finish_turn_table(t);
  return t;
}

/// The paper's PSI Ring measurement layout: RRI2 turns 1-16, RRL turns 9-182 (190 turns).
std::vector<std::tuple<std::string, int, double>> paper_layout(std::mt19937_64& rng) {
  std::uniform_real_distribution<double> jitter(-3, 3);
  std::vector<std::tuple<std::string, int, double>> rows;
  for (int t = 1; t <= 16; ++t) rows.emplace_back("RRI2", t, 2090 + 22.5 * t + jitter(rng));
  for (int t = 9; t <= 182; ++t) rows.emplace_back("RRL", t, 2300 + 12.0 * t + jitter(rng));
  return rows;
}

/// Objectives evaluated through the optimizer's path.
std::vector<ObjectiveValue> evaluate(const std::vector<Objective>& objs, const TurnTable& meas, const TurnTable& sim) {
  const ObjectivePlan plan = plan_objectives(objs, meas);
  std::vector<double> delta;
  std::vector<unsigned char> matched;
  match_turns(meas, sim, delta, matched);
  std::vector<ObjectiveValue> out(objs.size());
  evaluate_objectives(plan, delta.data(), matched.data(), out.data());
  return out;
}

}  // namespace

TEST_CASE("error_stats agrees with an independent sort-based calculation on random data", "[metrics]") {
  std::mt19937_64 rng(20240611);
  for (int trial = 0; trial < 200; ++trial) {
    const size_t n = 1 + rng() % 300;
    std::normal_distribution<double> g(rng() % 2 ? 0.0 : 1.5, 0.1 + (rng() % 50) * 0.1);
    std::vector<double> d(n);
    for (auto& x : d) x = g(rng);

    // Independent: sort |d| descending (not a running maximum), long-double sums.
    std::vector<double> a(n);
    std::transform(d.begin(), d.end(), a.begin(), [](double x) { return std::fabs(x); });
    std::vector<double> sorted = a;
    std::sort(sorted.begin(), sorted.end(), std::greater<double>());
    long double sum_abs = 0, sum_sq = 0;
    for (double x : d) {
      sum_abs += std::fabs(static_cast<long double>(x));
      sum_sq += static_cast<long double>(x) * x;
    }
    const double mae = static_cast<double>(sum_abs / n), mse = static_cast<double>(sum_sq / n);

    const ErrorStats s = error_stats(d.data(), n);
    REQUIRE(s.n == n);
    CHECK(s.linf_mm == sorted[0]);
    CHECK(s.mae_mm == Approx(mae).epsilon(1e-12));
    CHECK(s.mse_mm2 == Approx(mse).epsilon(1e-12));
    CHECK(s.rms_mm == Approx(std::sqrt(mse)).epsilon(1e-12));
    // The paper's l2: (1/N) sqrt(sum dr^2); rms is sqrt(N) times larger.
    CHECK(s.l2_mm == Approx(std::sqrt(static_cast<double>(sum_sq)) / static_cast<double>(n)).epsilon(1e-12));
    CHECK(s.rms_mm == Approx(s.l2_mm * std::sqrt(static_cast<double>(n))).epsilon(1e-12));
    for (size_t k = 0; k < 3; ++k) {
      if (k < n) {
        CHECK(s.largest_mm[k] == sorted[k]);
        REQUIRE(s.largest_index[k] < n);
        CHECK(a[s.largest_index[k]] == sorted[k]);
      } else {
        CHECK(std::isnan(s.largest_mm[k]));
        CHECK(s.largest_index[k] == SIZE_MAX);
      }
    }
  }
}

TEST_CASE("largest errors: ties keep the first, signs do not matter, indices are distinct", "[metrics]") {
  const std::vector<double> d = {0.5, -2.0, 2.0, 1.0, -2.0, 0.1};
  const ErrorStats s = error_stats(d.data(), d.size());
  CHECK(s.largest_mm == std::array<double, 3>{2.0, 2.0, 2.0});
  CHECK(s.largest_index == std::array<size_t, 3>{1, 2, 4});
  const std::vector<double> e = {1, 3, 2, 5, 4};
  const ErrorStats t = error_stats(e.data(), e.size());
  CHECK(t.largest_mm == std::array<double, 3>{5, 4, 3});
  CHECK(t.largest_index == std::array<size_t, 3>{3, 4, 1});
}

TEST_CASE("no residual and NaN residuals give NaN, never a good-looking number", "[metrics]") {
  const ErrorStats none = error_stats(nullptr, 0);
  CHECK(none.n == 0);
  CHECK(std::isnan(none.linf_mm));
  CHECK(std::isnan(none.l2_mm));
  CHECK(std::isnan(none.mae_mm));
  // NaN anywhere, including after the largest value (a running max would skip it).
  for (size_t at : {0u, 2u, 4u}) {
    std::vector<double> d = {1, 5, 2, 3, 0.5};
    d[at] = kNaN;
    const ErrorStats s = error_stats(d.data(), d.size());
    CHECK(s.n == 5);
    CHECK(std::isnan(s.linf_mm));
    CHECK(std::isnan(s.mae_mm));
    CHECK(std::isnan(s.mse_mm2));
    CHECK(std::isnan(s.rms_mm));
    CHECK(std::isnan(s.l2_mm));
    CHECK(std::isnan(s.largest_mm[1]));
  }
  // In an objective too.
  TurnTable meas = table({{"P", 1, 10}, {"P", 2, 20}, {"P", 3, 30}});
  TurnTable sim = table({{"P", 1, 10.5}, {"P", 2, kNaN}, {"P", 3, 30}});
  auto v = evaluate(parse_objectives_spec("P:linf,P:l2,P:wl2,P:max3"), meas, sim);
  for (const auto& x : v) CHECK(std::isnan(x.value));
}

TEST_CASE("the paper's six objectives (Table II grouping) against the paper's equations", "[metrics][paper]") {
  std::mt19937_64 rng(7);
  const auto rows = paper_layout(rng);
  TurnTable meas = table(rows);
  std::normal_distribution<double> g(0.3, 2.0);
  std::vector<std::tuple<std::string, int, double>> sim_rows;
  for (const auto& [p, t, r] : rows) sim_rows.emplace_back(p, t, r + g(rng));
  // Shuffled: matching must not depend on file order.
  std::shuffle(sim_rows.begin(), sim_rows.end(), rng);
  TurnTable sim = table(sim_rows);

  const char* spec = "RRI2:1-16:linf,RRL:9-31:linf,RRL:32-61:linf,RRL:62-105:linf,RRL:106-148:linf,RRL:149-182:linf";
  const auto objs = parse_objectives_spec(spec);
  REQUIRE(objs.size() == 6);
  const int bounds[6][2] = {{1, 16}, {9, 31}, {32, 61}, {62, 105}, {106, 148}, {149, 182}};

  // Independent: look up each turn's radii by search over the unsorted rows.
  auto radius = [](const std::vector<std::tuple<std::string, int, double>>& rs, const std::string& probe, int turn) {
    for (const auto& [p, t, r] : rs)
      if (p == probe && t == turn) return r;
    FAIL("turn not found");
    return 0.0;
  };
  std::vector<Objective> l2objs = objs;
  for (auto& o : l2objs) o.norm = Norm::l2;
  const auto linf = evaluate(objs, meas, sim);
  const auto l2 = evaluate(l2objs, meas, sim);
  const ObjectivePlan plan = plan_objectives(objs, meas);
  for (int k = 0; k < 6; ++k) {
    const std::string probe = k == 0 ? "RRI2" : "RRL";
    const int l = bounds[k][0], u = bounds[k][1];
    double mx = 0, sum = 0;
    for (int i = l; i <= u; ++i) {
      const double d = radius(rows, probe, i) - radius(sim_rows, probe, i);  // r^m - r^s, as printed
      mx = std::max(mx, std::fabs(d));
      sum += d * d;
    }
    const double N = u - l + 1;  // the paper: N = u - l + 1
    CHECK(plan.items[k].measured == static_cast<size_t>(N));
    CHECK(linf[k].value == Approx(mx).epsilon(1e-14));
    CHECK(l2[k].value == Approx(std::sqrt(sum) / N).epsilon(1e-12));
    CHECK(linf[k].n == static_cast<size_t>(N));
    CHECK(linf[k].missing == 0);
    CHECK(objs[k].name == probe + ":" + std::to_string(l) + "-" + std::to_string(u) + ":linf");
  }
  // The overall figures pool all 190 turns (the paper's Tables III-IV divide by 190).
  const auto all = evaluate(parse_objectives_spec("*:mae,*:mse,*:linf"), meas, sim);
  CHECK(all[0].n == 190);
  const Comparison cmp = compare_turns(meas, sim);
  std::vector<double> d;
  for (const auto& r : cmp.residuals) d.push_back(r.delta_mm);
  const ErrorStats s = error_stats(d.data(), d.size());
  CHECK(all[0].value == Approx(s.mae_mm).epsilon(1e-14));
  CHECK(all[1].value == Approx(s.mse_mm2).epsilon(1e-14));
  CHECK(all[2].value == s.linf_mm);
}

TEST_CASE("local search norms: weighted l2 with probes weighing equally, 2nd and 3rd largest", "[metrics][paper]") {
  std::mt19937_64 rng(11);
  const auto rows = paper_layout(rng);
  TurnTable meas = table(rows);
  std::vector<std::tuple<std::string, int, double>> sim_rows;
  // RRI2 errors ten times the RRL ones: pooling would drown RRI2's 16 turns in RRL's 174.
  std::normal_distribution<double> g(0, 1);
  for (const auto& [p, t, r] : rows) sim_rows.emplace_back(p, t, r + (p == "RRI2" ? 10.0 : 1.0) * g(rng));
  TurnTable sim = table(sim_rows);

  double ss[2] = {0, 0};
  int nn[2] = {0, 0};
  std::vector<double> abs_all;
  for (size_t i = 0; i < rows.size(); ++i) {
    const int k = std::get<0>(rows[i]) == "RRI2" ? 0 : 1;
    // rows and sim_rows are in the same order here (not shuffled).
    const double d = std::get<2>(sim_rows[i]) - std::get<2>(rows[i]);
    ss[k] += d * d;
    ++nn[k];
    abs_all.push_back(std::fabs(d));
  }
  const double wl2 = std::sqrt(0.5 * (ss[0] / nn[0] + ss[1] / nn[1]));
  const double pooled_rms = std::sqrt((ss[0] + ss[1]) / (nn[0] + nn[1]));
  std::sort(abs_all.begin(), abs_all.end(), std::greater<double>());

  const auto v = evaluate(parse_objectives_spec("RRI2:1-16+RRL:9-182:wl2,*:wl2,*:rms,*:max2,*:max3,*:linf"), meas, sim);
  CHECK(v[0].value == Approx(wl2).epsilon(1e-12));
  CHECK(v[1].value == Approx(wl2).epsilon(1e-12));  // '*' is one part per probe
  CHECK(v[0].n == 190);
  CHECK(v[2].value == Approx(pooled_rms).epsilon(1e-12));
  CHECK(std::fabs(v[0].value - v[2].value) > 1.0);  // the weighting matters here
  CHECK(v[3].value == abs_all[1]);
  CHECK(v[4].value == abs_all[2]);
  CHECK(v[5].value == abs_all[0]);
}

TEST_CASE("missing and extra turns are counted and listed, simulated-only probes are not", "[metrics]") {
  TurnTable meas = table({{"RRL", 9, 100}, {"RRL", 10, 110}, {"RRL", 11, 120}, {"RRL", 12, 130}, {"RRI2", 1, 50},
                          {"RRI2", 2, 60}, {"RRX", 5, 1}});
  // RRL 11 and 12 not simulated, RRI2 3 extra, RRX not simulated at all, X0 not measured.
  TurnTable sim = table({{"X0", 1, 7}, {"RRI2", 3, 70}, {"RRI2", 2, 61}, {"RRI2", 1, 49.5}, {"RRL", 9, 101},
                         {"RRL", 10, 108}, {"RRL", 8, 90}});
  const Comparison c = compare_turns(meas, sim);
  REQUIRE(c.probes == std::vector<std::string>{"RRL", "RRI2", "RRX"});
  CHECK(c.simulated_only == std::vector<std::string>{"X0"});
  CHECK(c.counts[0].measured == 4);
  CHECK(c.counts[0].simulated == 3);
  CHECK(c.counts[0].matched == 2);
  CHECK(c.counts[0].missing == std::vector<int>{11, 12});
  CHECK(c.counts[0].extra == std::vector<int>{8});
  CHECK(c.counts[1].missing.empty());
  CHECK(c.counts[1].extra == std::vector<int>{3});
  CHECK(c.counts[2].missing == std::vector<int>{5});
  CHECK(c.violation() == 5);
  REQUIRE(c.residuals.size() == 4);
  CHECK(c.residuals[0].turn == 9);
  CHECK(c.residuals[0].delta_mm == 1.0);  // sim - meas
  CHECK(c.residuals[1].delta_mm == -2.0);
  CHECK(c.residuals[2].delta_mm == -0.5);

  std::vector<double> delta;
  std::vector<unsigned char> matched;
  CHECK(match_turns(meas, sim, delta, matched) == 5);
  CHECK(std::count(matched.begin(), matched.end(), 1) == 4);

  const auto v = evaluate(parse_objectives_spec("RRL:9-12:linf,RRL:11-12:l2,RRX:mae"), meas, sim);
  CHECK(v[0].value == 2.0);
  CHECK(v[0].n == 2);
  CHECK(v[0].missing == 2);
  CHECK(std::isnan(v[1].value));  // nothing matched: no value, not zero
  CHECK(v[1].missing == 2);
  CHECK(v[2].missing == 1);

  const CompareReport r = make_compare_report(meas, sim, {}, 100.0);
  CHECK_FALSE(r.agrees());  // within tolerance, but the turn counts differ
  const CompareReport ok = make_compare_report(meas, meas, {}, 0.0);
  CHECK(ok.agrees());
}

TEST_CASE("match_turns equals compare_turns on random tables with gaps", "[metrics]") {
  std::mt19937_64 rng(3);
  for (int trial = 0; trial < 50; ++trial) {
    std::vector<std::tuple<std::string, int, double>> m, s;
    for (int t = 1; t <= 60; ++t) {
      const std::string p = t % 3 ? "A" : "B";
      if (rng() % 5) m.emplace_back(p, t, t * 10.0);
      if (rng() % 5) s.emplace_back(p, t, t * 10.0 + static_cast<double>(rng() % 100) / 10);
    }
    if (m.empty()) continue;
    std::shuffle(s.begin(), s.end(), rng);
    TurnTable meas = table(m), sim = table(s);
    const Comparison c = compare_turns(meas, sim);
    std::vector<double> delta;
    std::vector<unsigned char> matched;
    CHECK(match_turns(meas, sim, delta, matched) == c.violation());
    size_t k = 0;
    for (size_t i = 0; i < meas.points.size(); ++i) {
      if (!matched[i]) continue;
      REQUIRE(k < c.residuals.size());
      CHECK(c.residuals[k].meas_index == i);
      CHECK(c.residuals[k].delta_mm == delta[i]);
      ++k;
    }
    CHECK(k == c.residuals.size());
  }
}

TEST_CASE("CSV input: peaks and turns formats, duplicates and bad cells name file and line", "[metrics][io]") {
  const std::string peaks =
      "probe,turn,r_mm,height,area,width_mm,flag\n"
      "RRL,10,2410.5,1,2,3,merged\n"
      "RRL,9,2400.25,1,2,3,\n";
  TurnTable p = turn_table_from_csv(CsvTable::parse(peaks, "peaks.csv"));
  CHECK(p.format == "peaks");
  REQUIRE(p.points.size() == 2);
  CHECK(p.points[0].turn == 9);  // sorted
  CHECK(p.points[1].flag == "merged");

  const std::string turns =
      "# turnfit-track 0.1.0\n"
      "probe,turn,r_mm,s_mm,t_ns,energy_MeV,phase_deg\n"
      "RRI2,1,2094.875516,2094.875516,19.666073,72.45350688,-1.40883\n"
      "RRI2,2,2117.259326,2117.259326,138.063326,74.19725038,\n"
      "# end particle=0 turns=182.0000 energy_MeV=590.000001 r_mm=4432.2441 t_ns=21556.602 status=turn limit\n";
  TurnTable t = turn_table_from_csv(CsvTable::parse(turns, "turns.csv"));
  CHECK(t.format == "turns");
  CHECK(t.points.size() == 2);
  CHECK(t.points[1].r_mm == 2117.259326);

  std::string msg;
  const std::string dup = "probe,turn,r_mm\nA,1,1\nA,2,2\nB,1,3\nA,1,4\n";
  CHECK(test::error_code([&] { turn_table_from_csv(CsvTable::parse(dup, "dup.csv")); }, &msg) == 65);
  CHECK(msg == "dup.csv:5: probe A turn 1 appears twice (first at line 2)");

  CHECK(test::error_code([&] { turn_table_from_csv(CsvTable::parse("probe,turn,r_mm\nA,1,nan\n", "n.csv")); },
                         &msg) == 65);
  CHECK(msg.find("n.csv:2") == 0);
  CHECK(test::error_code([&] { turn_table_from_csv(CsvTable::parse("probe,turn,r_mm\nA,1.5,3\n", "f.csv")); },
                         &msg) == 65);
  CHECK(msg.find("f.csv:2") == 0);
  CHECK(test::error_code([&] { turn_table_from_csv(CsvTable::parse("probe,turn,r_mm\nA,-1,3\n", "g.csv")); },
                         &msg) == 65);
  CHECK(test::error_code([&] { turn_table_from_csv(CsvTable::parse("probe,turn,radius\nA,1,3\n", "h.csv")); },
                         &msg) == 65);
  CHECK(msg.find("'r_mm'") != std::string::npos);
}

TEST_CASE("objective specs: the paper's grouping, names, round trip and usage errors", "[metrics]") {
  const auto o = parse_objectives_spec(" s1=RRI2:1-16:linf , RRL:9-31:l2,RRL:max2,RRI2:3:mae,*:1-20+RRL:9-182:wl2");
  REQUIRE(o.size() == 5);
  CHECK(o[0].name == "s1");
  CHECK(o[0].parts[0].probe == "RRI2");
  CHECK(o[0].parts[0].first_turn == 1);
  CHECK(o[0].parts[0].last_turn == 16);
  CHECK(o[1].norm == Norm::l2);
  CHECK(o[2].parts[0].first_turn == INT_MIN);
  CHECK(o[3].parts[0].first_turn == 3);
  CHECK(o[3].parts[0].last_turn == 3);
  CHECK(o[4].parts.size() == 2);
  CHECK(objective_spec(o[4]) == "*:1-20+RRL:9-182:wl2");
  for (const auto& x : o) {
    const auto again = parse_objectives_spec(objective_spec(x));
    CHECK(objective_spec(again[0]) == objective_spec(x));
  }
  std::string msg;
  for (const char* bad : {"", "RRL:9-31", "RRL:9-31:l3", "RRL:31-9:linf", "RRL:a-b:linf", "RRL:9-31:linf,,RRI2:linf",
                          ":linf", "=RRL:linf", "RRL:-5:linf"}) {
    CAPTURE(bad);
    CHECK(test::error_code([&] { parse_objectives_spec(bad); }, &msg) == 64);
  }
  CHECK(test::error_code([&] { parse_objectives_spec("RRL:9-31:l3"); }, &msg) == 64);
  CHECK(msg.find("unknown norm 'l3'") != std::string::npos);
  CHECK(msg.find("linf, l2, rms, mae, mse, wl2, max2, max3") != std::string::npos);
}

TEST_CASE("objectives from JSON: problem file and array shapes, strict keys", "[metrics]") {
  const auto doc = nlohmann::json::parse(R"({
    "machine": "ring8",
    "objectives": [
      {"probe": "RRI2", "turns": [1, 16], "norm": "linf"},
      {"name": "rrl_late", "probe": "RRL", "turns": 149, "norm": "l2"},
      {"name": "local", "norm": "wl2", "parts": [{"probe": "RRI2", "turns": [1, 16]}, {"probe": "RRL"}]},
      "RRL:9-31:max3"
    ]})");
  const auto o = objectives_from_document(doc, "problem.json");
  REQUIRE(o.size() == 4);
  CHECK(o[0].name == "RRI2:1-16:linf");
  CHECK(o[1].parts[0].first_turn == 149);
  CHECK(o[1].parts[0].last_turn == 149);
  CHECK(o[2].parts.size() == 2);
  CHECK(o[2].parts[1].last_turn == INT_MAX);
  CHECK(o[3].norm == Norm::max3);
  // Written back, the JSON reads the same.
  nlohmann::json back = nlohmann::json::array();
  for (const auto& x : o) back.push_back(objective_to_json(x));
  const auto o2 = objectives_from_document(back, "back");
  for (size_t k = 0; k < o.size(); ++k) {
    CHECK(o2[k].name == o[k].name);
    CHECK(objective_spec(o2[k]) == objective_spec(o[k]));
  }
  std::string msg;
  auto code = [&](const char* text) {
    return test::error_code([&] { objectives_from_document(nlohmann::json::parse(text), "p.json"); }, &msg);
  };
  CHECK(code(R"({"objectives": [{"probe": "RRL", "turns": [9, 31], "norm": "linf", "weight": 2}]})") == 65);
  CHECK(msg == "p.json: objectives[0]: unknown key \"weight\" (known: name, probe, turns, parts, norm)");
  CHECK(code(R"({"objectives": [{"probe": "RRL", "turns": [9, 31]}]})") == 65);
  CHECK(msg.find("\"norm\" is missing") != std::string::npos);
  CHECK(code(R"({"objectives": [{"probe": "RRL", "turns": [31, 9], "norm": "linf"}]})") == 65);
  CHECK(code(R"({"objectives": [{"probe": "RRL", "turns": [9.5, 31], "norm": "linf"}]})") == 65);
  CHECK(code(R"({"objectives": [{"probe": "RRL", "norm": "linf", "parts": [{"probe": "RRL"}]}]})") == 65);
  CHECK(code(R"({"objectives": [{"norm": "wl2", "parts": [{"probe": "RRL", "norm": "linf"}]}]})") == 65);
  CHECK(msg.find("objectives[0].parts[0]") != std::string::npos);
  CHECK(code(R"({"objectives": []})") == 65);
  CHECK(code(R"({"machine": "x"})") == 65);
  CHECK(code(R"({"objectives": ["RRL:9-31:lone"]})") == 65);
  CHECK(code(R"(["RRL:9-31:linf"])") == 0);
}

TEST_CASE("planning objectives against the measurement: unknown probes and empty ranges", "[metrics]") {
  TurnTable meas = table({{"RRI2", 1, 1}, {"RRI2", 2, 2}, {"RRL", 9, 3}, {"RRL", 10, 4}}, "peaks.csv");
  std::string msg;
  CHECK(test::error_code([&] { plan_objectives(parse_objectives_spec("RRI1:1-16:linf"), meas); }, &msg) == 65);
  CHECK(msg.find("probe RRI1 is not in the measured data (probes: RRI2, RRL); did you mean RRI2?") !=
        std::string::npos);
  CHECK(test::error_code([&] { plan_objectives(parse_objectives_spec("RRL:1-8:linf"), meas); }, &msg) == 65);
  CHECK(msg.find("RRL:1-8 covers no measured turn") != std::string::npos);
  const ObjectivePlan plan = plan_objectives(parse_objectives_spec("*:2-9:linf,RRL:linf"), meas);
  CHECK(plan.items[0].measured == 2);  // RRI2 2 and RRL 9
  CHECK(plan.items[0].parts.size() == 2);
  CHECK(plan.items[1].measured == 2);
}

TEST_CASE("report writers: JSON keys, text table, residuals", "[metrics][app]") {
  TurnTable meas = table({{"RRI2", 1, 2000}, {"RRI2", 2, 2020}, {"RRL", 9, 2400}, {"RRL", 10, 2410}}, "m.csv");
  TurnTable sim = table({{"RRI2", 1, 2000.5}, {"RRI2", 2, 2019}, {"RRL", 9, 2400.25}, {"RRL", 11, 2420}}, "s.csv");
  const CompareReport r = make_compare_report(meas, sim, parse_objectives_spec("RRI2:linf,RRL:9-10:l2"), 2.0);
  std::ostringstream js;
  write_errors_json(js, r, false);
  const auto j = nlohmann::json::parse(js.str());
  CHECK(j["column"] == "r_mm");
  CHECK(j["overall"]["n"] == 3);
  CHECK(j["overall"]["linf_mm"] == 1.0);
  CHECK(j["overall"]["largest"][0]["probe"] == "RRI2");
  CHECK(j["overall"]["largest"][0]["turn"] == 2);
  CHECK(j["overall"]["largest"][0]["delta_mm"] == -1.0);
  CHECK(j["probes"]["RRL"]["turn_count"]["missing_turns"] == std::vector<int>{10});
  CHECK(j["probes"]["RRL"]["turn_count"]["extra_turns"] == std::vector<int>{11});
  CHECK(j["probes"]["RRL"]["n"] == 1);
  CHECK(j["probes"]["RRL"]["largest"].size() == 1);
  CHECK(j["turn_counts_agree"] == false);
  CHECK(j["within_tol"] == true);
  CHECK(j["agree"] == false);
  CHECK(j["objectives"][1]["value"] == 0.25);  // sqrt(0.25^2)/1, exact: 2400.25 - 2400 and its square are binary-exact, and the JSON writer round-trips doubles
  CHECK(j["objectives"][1]["missing"] == 1);
  CHECK_FALSE(j.contains("provenance"));

  std::ostringstream txt;
  write_errors_text(txt, r);
  const std::string t = txt.str();
  CHECK(t.find("     2      2020.000      2019.000      -1.000  <- largest") != std::string::npos);
  CHECK(t.find("    10      2410.000             -           -  missing: not simulated") != std::string::npos);
  CHECK(t.find("    11             -      2420.000           -  extra: not measured") != std::string::npos);
  CHECK(t.find("result: max |dr| 1.000 mm, tolerance 2 mm: DIFFER") != std::string::npos);

  std::ostringstream csv;
  write_residuals_csv(csv, r, false);
  const CsvTable back = CsvTable::parse(csv.str(), "res");
  CHECK(back.header() == std::vector<std::string>{"probe", "turn", "r_meas_mm", "r_sim_mm", "delta_mm"});
  REQUIRE(back.rows() == 3);
  CHECK(back.number(1, 4) == -1.0);
  CHECK(csv.str().find("# missing probe=RRL turns=10 (not simulated)") != std::string::npos);
}
