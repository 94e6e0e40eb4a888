// turnfit-nsga in-process: the population log, resume, problem files and the command evaluator.
#include <unistd.h>

#include <catch2/catch.hpp>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "../support.hpp"
#include "turnfit/optimize/mpi.hpp"
#include "turnfit/optimize/nsga_app.hpp"

using namespace turnfit;

namespace {

using test::TempDir;

std::string slurp(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

/// ZDT1 in Python, answering with repr() floats (exact round trip).
const char* kZdt1Py = R"(import json, math, sys
x = json.load(sys.stdin)["x"]
n = len(x)
g = 1 + 9 * sum(x[1:]) / (n - 1)
f1 = x[0]
f2 = g * (1 - math.sqrt(f1 / g))
print(json.dumps({"f": [f1, f2]}))
)";

}  // namespace

TEST_CASE("population log: records round-trip exactly, a torn last record is dropped", "[nsga][app]") {
  Individual a;
  a.id = 7;
  a.generation = 1;
  a.x = {0.1, 1.0 / 3.0};
  a.f = {std::nextafter(1.0, 2.0), -2.5e-300};
  a.g = {-1};
  a.violation = 0;
  Individual b = a;
  b.id = 8;
  b.ok = false;
  b.reason = "evaluator exit 3";
  b.f = {NAN, NAN};
  b.violation = INFINITY;
  const std::vector<std::string> names = {"p", "q"};
  const std::string run = R"({"record":"run","problem":"T"})";
  const std::string text = run + "\n" + eval_record(a, names) + "\n" + eval_record(b, names) + "\n";
  PopulationLog log = parse_population_log(text, "log", names);
  REQUIRE(log.evaluated.size() == 2);
  CHECK_FALSE(log.torn_tail);
  CHECK(log.valid_bytes == text.size());
  CHECK(log.evaluated[0].x == a.x);  // bit for bit: resume checks x by equality
  CHECK(log.evaluated[0].f == a.f);
  CHECK(log.evaluated[1].ok == false);
  CHECK(log.evaluated[1].reason == "evaluator exit 3");
  CHECK(std::isinf(log.evaluated[1].violation));
  CHECK(std::isnan(log.evaluated[1].f[0]));

  // A killed run: the last record cut anywhere.
  const std::string torn = text.substr(0, text.size() - 17);
  log = parse_population_log(torn, "log", names);
  CHECK(log.torn_tail);
  CHECK(log.evaluated.size() == 1);
  CHECK(log.valid_bytes == run.size() + 1 + eval_record(a, names).size() + 1);
  // A bad record before the last one is an error that names the line.
  std::string msg;
  CHECK(test::error_code([&] { parse_population_log("{\"record\":\"run\"}\nnot json\n" + eval_record(a, names) + "\n",
                                                    "pop.jsonl", names); },
                         &msg) == 65);
  CHECK(msg.find("pop.jsonl:2") != std::string::npos);
  CHECK(test::error_code([&] { parse_population_log(run + "\n" + run + "\n", "pop.jsonl", names); }) == 65);
  // x keyed by other names than the problem's.
  CHECK(test::error_code([&] { parse_population_log(eval_record(a, {"p", "r"}) + "\n", "pop.jsonl", names); }) == 65);
}

TEST_CASE("command answers: arrays, objects by name, errors and malformed answers", "[nsga][app]") {
  const std::vector<std::string> fn = {"f1", "f2"}, gn = {"c"};
  Evaluation e = parse_command_answer("progress...\n{\"f\": [1, 2], \"g\": [-0.5]}\n", fn, gn);
  CHECK(e.ok);
  CHECK(e.f == std::vector<double>{1, 2});
  e = parse_command_answer(R"({"f": {"f2": 4, "f1": 3}, "g": {"c": 1}})", fn, gn);
  CHECK(e.ok);
  CHECK(e.f == std::vector<double>{3, 4});
  CHECK(e.g == std::vector<double>{1});
  e = parse_command_answer(R"({"error": "particle lost at turn 12"})", fn, gn);
  CHECK_FALSE(e.ok);
  CHECK(e.reason.find("particle lost") != std::string::npos);
  CHECK_FALSE(parse_command_answer(R"({"f": [1], "g": [0]})", fn, gn).ok);
  CHECK_FALSE(parse_command_answer(R"({"f": [1, 2]})", fn, gn).ok);          // g missing
  CHECK_FALSE(parse_command_answer(R"({"f": {"f1": 1, "f3": 2}, "g": [0]})", fn, gn).ok);
  CHECK_FALSE(parse_command_answer("", fn, gn).ok);
  CHECK_FALSE(parse_command_answer("Traceback ...", fn, gn).ok);
}

