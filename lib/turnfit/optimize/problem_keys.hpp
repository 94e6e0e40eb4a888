// Reading a problem file's keys with errors that name the file and the key (both kinds of
// turnfit-problem/1 file: command problems and turn-pattern problems).
#pragma once

#include <cmath>
#include <nlohmann/json.hpp>
#include <string>

#include "turnfit/io/error.hpp"

namespace turnfit {

/// A problem file's keys; every error is EX_DATAERR "file: key/path: what".
struct ProblemKeys {
  std::string file;  ///< the file's name in messages
  /// Fails naming `key` (a path through the document, as variables/2/upper).
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw data_error(file, 0, key + ": " + what);
  }
  /// obj[key], or an error naming where/key as missing.
  const nlohmann::json& need(const nlohmann::json& obj, const std::string& key, const std::string& where) const {
    auto it = obj.find(key);
    if (it == obj.end()) fail(where.empty() ? key : where + "/" + key, "missing");
    return *it;
  }
  /// A finite number.
  double number(const nlohmann::json& v, const std::string& where) const {
    if (!v.is_number() || !std::isfinite(v.get<double>())) fail(where, "expected a finite number");
    return v.get<double>();
  }
  /// A non-empty string.
  std::string text(const nlohmann::json& v, const std::string& where) const {
    if (!v.is_string() || v.get<std::string>().empty()) fail(where, "expected a non-empty string");
    return v.get<std::string>();
  }
};

}  // namespace turnfit
