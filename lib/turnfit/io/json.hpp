// JSON documents read with errors that name the file and line.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace turnfit {

/// Parses JSON text; a syntax error becomes EX_DATAERR "name:line: ...".
nlohmann::json parse_json(const std::string& text, const std::string& name);
/// Reads and parses a JSON file ("-" for stdin).
nlohmann::json read_json(const std::string& path);

}  // namespace turnfit
