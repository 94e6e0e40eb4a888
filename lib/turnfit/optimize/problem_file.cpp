// Built-in and file-defined problems, and the external-command evaluator.
#include "turnfit/optimize/problem_file.hpp"
#include "turnfit/optimize/problem_keys.hpp"
#include "turnfit/optimize/turn_problem.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <iostream>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "turnfit/cli/common.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/process.hpp"

namespace turnfit {

CommandProblem::CommandProblem(std::string name, std::vector<double> lower, std::vector<double> upper,
                               std::vector<std::string> variable_names, std::vector<std::string> objective_names,
                               std::vector<std::string> constraint_names, std::string command, std::string cwd,
                               double timeout_s)
    : Problem(std::move(name), std::move(lower), std::move(upper), objective_names.size(), constraint_names.size(),
              std::move(variable_names)),
      objective_names_(std::move(objective_names)),
      constraint_names_(std::move(constraint_names)),
      command_(std::move(command)),
      cwd_(std::move(cwd)),
      timeout_s_(timeout_s) {}

namespace {

/// The last non-empty line of a text (for a short reason).
std::string last_line(const std::string& text) {
  std::istringstream in(text);
  std::string line, last;
  while (std::getline(in, line))
    if (line.find_first_not_of(" \t\r") != std::string::npos) last = line;
  if (last.size() > 300) last = last.substr(0, 300) + "...";
  return last;
}

/// Reads "f" or "g" of an answer: an array of n numbers or an object keyed by the names.
bool read_values(const nlohmann::json& v, const char* key, const std::vector<std::string>& names,
                 std::vector<double>& out, std::string& why) {
  out.assign(names.size(), NAN);
  if (v.is_array()) {
    if (v.size() != names.size()) {
      why = std::string("\"") + key + "\" has " + std::to_string(v.size()) + " values, the problem " +
            std::to_string(names.size());
      return false;
    }
    for (size_t i = 0; i < v.size(); ++i) {
      if (!v[i].is_number()) {
        why = std::string("\"") + key + "\"[" + std::to_string(i) + "] is not a number";
        return false;
      }
      out[i] = v[i].get<double>();
    }
    return true;
  }
  if (v.is_object()) {
    for (size_t i = 0; i < names.size(); ++i) {
      auto it = v.find(names[i]);
      if (it == v.end() || !it->is_number()) {
        why = std::string("\"") + key + "\" lacks a number for '" + names[i] + "'";
        return false;
      }
      out[i] = it->get<double>();
    }
    for (auto it = v.begin(); it != v.end(); ++it)
      if (std::find(names.begin(), names.end(), it.key()) == names.end()) {
        why = std::string("\"") + key + "\" has '" + it.key() + "', which the problem does not name";
        return false;
      }
    return true;
  }
  why = std::string("\"") + key + "\" is neither an array nor an object";
  return false;
}

}  // namespace

Evaluation parse_command_answer(const std::string& out, const std::vector<std::string>& objective_names,
                                const std::vector<std::string>& constraint_names) {
  Evaluation e;
  e.ok = false;
  nlohmann::json j;
  // The whole output, else its last line (a command may print progress before its answer).
  // parse_json: an answer nested past the limit or holding a NUL is no answer (issue 18).
  try {
    j = parse_json(out, "answer");
  } catch (const Error&) {
    try {
      j = parse_json(last_line(out), "answer");
    } catch (const Error&) {
      e.reason = out.find_first_not_of(" \t\r\n") == std::string::npos
                     ? "the command printed no answer"
                     : "the command's answer is not JSON: " + last_line(out);
      return e;
    }
  }
  if (!j.is_object()) {
    e.reason = "the command's answer is not a JSON object";
    return e;
  }
  if (auto it = j.find("error"); it != j.end()) {
    e.reason = "the command says: " + (it->is_string() ? it->get<std::string>() : json_text(*it));
    return e;
  }
  auto f = j.find("f");
  if (f == j.end()) {
    e.reason = "the command's answer has no \"f\"";
    return e;
  }
  if (!read_values(*f, "f", objective_names, e.f, e.reason)) return e;
  auto g = j.find("g");
  if (g == j.end()) {
    if (!constraint_names.empty()) {
      e.reason = "the command's answer has no \"g\" for the problem's " + std::to_string(constraint_names.size()) +
                 " constraint(s)";
      return e;
    }
  } else if (!read_values(*g, "g", constraint_names, e.g, e.reason)) {
    return e;
  }
  e.ok = true;
  return e;
}

Evaluation CommandProblem::evaluate(const std::vector<double>& x) const {
  nlohmann::json in;
  const auto& names = variable_names();
  if (names.empty()) {
    in["x"] = x;
  } else {
    nlohmann::json obj = nlohmann::json::object();
    for (size_t i = 0; i < x.size(); ++i) obj[names[i]] = x[i];
    in["x"] = obj;
  }
  ProcessSpec spec;
  spec.argv = shell_argv(command_);
  spec.input = json_text(in) + "\n";
  spec.timeout_s = timeout_s_;
  spec.cwd = cwd_;
  spec.max_output = 1u << 20;
  const ProcessResult r = run_process(spec);
  if (!r.ok()) {
    Evaluation e;
    e.ok = false;
    const std::string tail = last_line(r.err);
    e.reason = "evaluator " + r.describe(timeout_s_) + (tail.empty() ? "" : ": " + tail);
    return e;
  }
  return parse_command_answer(r.out, objective_names_, constraint_names_);
}

namespace {

std::vector<std::string> numbered(const char* stem, size_t n) {
  std::vector<std::string> v;
  for (size_t i = 0; i < n; ++i) v.push_back(stem + std::to_string(i + 1));
  return v;
}

bool looks_like_file(const std::string& s) {
  return s.find('/') != std::string::npos || s.find('.') != std::string::npos || s == "-";
}

/// A problem file's parts, with errors that name the file and the key.
struct FileReader : ProblemKeys {
  /// "objectives"/"constraints": a list of names or a count.
  std::vector<std::string> names(const nlohmann::json& v, const std::string& where, const char* stem) const {
    if (v.is_number_unsigned()) return numbered(stem, v.get<size_t>());
    if (!v.is_array()) fail(where, "expected a list of names or a count");
    std::vector<std::string> out;
    std::set<std::string> seen;
    for (size_t i = 0; i < v.size(); ++i) {
      out.push_back(text(v[i], where + "/" + std::to_string(i)));
      if (!seen.insert(out.back()).second) fail(where, "'" + out.back() + "' appears twice");
    }
    return out;
  }
};

}  // namespace

LoadedProblem load_problem(const std::string& name_or_file, const std::string& eval_cmd, double timeout_s,
                           size_t n_variables, size_t n_objectives) {
  LoadedProblem lp;
  if (!looks_like_file(name_or_file) && !std::filesystem::exists(name_or_file)) {
    auto builtin = make_problem(name_or_file, n_variables, n_objectives);
    lp.objective_names = numbered("f", builtin->n_objectives());
    lp.constraint_names = numbered("g", builtin->n_constraints());
    lp.source = "builtin";
    if (!eval_cmd.empty()) {
      lp.problem = std::make_unique<CommandProblem>(builtin->name(), builtin->lower(), builtin->upper(),
                                                    builtin->variable_names(), lp.objective_names,
                                                    lp.constraint_names, eval_cmd, "", timeout_s < 0 ? 0 : timeout_s);
    } else {
      lp.problem = std::move(builtin);
    }
    return lp;
  }
  if (n_variables || n_objectives)
    throw usage_error("--variables and --objectives size the built-in problems only, not " + name_or_file);
  const std::string file = name_or_file == "-" ? "<stdin>" : name_or_file;
  FileReader rd{{file}};
  const nlohmann::json j = read_json(name_or_file);
  if (!j.is_object()) throw data_error(file, 0, "a problem file is a JSON object");
  if (rd.text(rd.need(j, "format", ""), "format") != "turnfit-problem/1")
    rd.fail("format", "expected \"turnfit-problem/1\"");
  // The hypervolume reference, once the objectives are known (both kinds of problem).
  auto read_reference = [&] {
    std::vector<double> ref;
    if (!j.contains("reference")) return ref;
    const auto& r = j["reference"];
    if (!r.is_array() || r.size() != lp.objective_names.size()) rd.fail("reference", "expected one number per objective");
    for (size_t i = 0; i < r.size(); ++i) ref.push_back(rd.number(r[i], "reference/" + std::to_string(i)));
    return ref;
  };
  if (j.contains("machine")) {
    // The turn-pattern kind: evaluated in process (track + compare).
    if (!eval_cmd.empty())
      throw usage_error(file + " is a turn-pattern problem (it names a machine), evaluated in process: "
                               "--eval-cmd is for problems without one");
    const std::string dir =
        name_or_file == "-" ? std::string() : std::filesystem::absolute(name_or_file).parent_path().string();
    auto tp = TurnPatternProblem::from_json(j, file, dir);
    for (const auto& o : tp->objectives()) lp.objective_names.push_back(o.name.empty() ? objective_spec(o) : o.name);
    if (tp->turn_count_constraint()) lp.constraint_names = {"turn-count"};
    lp.reference = read_reference();
    lp.problem = std::move(tp);
    lp.source = file;
    return lp;
  }
  static const std::set<std::string> known = {"format", "name", "variables", "objectives", "constraints",
                                              "evaluator", "reference", "description"};
  for (auto it = j.begin(); it != j.end(); ++it)
    if (!known.count(it.key())) {
      if (it.key() == "peaks" || it.key() == "sigma_mm")
        rd.fail(it.key(), "belongs to a turn-pattern problem, which names its \"machine\"");
      rd.fail(it.key(), "unknown key (known: format, name, variables, objectives, constraints, evaluator, "
                        "reference, description; a turn-pattern problem: machine, peaks, sigma_mm)");
    }
  const std::string name = j.contains("name") ? rd.text(j["name"], "name")
                                               : std::filesystem::path(file).stem().string();
  const auto& vars = rd.need(j, "variables", "");
  if (!vars.is_array() || vars.empty()) rd.fail("variables", "expected a non-empty list of {name, lower, upper}");
  std::vector<double> lo, hi;
  std::vector<std::string> vnames;
  std::set<std::string> seen;
  for (size_t i = 0; i < vars.size(); ++i) {
    const std::string where = "variables/" + std::to_string(i);
    const auto& v = vars[i];
    if (!v.is_object()) rd.fail(where, "expected {\"name\", \"lower\", \"upper\"}");
    for (auto it = v.begin(); it != v.end(); ++it)
      if (it.key() != "name" && it.key() != "lower" && it.key() != "upper")
        rd.fail(where + "/" + it.key(), "unknown key (known: name, lower, upper)");
    vnames.push_back(rd.text(rd.need(v, "name", where), where + "/name"));
    if (!seen.insert(vnames.back()).second) rd.fail(where + "/name", "'" + vnames.back() + "' appears twice");
    lo.push_back(rd.number(rd.need(v, "lower", where), where + "/lower"));
    hi.push_back(rd.number(rd.need(v, "upper", where), where + "/upper"));
    if (!(lo.back() < hi.back())) rd.fail(where, "lower must be below upper");
  }
  lp.objective_names = rd.names(rd.need(j, "objectives", ""), "objectives", "f");
  if (lp.objective_names.empty()) rd.fail("objectives", "at least one objective");
  if (j.contains("constraints")) lp.constraint_names = rd.names(j["constraints"], "constraints", "g");
  lp.reference = read_reference();
  std::string command = eval_cmd, cwd;
  double limit = timeout_s;
  if (j.contains("evaluator")) {
    const auto& ev = j["evaluator"];
    if (!ev.is_object()) rd.fail("evaluator", "expected {\"command\", \"timeout_s\"}");
    for (auto it = ev.begin(); it != ev.end(); ++it)
      if (it.key() != "command" && it.key() != "timeout_s")
        rd.fail("evaluator/" + it.key(), "unknown key (known: command, timeout_s)");
    if (command.empty()) {
      command = rd.text(rd.need(ev, "command", "evaluator"), "evaluator/command");
      // The file's command runs beside the file, so it can name its scripts relatively.
      if (name_or_file != "-") cwd = std::filesystem::absolute(name_or_file).parent_path().string();
    }
    if (limit < 0 && ev.contains("timeout_s")) {
      limit = rd.number(ev["timeout_s"], "evaluator/timeout_s");
      if (limit < 0) rd.fail("evaluator/timeout_s", "must not be negative");
    }
  }
  if (command.empty())
    throw usage_error(file + ": the problem has no \"evaluator\" command; give --eval-cmd 'CMD'");
  lp.problem = std::make_unique<CommandProblem>(name, lo, hi, vnames, lp.objective_names, lp.constraint_names,
                                                command, cwd, limit < 0 ? 0 : limit);
  lp.source = file;
  return lp;
}

}  // namespace turnfit
