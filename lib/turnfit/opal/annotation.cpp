// Writing and reading the turnfit annotation of exported OPAL inputs.
#include "turnfit/opal/annotation.hpp"

#include <cstring>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {

using nlohmann::json;

const char* const kAnnotationFormat = "turnfit-opal-annotation/1";
// The sections OPAL's commands describe; name and description come from the import itself.
const char* const kSections[] = {"particle", "field", "rf", "cavities", "trimcoils", "probes", "injection", "tracking"};

}  // namespace

std::string write_annotation(const json& opal_part, const json& machine) {
  json a = json::object();
  a["format"] = kAnnotationFormat;
  json o = json::object();
  for (const char* s : kSections)
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
  for (const char* s : kSections) {
    const bool a = recorded.contains(s), b = now.contains(s);
    if (a != b || (a && recorded[s] != now[s])) out.push_back(s);
  }
  return out;
}

}  // namespace turnfit
