// JSON documents read with errors that name the file and line.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace turnfit {

/// Parses JSON text; a syntax error becomes EX_DATAERR "name:line: ...".
nlohmann::json parse_json(const std::string& text, const std::string& name);
/// Reads and parses a JSON file ("-" for stdin).
nlohmann::json read_json(const std::string& path);

/// The JSON text of j (compact, or indented by `indent`). Never throws: a string that is not
/// UTF-8 (a coil name from a CSV comment, a map label, an argument) has its bad bytes written
/// as U+FFFD instead of stopping the tool at its last step.
template <class Json>
std::string json_text(const Json& j, int indent = -1) {
  return j.dump(indent, ' ', false, Json::error_handler_t::replace);
}

}  // namespace turnfit
