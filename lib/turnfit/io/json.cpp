// JSON parsing that turns nlohmann's byte offsets into line numbers for the user, and refuses
// what nlohmann would take badly: NUL bytes (its lexer reads one as the end of input, so a
// document followed by garbage after a NUL passed) and nesting so deep that copying or
// destroying the value overflows the stack.
#include "turnfit/io/json.hpp"

#include <algorithm>

#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {
namespace {

long line_at(const std::string& text, size_t pos) {
  pos = std::min(pos, text.size());
  return 1 + static_cast<long>(std::count(text.begin(), text.begin() + static_cast<long>(pos), '\n'));
}

/// NUL bytes and nesting depth, outside strings (brackets in strings do not nest). The document
/// need not be valid JSON: nlohmann judges the rest.
void check_structure(const std::string& text, const std::string& name) {
  int depth = 0;
  bool in_string = false, escaped = false;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (c == '\0') throw data_error(name, line_at(text, i), "invalid JSON: a NUL byte (binary data?)");
    if (in_string) {
      if (escaped) escaped = false;
      else if (c == '\\') escaped = true;
      else if (c == '"') in_string = false;
      continue;
    }
    if (c == '"') {
      in_string = true;
    } else if (c == '[' || c == '{') {
      if (++depth > limits::kJsonDepth)
        throw data_error(name, line_at(text, i), "invalid JSON: nested deeper than " +
                                                     std::to_string(limits::kJsonDepth) + " levels (the limit)");
    } else if (c == ']' || c == '}') {
      --depth;
    }
  }
}

/// nlohmann's message without its "[json.exception.parse_error.101] parse error at line L,
/// column C: " prefix (our own prefix names the file and line).
std::string without_prefix(const std::string& what) {
  const auto colon = what.find(": ");
  if (what.rfind("[json.exception.", 0) == 0 && colon != std::string::npos) return what.substr(colon + 2);
  const auto bracket = what.find("] ");
  return what.rfind("[json.exception.", 0) == 0 && bracket != std::string::npos ? what.substr(bracket + 2) : what;
}

}  // namespace

nlohmann::json parse_json(const std::string& text, const std::string& name) {
  if (trim(text).empty()) throw data_error(name, 0, "empty input: no JSON document");
  check_structure(text, name);
  try {
    return nlohmann::json::parse(text.begin(), text.end());
  } catch (const nlohmann::json::parse_error& e) {
    throw data_error(name, line_at(text, e.byte), "invalid JSON: " + without_prefix(e.what()));
  } catch (const nlohmann::json::out_of_range& e) {
    // A number out of a double's range ("1e400"): nlohmann names the token but not where it is.
    const std::string what = without_prefix(e.what());
    const auto q1 = what.find('\''), q2 = what.rfind('\'');
    long line = 0;
    if (q1 != std::string::npos && q2 > q1 + 1) {
      const size_t at = text.find(what.substr(q1 + 1, q2 - q1 - 1));
      if (at != std::string::npos) line = line_at(text, at);
    }
    throw data_error(name, line, "invalid JSON: " + what + " (out of range of a double)");
  } catch (const nlohmann::json::exception& e) {
    throw data_error(name, 0, "invalid JSON: " + without_prefix(e.what()));
  }
}

nlohmann::json read_json(const std::string& path) {
  InputText in = read_input(path);
  return parse_json(in.text, in.name);
}

}  // namespace turnfit
