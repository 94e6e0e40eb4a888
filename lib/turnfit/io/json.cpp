// JSON parsing that turns nlohmann's byte offsets into line numbers for the user.
#include "turnfit/io/json.hpp"

#include <algorithm>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

nlohmann::json parse_json(const std::string& text, const std::string& name) {
  if (trim(text).empty()) throw data_error(name, 0, "empty input: no JSON document");
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::parse_error& e) {
    size_t pos = std::min<size_t>(e.byte, text.size());
    long line = 1 + static_cast<long>(std::count(text.begin(), text.begin() + static_cast<long>(pos), '\n'));
    std::string what = e.what();
    // nlohmann prefixes "[json.exception.parse_error.101] parse error at line L, column C: "
    auto colon = what.find(": ");
    if (colon != std::string::npos) what = what.substr(colon + 2);
    throw data_error(name, line, "invalid JSON: " + what);
  }
}

nlohmann::json read_json(const std::string& path) {
  InputText in = read_input(path);
  return parse_json(in.text, in.name);
}

}  // namespace turnfit
