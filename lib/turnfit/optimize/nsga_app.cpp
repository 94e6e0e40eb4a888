// turnfit-nsga: NSGA-II over a built-in or file-defined problem, with a population log that is
// also the checkpoint, exact resume, the final front, and progress on stderr.
#include "turnfit/optimize/nsga_app.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/optimize/mpi.hpp"

namespace turnfit {

void add_nsga_options(CLI::App& app, NsgaOptions& o) {
  app.description(
      "NSGA-II (Deb et al. 2002) with constraint-domination, deterministic for a seed whatever the\n"
      "threads or MPI ranks. Writes one JSON line per evaluated design (the population log, also the\n"
      "checkpoint: --resume continues a killed run with no evaluation lost or repeated) and the final\n"
      "non-dominated set (--front). Progress per generation on stderr.\n"
      "A problem file's evaluator.command (and --eval-cmd) is run by /bin/sh once per design: a\n"
      "problem file runs code, trust it as you would a Makefile (turnfit-problem(5), SECURITY).");
  app.add_option("--problem", o.problem,
                 "A built-in problem (" + [] {
                   std::string s;
                   for (const auto& n : builtin_problem_names()) s += (s.empty() ? "" : ", ") + n;
                   return s;
                 }() + ") or a problem file (turnfit-problem(5))")
      ->required();
  app.add_option("--eval-cmd", o.eval_cmd,
                 "Evaluate each design by this shell command: the design as JSON on stdin, {\"f\": [...], \"g\": "
                 "[...]} on stdout");
  app.add_option("--timeout", o.timeout_s, "Seconds an evaluation may take (default: the problem file's, else none)")
      ->check(CLI::Range(0.0, 1e9));
  app.add_option("--variables", o.n_variables, "Number of variables of a built-in problem (default: its usual)")
      ->check(CLI::Range(1, 100000));
  app.add_option("--objectives", o.n_objectives, "Number of objectives of DTLZ2 and C2-DTLZ2 (default 3)")
      ->check(CLI::Range(2, 50));
  app.add_option("--population", o.settings.population, "Individuals per generation")
      ->check(CLI::Range(2, 100000000))
      ->capture_default_str();
  app.add_option("--generations", o.settings.generations, "Offspring generations after the initial population")
      ->check(CLI::Range(0, 100000000))
      ->capture_default_str();
  app.add_option("--crossover-probability", o.settings.crossover_probability, "Probability that a pair is crossed")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  app.add_option("--eta-c", o.settings.eta_c, "SBX distribution index")->check(CLI::Range(0.0, 1e6))->capture_default_str();
  app.add_option("--mutation-probability", o.settings.mutation_probability,
                 "Per-variable mutation probability (default 1/n)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--eta-m", o.settings.eta_m, "Polynomial mutation distribution index")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app.add_option("--reference", o.reference,
                 "Hypervolume reference point for progress (default: the problem file's; 1.1 per objective for "
                 "ZDT and DTLZ2)")
      ->delimiter(',');
  app.add_option("--front", o.front, "Write the final non-dominated feasible set here (JSON array)");
  app.add_option("--resume", o.resume,
                 "Continue the run this population log holds (new records are appended to it, or go with its "
                 "records to -o FILE)");
  cli::add_common_options(app, o.common, cli::kOutput | cli::kThreads | cli::kSeed);
}

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

/// A JSON number, or null for NaN and infinities (JSON has neither).
nlohmann::json jnum(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); }

nlohmann::json jvec(const std::vector<double>& v) {
  nlohmann::json a = nlohmann::json::array();
  for (double x : v) a.push_back(jnum(x));
  return a;
}

nlohmann::json x_json(const std::vector<double>& x, const std::vector<std::string>& names) {
  if (names.empty()) return x;
  nlohmann::json o = nlohmann::json::object();
  for (size_t i = 0; i < x.size(); ++i) o[names[i]] = x[i];
  return o;
}

std::vector<double> read_doubles(const nlohmann::json& v, const std::string& where, const std::string& file,
                                 long line) {
  if (!v.is_array()) throw data_error(file, line, where + ": expected an array");
  std::vector<double> out;
  for (const auto& e : v) {
    if (e.is_null()) out.push_back(NAN);
    else if (e.is_number()) out.push_back(e.get<double>());
    else throw data_error(file, line, where + ": expected numbers");
  }
  return out;
}

}  // namespace