TEST_CASE("an external evaluator of ZDT1 gives the built-in's run bit for bit, failures are recorded",
          "[nsga][app]") {
  // python3 is a build dependency (CMake's find_package(Python3), Makefile.wrap's DEBS): no skip.
  REQUIRE(::access("/usr/bin/python3", X_OK) == 0);
  TempDir tmp;
  tmp.file("zdt1.py", kZdt1Py);
  LoadedProblem builtin = load_problem("zdt1", "", -1, 6);
  LoadedProblem command = load_problem("zdt1", "/usr/bin/python3 " + tmp.path + "/zdt1.py", 30, 6);
  Nsga2Settings s;
  s.population = 8;
  s.generations = 3;
  s.seed = 11;
  const Nsga2Result a = run_nsga2(*builtin.problem, s, 1);
  const Nsga2Result b = run_nsga2(*command.problem, s, 2);
  REQUIRE(a.population.size() == b.population.size());
  for (size_t i = 0; i < a.population.size(); ++i) {
    CHECK(a.population[i].id == b.population[i].id);
    CHECK(a.population[i].f == b.population[i].f);
  }
  // A command that fails for some designs: the run goes on, the reasons are kept.
  tmp.file("flaky.py", std::string(kZdt1Py) + "if x[0] > 0.5: sys.exit(3)\n");
  const std::string flaky_py = tmp.path + "/flaky.py";
  LoadedProblem flaky = load_problem("zdt1", "/usr/bin/python3 " + flaky_py + " && true", 30, 6);
  size_t failed = 0;
  Nsga2Callbacks cb;
  cb.on_evaluated = [&](const Individual& ind) {
    if (!ind.ok) {
      ++failed;
      CHECK(ind.reason.find("exit 3") != std::string::npos);
    }
  };
  run_nsga2(*flaky.problem, s, 2, cb);
  CHECK(failed > 0);
}

