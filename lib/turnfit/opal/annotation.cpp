// Writing and reading the turnfit annotation of exported OPAL inputs.
#include "turnfit/opal/annotation.hpp"

#include <cstring>
#include <filesystem>
#include <functional>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {

using nlohmann::json;

namespace fs = std::filesystem;

const char* const kAnnotationFormat = "turnfit-opal-annotation/1";

// A folder as an absolute path ("" is the current folder).
fs::path folder(const std::string& d) { return fs::absolute(d.empty() ? fs::path(".") : fs::path(d)).lexically_normal(); }

// Paths in a machine document: apply f to each (field map, profiles, coil tables, bunch file).
void for_each_path(json& m, const std::function<void(json&)>& f) {
  if (m.contains("field") && m["field"].contains("map")) f(m["field"]["map"]);
  for (const char* list : {"cavities", "trimcoils"}) {
    if (!m.contains(list) || !m[list].is_array()) continue;
    for (auto& e : m[list])
      for (const char* k : {"profile", "table"})
        if (e.is_object() && e.contains(k) && e[k].is_string()) f(e[k]);
  }
  if (m.contains("bunch") && m["bunch"].is_object() && m["bunch"].contains("file") && m["bunch"]["file"].is_string())
    f(m["bunch"]["file"]);
}

}  // namespace

const std::vector<std::string>& opal_sections() {
  static const std::vector<std::string> s = {"particle", "field",  "rf",        "cavities",
                                             "trimcoils", "probes", "injection", "tracking"};
  return s;
}

std::string relative_to(const std::string& path, const std::string& dir) {
  const fs::path abs = fs::absolute(fs::path(path)).lexically_normal();
  const fs::path rel = abs.lexically_relative(folder(dir));
  return rel.empty() ? abs.string() : rel.string();
}

void rebase_paths(json& m, const std::string& from_dir, const std::string& to_dir) {
  const fs::path from = folder(from_dir);
  for_each_path(m, [&](json& p) {
    const std::string s = p.get<std::string>();
    if (s.empty()) return;
    p = relative_to((fs::path(s).is_absolute() ? fs::path(s) : from / s).string(), to_dir);
  });
}

std::string write_annotation(const json& opal_part, const json& machine) {
  json a = json::object();
  a["format"] = kAnnotationFormat;
  json o = json::object();
  for (const auto& s : opal_sections())
    if (opal_part.contains(s)) o[s] = opal_part[s];
  a["opal"] = o;
  a["machine"] = machine;
  const std::string text = json_text(a, 1);
  std::string out;
  for (std::string_view l : split_lines(text)) out += std::string(kAnnotationPrefix) + std::string(l) + "\n";
  return out;
}

std::optional<Annotation> read_annotation(const std::string& text, const std::string& name) {
  std::string body;
  long first = 0, n = 0;
  const size_t plen = std::strlen(kAnnotationPrefix);
  for (std::string_view l : split_lines(text)) {
    ++n;
    if (l.size() >= plen - 1 && l.substr(0, plen - 1) == std::string_view(kAnnotationPrefix, plen - 1)) {
      if (!first) first = n;
      body += std::string(l.size() > plen ? l.substr(plen) : std::string_view()) + "\n";
    }
  }
  if (!first) return std::nullopt;
  const std::string where = name + ": turnfit annotation (line " + std::to_string(first) + ")";
  json a = parse_json(body, where);
  if (!a.is_object() || !a.contains("format") || a["format"] != kAnnotationFormat || !a.contains("opal") ||
      !a["opal"].is_object() || !a.contains("machine") || !a["machine"].is_object())
    throw data_error(name, first, "the '" + std::string(kAnnotationPrefix) + "' lines are not a " +
                                      kAnnotationFormat + " annotation");
  Annotation out;
  out.line = first;
  out.opal = a["opal"];
  out.machine = a["machine"];
  return out;
}

std::vector<std::string> changed_sections(const json& recorded, const json& now) {
  std::vector<std::string> out;
  for (const auto& s : opal_sections()) {
    const bool a = recorded.contains(s), b = now.contains(s);
    if (a != b || (a && recorded[s] != now[s])) out.push_back(s);
  }
  return out;
}

}  // namespace turnfit