std::string eval_record(const Individual& ind, const std::vector<std::string>& names) {
  nlohmann::json j;
  j["record"] = "eval";
  j["gen"] = ind.generation;
  j["id"] = ind.id;
  j["x"] = x_json(ind.x, names);
  j["f"] = jvec(ind.f);
  j["g"] = jvec(ind.g);
  j["violation"] = jnum(ind.violation);  // null: a failed evaluation (infinite violation)
  j["ok"] = ind.ok;
  if (!ind.ok) j["reason"] = ind.reason;
  // Known only once the generation is selected: see the "generation" record.
  j["rank"] = nullptr;
  j["crowding"] = nullptr;
  return json_text(j);
}

PopulationLog parse_population_log(const std::string& text, const std::string& name,
                                   const std::vector<std::string>& names) {
  PopulationLog log;
  size_t pos = 0;
  long line_no = 0;
  while (pos < text.size()) {
    const size_t nl = text.find('\n', pos);
    ++line_no;
    const bool last = nl == std::string::npos || nl + 1 >= text.size();
    const std::string line = text.substr(pos, nl == std::string::npos ? std::string::npos : nl - pos);
    const size_t next = nl == std::string::npos ? text.size() : nl + 1;
    // turnfit-population(5): one record a line, each ended by a newline. A blank line is no
    // record; a killed run's torn last line may be one (a record cut before its first byte).
    if (line.find_first_not_of(" \t\r") == std::string::npos) {
      if (nl == std::string::npos) {
        log.torn_tail = true;
        break;
      }
      throw data_error(name, line_no, "a blank line: every line of a population log is a record");
    }
    nlohmann::json j;
    bool parsed = true;
    try {
      j = parse_json(line, name);
    } catch (const Error&) {
      parsed = false;
    }
    // A killed run leaves at most its last record torn: without its newline, or cut short.
    if (nl == std::string::npos || (!parsed && last)) {
      log.torn_tail = true;
      break;
    }
    if (!parsed || !j.is_object() || !j.contains("record"))
      throw data_error(name, line_no, "not a population log record (a JSON object with \"record\")");
    const std::string kind = j["record"].is_string() ? j["record"].get<std::string>() : "";
    if (kind == "run") {
      if (!log.run.is_null()) throw data_error(name, line_no, "a second \"run\" record: the log holds two runs");
      log.run = j;
    } else if (kind == "eval") {
      Individual ind;
      try {
        // A count, not any number: nlohmann converts 4e47 to an integer without a check.
        for (const char* key : {"id", "gen"})
          if (!j.at(key).is_number_unsigned())
            throw data_error(name, line_no, std::string("bad \"eval\" record: \"") + key + "\" is not an integer >= 0");
        ind.id = j.at("id").get<std::uint64_t>();
        ind.generation = j.at("gen").get<size_t>();
        const auto& x = j.at("x");
        if (x.is_object()) {
          if (names.empty()) throw data_error(name, line_no, "\"x\" is an object but the problem names no variables");
          if (x.size() != names.size())
            throw data_error(name, line_no, "\"x\" has " + std::to_string(x.size()) + " variables, the problem " +
                                                std::to_string(names.size()));
          for (const auto& n : names) {
            auto it = x.find(n);
            if (it == x.end() || !it->is_number())
              throw data_error(name, line_no, "\"x\" lacks variable '" + n + "'");
            ind.x.push_back(it->get<double>());
          }
        } else {
          ind.x = read_doubles(x, "x", name, line_no);
        }
        ind.f = read_doubles(j.at("f"), "f", name, line_no);
        ind.g = read_doubles(j.at("g"), "g", name, line_no);
        ind.ok = j.at("ok").get<bool>();
        ind.violation = j.at("violation").is_null() ? kInf : j.at("violation").get<double>();
        if (!ind.ok) ind.violation = kInf;
        if (j.contains("reason")) ind.reason = j["reason"].get<std::string>();
      } catch (const nlohmann::json::exception& e) {
        throw data_error(name, line_no, std::string("bad \"eval\" record: ") + e.what());
      }
      log.evaluated.push_back(std::move(ind));
    } else if (kind == "generation") {
      // Only its number matters to a resume (its record is not written twice).
      auto gen = j.find("gen");
      if (gen == j.end() || !gen->is_number_unsigned())
        throw data_error(name, line_no, "a \"generation\" record without its number (\"gen\", an integer >= 0)");
      log.generations.insert(gen->get<size_t>());
    } else {
      throw data_error(name, line_no, "unknown record \"" + kind + "\"");
    }
    pos = next;
    log.valid_bytes = pos;
  }
  return log;
}