TEST_CASE("problem files: strict keys with file and key in the message, the command runs beside the file",
          "[nsga][app]") {
  TempDir tmp;
  auto code = [&](const std::string& text, std::string* msg = nullptr) {
    const std::string p = tmp.file("p.json", text);
    return test::error_code([&] { load_problem(p, "", -1); }, msg);
  };
  const std::string vars = R"("variables": [{"name": "a", "lower": 0, "upper": 1}])";
  std::string msg;
  CHECK(code(R"({"format": "turnfit-problem/1", )" + vars + R"(, "objectives": 2, "evaluatr": {}})", &msg) == 65);
  CHECK(msg.find("p.json") != std::string::npos);
  CHECK(msg.find("evaluatr") != std::string::npos);
  CHECK(code(R"({"format": "turnfit-problem/1", "variables": [{"name": "a", "lower": 1, "upper": 1}],
                 "objectives": 2, "evaluator": {"command": "true"}})",
             &msg) == 65);
  CHECK(msg.find("variables/0") != std::string::npos);
  CHECK(code(R"({)" + vars + R"(, "objectives": 2, "evaluator": {"command": "true"}})") == 65);  // no format
  CHECK(code(R"({"format": "turnfit-problem/1", )" + vars + R"(, "objectives": 2})") == 64);  // no evaluator
  // A machine makes it a turn-pattern problem (test_turn_problem.cpp): a missing machine is 66,
  // and its keys without a machine are refused with the reason.
  CHECK(code(R"({"format": "turnfit-problem/1", )" + vars + R"(, "objectives": 2, "machine": "m.json"})", &msg) == 66);
  CHECK(msg.find("m.json") != std::string::npos);
  CHECK(code(R"({"format": "turnfit-problem/1", )" + vars + R"(, "objectives": 2, "peaks": "p.csv"})", &msg) == 65);
  CHECK(msg.find("turn-pattern") != std::string::npos);
  CHECK(test::error_code([&] { load_problem(tmp.path + "/none.json", "", -1); }) == 66);
  CHECK(test::error_code([&] { load_problem("zdt9", "", -1); }) == 64);

  // A relative command is found beside the file whatever the current folder.
  std::filesystem::create_directories(tmp.path + "/sub");
  tmp.file("sub/eval.sh", "#!/bin/sh\ncat > /dev/null\necho '{\"f\": [1, 2], \"g\": {\"c\": -1}}'\n");
  std::filesystem::permissions(tmp.path + "/sub/eval.sh", std::filesystem::perms::owner_all);
  const std::string p = tmp.file("sub/problem.json", R"({"format": "turnfit-problem/1", "name": "demo", )" + vars +
                                                         R"(, "objectives": ["cost", "loss"], "constraints": ["c"],
                                                         "evaluator": {"command": "./eval.sh", "timeout_s": 10}})");
  LoadedProblem lp = load_problem(p, "", -1);
  CHECK(lp.problem->name() == "demo");
  CHECK(lp.objective_names == std::vector<std::string>{"cost", "loss"});
  const Evaluation e = lp.problem->evaluate({0.5});
  CHECK(e.ok);
  CHECK(e.g == std::vector<double>{-1});
}

TEST_CASE("run_nsga: a log cut anywhere resumes to the uninterrupted run's front and log", "[nsga][app]") {
  TempDir tmp;
  NsgaOptions o;
  o.problem = "tnk";
  o.settings.population = 12;
  o.settings.generations = 6;
  o.common.seed = 3;
  o.common.quiet = true;
  o.common.no_provenance = true;
  o.common.output = tmp.path + "/full.jsonl";
  o.front = tmp.path + "/full.json";
  REQUIRE(run_nsga(o) == 0);
  const std::string full = slurp(o.common.output);
  for (double cut : {0.05, 0.5, 0.93}) {
    const std::string part = full.substr(0, static_cast<size_t>(cut * static_cast<double>(full.size())));
    const std::string log = tmp.file("part.jsonl", part);
    NsgaOptions r = o;
    r.common.output = "-";
    r.resume = log;
    r.front = tmp.path + "/resumed.json";
    REQUIRE(run_nsga(r) == 0);
    CHECK(slurp(r.front) == slurp(o.front));
    CHECK(slurp(log) == full);  // appended to the log: the same records in the same order
  }
  // Another seed's log is refused, naming the key.
  NsgaOptions other = o;
  other.common.seed = 4;
  other.resume = o.common.output;
  other.common.output = tmp.path + "/other.jsonl";
  std::string msg;
  CHECK(test::error_code([&] { run_nsga(other); }, &msg) == 64);
  CHECK(msg.find("seed") != std::string::npos);
}

TEST_CASE("MPI wire format keeps every bit, NaN and infinity included", "[nsga][app]") {
  Evaluation e;
  e.f = {0.1, NAN, -INFINITY, 5e-324};
  e.g = {1.0 / 3.0};
  e.ok = false;
  e.reason = "lost";
  const Evaluation d = decode_evaluation(encode_evaluation(e));
  CHECK(d.ok == false);
  CHECK(d.reason == "lost");
  REQUIRE(d.f.size() == 4);
  CHECK(std::memcmp(d.f.data(), e.f.data(), 4 * sizeof(double)) == 0);
  CHECK(d.g == e.g);
  CHECK_FALSE(decode_evaluation("xy").ok);
}
