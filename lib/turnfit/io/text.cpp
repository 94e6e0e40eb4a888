// Input reading and strict number parsing shared by every reader.
#include "turnfit/io/text.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <sstream>
#include <sys/stat.h>

#include "turnfit/io/error.hpp"

namespace turnfit {

InputText read_input(const std::string& path) {
  InputText in;
  if (path == "-" || path.empty()) {
    in.name = "<stdin>";
    std::ostringstream ss;
    ss << std::cin.rdbuf();
    if (std::cin.bad()) throw Error(ExitCode::io, "<stdin>: read error");
    in.text = ss.str();
    return in;
  }
  in.name = path;
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode)) throw open_error(path, "is a directory");
  std::ifstream f(path, std::ios::binary);
  if (!f) throw open_error(path, std::strerror(errno));
  std::ostringstream ss;
  ss << f.rdbuf();
  if (f.bad()) throw Error(ExitCode::io, path + ": read error");
  in.text = ss.str();
  return in;
}

std::vector<std::string_view> split_lines(std::string_view text) {
  std::vector<std::string_view> lines;
  size_t pos = 0;
  while (pos < text.size()) {
    size_t nl = text.find('\n', pos);
    size_t end = nl == std::string_view::npos ? text.size() : nl;
    std::string_view line = text.substr(pos, end - pos);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    lines.push_back(line);
    if (nl == std::string_view::npos) break;
    pos = nl + 1;
  }
  return lines;
}

std::string_view trim(std::string_view s) {
  const char* blanks = " \t\r\n";
  size_t b = s.find_first_not_of(blanks);
  if (b == std::string_view::npos) return {};
  size_t e = s.find_last_not_of(blanks);
  return s.substr(b, e - b + 1);
}

double parse_double(std::string_view token, const std::string& file, long line,
                    const std::string& what) {
  std::string t(trim(token));
  if (t.empty()) throw data_error(file, line, what + ": empty field where a number is expected");
  errno = 0;
  char* end = nullptr;
  double v = std::strtod(t.c_str(), &end);
  if (end != t.c_str() + t.size())
    throw data_error(file, line, what + ": '" + t + "' is not a number");
  if (!std::isfinite(v))
    throw data_error(file, line, what + ": '" + t + "' is not a finite number");
  return v;
}

long parse_long(std::string_view token, const std::string& file, long line,
                const std::string& what) {
  std::string t(trim(token));
  errno = 0;
  char* end = nullptr;
  long v = t.empty() ? 0 : std::strtol(t.c_str(), &end, 10);
  if (t.empty() || end != t.c_str() + t.size() || errno == ERANGE)
    throw data_error(file, line, what + ": '" + t + "' is not an integer");
  return v;
}

std::vector<std::string_view> split_fields(std::string_view line, char sep) {
  std::vector<std::string_view> out;
  size_t pos = 0;
  while (true) {
    size_t p = line.find(sep, pos);
    out.push_back(trim(line.substr(pos, p == std::string_view::npos ? std::string_view::npos : p - pos)));
    if (p == std::string_view::npos) break;
    pos = p + 1;
  }
  return out;
}

std::vector<std::string_view> split_blanks(std::string_view line) {
  std::vector<std::string_view> out;
  size_t pos = 0;
  while (pos < line.size()) {
    size_t b = line.find_first_not_of(" \t\r", pos);
    if (b == std::string_view::npos) break;
    size_t e = line.find_first_of(" \t\r", b);
    if (e == std::string_view::npos) e = line.size();
    out.push_back(line.substr(b, e - b));
    pos = e;
  }
  return out;
}

size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diag = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diag + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diag = up;
    }
  }
  return row[b.size()];
}

std::string format_exact(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

}  // namespace turnfit