nlohmann::json front_json(const std::vector<Individual>& front, const std::vector<std::string>& names) {
  nlohmann::json a = nlohmann::json::array();
  for (const auto& ind : front)
    a.push_back({{"id", ind.id}, {"x", x_json(ind.x, names)}, {"f", jvec(ind.f)}, {"violation", jnum(ind.violation)}});
  return a;
}

namespace {

/// The run record: what a resumed run must match.
nlohmann::json run_record(const NsgaOptions& o, const LoadedProblem& lp, bool provenance) {
  const Problem& p = *lp.problem;
  nlohmann::json j;
  j["record"] = "run";
  if (provenance) j["provenance"] = cli::provenance();
  j["problem"] = p.name();
  j["source"] = lp.source;
  j["variables"] = p.variable_names().empty() ? nlohmann::json(p.n_variables()) : nlohmann::json(p.variable_names());
  j["lower"] = p.lower();
  j["upper"] = p.upper();
  j["objectives"] = lp.objective_names;
  j["constraints"] = lp.constraint_names;
  const Nsga2Settings& s = o.settings;
  j["population"] = s.population;
  j["generations"] = s.generations;
  j["seed"] = o.common.seed;
  j["crossover_probability"] = s.crossover_probability;
  j["eta_c"] = s.eta_c;
  j["crossover_variable_probability"] = s.crossover_variable_probability;
  // The probability used (the default -1 means 1/n).
  j["mutation_probability"] =
      s.mutation_probability < 0 ? 1.0 / static_cast<double>(p.n_variables()) : s.mutation_probability;
  j["eta_m"] = s.eta_m;
  return j;
}

/// A resumed run must be the logged one: same problem, bounds, population, seed and operators
/// (more generations may be asked for: the run continues further).
void check_same_run(const nlohmann::json& logged, const nlohmann::json& now, const std::string& file) {
  for (const char* key : {"problem", "variables", "lower", "upper", "objectives", "constraints", "population", "seed",
                          "crossover_probability", "eta_c", "crossover_variable_probability",
                          "mutation_probability", "eta_m"}) {
    if (!logged.contains(key)) throw data_error(file, 1, std::string("the run record lacks \"") + key + "\"");
    if (logged[key] != now[key])
      throw usage_error(file + ": the log is of another run: " + key + " " + json_text(logged[key]) + " there, " +
                        json_text(now[key]) + " here");
  }
}

/// The default hypervolume reference: 1.1 per objective for ZDT and DTLZ2 (fronts in [0, 1]).
std::vector<double> default_reference(const LoadedProblem& lp) {
  if (!lp.reference.empty()) return lp.reference;
  const std::string& n = lp.problem->name();
  if (lp.source == "builtin" && (n.rfind("ZDT", 0) == 0 || n == "DTLZ2"))
    return std::vector<double>(lp.problem->n_objectives(), 1.1);
  return {};
}

}  // namespace

int run_nsga(const NsgaOptions& o) {
  MpiSession mpi;  // initializes MPI only when started by mpirun (TURNFIT_WITH_MPI builds)
  LoadedProblem lp = load_problem(o.problem, o.eval_cmd, o.timeout_s, o.n_variables, o.n_objectives);
  const Problem& problem = *lp.problem;
  const std::vector<std::string>& names = problem.variable_names();
  if (mpi.size() > 1 && mpi.rank() > 0) {
    mpi_worker_loop(mpi, problem);
    return 0;
  }

  // Workers wait in mpi_worker_loop until told to stop: on every way out, error or not.
  std::unique_ptr<MpiEvaluator> mpi_eval;
  if (mpi.size() > 1) mpi_eval = std::make_unique<MpiEvaluator>(mpi);
  struct StopWorkers {
    MpiEvaluator* ev;
    ~StopWorkers() {
      if (ev) ev->stop_workers();
    }
  } stop_workers{mpi_eval.get()};
  if (o.front == "-" && (o.common.output.empty() || o.common.output == "-") && o.resume.empty())
    throw usage_error("--front - and the population log (-o) both on stdout: give one of them a file");
  Nsga2Settings settings = o.settings;
  settings.seed = o.common.seed;
  settings.reference = o.reference.empty() ? default_reference(lp) : o.reference;
  // The exact hypervolume grows steeply with the objectives (WFG: 7 s for 8000 points in 4-D,
  // 22 s in 6-D): the progress figure is left out there unless asked for with --reference.
  if (o.reference.empty() && problem.n_objectives() > 3 && settings.population > 500) settings.reference.clear();
  if (!settings.reference.empty() && settings.reference.size() != problem.n_objectives())
    throw usage_error("--reference has " + std::to_string(settings.reference.size()) + " values for " +
                      std::to_string(problem.n_objectives()) + " objectives");
  if (settings.population < 2) throw usage_error("--population must be at least 2");
  const nlohmann::json run = run_record(o, lp, !o.common.no_provenance);

  // Resume: the log's records, checked against this run.
  PopulationLog log;
  std::string resume_text;
  std::string out_path = o.common.output.empty() ? "-" : o.common.output;
  bool append = false;
  bool fresh = o.resume.empty();
  if (!o.resume.empty()) {
    resume_text = read_input(o.resume, limits::kLogBytes).text;
    log = parse_population_log(resume_text, o.resume, names);
    // A run killed before its run record was complete left nothing to resume: start afresh.
    fresh = log.run.is_null() && log.evaluated.empty();
    if (log.run.is_null() && !fresh)
      throw data_error(o.resume, 0, "no \"run\" record: not a turnfit-nsga population log");
    if (!fresh) check_same_run(log.run, run, o.resume);
    std::error_code ec;
    if (out_path == "-" || std::filesystem::equivalent(out_path, o.resume, ec)) {
      out_path = o.resume;
      append = true;
      // Cut a torn last record so the appended ones start on a line of their own.
      if (log.torn_tail && ::truncate(o.resume.c_str(), static_cast<off_t>(log.valid_bytes)) != 0)
        throw Error(ExitCode::cant_create, o.resume + ": cannot cut its torn last record: " + std::strerror(errno));
    }
    if (log.torn_tail) cli::warn(o.common, o.resume + ": its last record was torn (a killed run): dropped");
    if (!o.common.quiet)
      std::cerr << "turnfit-nsga: resuming " << o.resume << ": " << log.evaluated.size() << " evaluations logged\n";
  }

  // The log stream: records flushed one by one (it is the checkpoint, not an atomic output).
  // It is written from the first record the search makes, so that a run refused before its
  // first evaluation (a resumed log whose records do not fit this run) leaves a file it names
  // as it was, and no new file behind. Whether it can be written is checked now.
  // A FIFO or device is opened at once (a probe open and close would end a reader's input).
  struct NewLog {
    std::string path;  ///< a file this run created, removed unless a record went into it
    bool kept = false;
    StopCleanup stop;  ///< a stop signal before the first record removes it too
    ~NewLog() {
      if (!path.empty() && !kept) std::remove(path.c_str());
    }
  } new_log;
  bool open_now = false;
  if (out_path != "-") {
    struct stat st {};
    const bool existed = ::stat(out_path.c_str(), &st) == 0;
    if (existed && !S_ISREG(st.st_mode)) {
      open_now = true;
    } else {
      const StopSignalsHeld held;  // no stop between the creation and the registration
      std::ofstream probe(out_path, std::ios::binary | std::ios::app);  // creates, never truncates
      if (!probe) throw Error(ExitCode::cant_create, out_path + ": cannot open: " + std::strerror(errno));
      if (!existed) {
        new_log.path = out_path;
        new_log.stop = StopCleanup::path(out_path);
      }
    }
  }
  std::ofstream file;
  std::ostream* out = nullptr;
  bool write_failed = false;
  const auto open_log = [&] {
    if (out) return;
    new_log.kept = true;
    new_log.stop.release();
    if (out_path == "-") {
      out = &std::cout;
    } else {
      file.open(out_path, std::ios::binary | (append ? std::ios::app : std::ios::trunc));
      out = &file;
    }
    if (fresh) {
      *out << json_text(run) << "\n";
    } else if (!append) {
      // A new file continues the old one: its records first.
      out->write(resume_text.data(), static_cast<std::streamsize>(log.valid_bytes));
    }
    out->flush();
    write_failed = !*out;
  };

  if (open_now) open_log();

  const bool quiet = o.common.quiet;
  Nsga2Callbacks cb;
  cb.on_evaluated = [&](const Individual& ind) {
    open_log();
    if (write_failed) return;
    *out << eval_record(ind, names) << '\n';
    out->flush();
    write_failed = !*out;
  };
  const size_t total = settings.generations;
  bool printed = false;
  std::chrono::steady_clock::time_point last_print;
  cb.on_generation = [&](const Nsga2Progress& p) {
    open_log();
    if (!log.generations.count(p.generation) && !write_failed) {
      nlohmann::json g;
      g["record"] = "generation";
      g["gen"] = p.generation;
      g["evaluations"] = p.evaluations;
      g["feasible"] = p.feasible;
      g["hypervolume"] = jnum(p.hypervolume);
      g["best_sum"] = jnum(p.best_sum);
      if (std::isfinite(p.best_sum)) g["best_id"] = p.best_id;
      nlohmann::json surv = nlohmann::json::array();  // [id, rank, crowding]; crowding null = infinite
      if (p.population)
        for (const auto& ind : *p.population) surv.push_back({ind.id, ind.rank, jnum(ind.crowding)});
      g["survivors"] = surv;
      *out << json_text(g) << '\n';
      out->flush();
      write_failed = !*out;
    }
    // A line a second at most (and the first and last): a fast problem would flood stderr.
    const auto now = std::chrono::steady_clock::now();
    const bool due = p.generation == total || !printed ||
                     std::chrono::duration<double>(now - last_print).count() >= 1.0;
    if (quiet || !due || (p.new_evaluations == 0 && p.generation != total)) return;
    printed = true;
    last_print = now;
    char buf[256];
    std::snprintf(buf, sizeof buf, "turnfit-nsga: gen %zu/%zu  evals %zu  feasible %zu/%zu", p.generation, total,
                  p.evaluations, p.feasible, settings.population);
    std::cerr << buf;
    if (std::isfinite(p.hypervolume)) std::cerr << "  hv " << cli::fmt(p.hypervolume, 7);
    if (std::isfinite(p.best_sum)) std::cerr << "  best sum " << cli::fmt(p.best_sum, 7) << " (id " << p.best_id << ")";
    std::cerr << "\n";
  };

  Nsga2Result result;
  if (mpi_eval) {
    result = run_nsga2(problem, settings, *mpi_eval, cb, log.evaluated);
  } else {
    result = run_nsga2(problem, settings, cli::resolve_threads(o.common.threads), cb, log.evaluated);
  }
  open_log();  // a run with nothing left to do still writes its log
  if (write_failed) throw Error(ExitCode::io, (out_path == "-" ? std::string("<stdout>") : out_path) + ": write error");

  size_t failed = 0;
  for (const auto& ind : result.population) failed += !ind.ok;
  // Not one design could be evaluated: the problem (a machine that loses the particle wherever
  // the bounds allow, an evaluator that always fails) is at fault, not the search. The log keeps
  // every attempt and its reason; no front is written.
  if (!result.population.empty() && failed == result.population.size()) {
    std::string why;
    for (const auto& ind : result.population)
      if (!ind.reason.empty()) {
        why = ind.reason;
        break;
      }
    throw Error(ExitCode::data, o.problem + ": no design of the final population could be evaluated (" +
                                    std::to_string(result.evaluations) + " evaluations; the log " +
                                    (out_path == "-" ? std::string("on stdout") : out_path) +
                                    " has every reason); the first: " + why);
  }
  if (failed) cli::warn(o.common, std::to_string(failed) + " of the final population failed to evaluate (see \"reason\")");
  const std::vector<Individual> front = pareto_front(result.population);
  if (front.empty()) cli::warn(o.common, "no feasible individual in the final population: the front is empty");
  if (!o.front.empty()) {
    OutputFile f(o.front);
    f.stream() << json_text(front_json(front, names), 1) << "\n";
    f.commit();
  }
  if (!quiet)
    std::cerr << "turnfit-nsga: " << result.evaluations << " evaluations (" << result.new_evaluations << " new, "
              << result.reused << " from the log), front of " << front.size() << "\n";
  return 0;
}

}  // namespace turnfit
