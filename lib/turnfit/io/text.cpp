// Input reading and strict number parsing shared by every reader.
#include "turnfit/io/text.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <sstream>
#include <sys/stat.h>

#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"

namespace turnfit {

namespace {

/// Reads a stream to its end, refusing more than max_bytes (an endless pipe, /dev/zero, a
/// mistaken multi-GB file) before holding it all.
std::string read_bounded(std::istream& in, const std::string& name, std::size_t max_bytes) {
  std::string text;
  char buf[1 << 16];
  while (in) {
    in.read(buf, sizeof buf);
    const auto got = static_cast<std::size_t>(in.gcount());
    if (text.size() + got > max_bytes)
      throw data_error(name, 0, "input larger than " + std::to_string(max_bytes >> 20) +
                                    " MiB: refused (the limit of one input)");
    text.append(buf, got);
  }
  if (in.bad()) throw Error(ExitCode::io, name + ": read error");
  return text;
}

}  // namespace

InputText read_input(const std::string& path, std::size_t max_bytes) {
  InputText in;
  if (path == "-" || path.empty()) {
    in.name = "<stdin>";
    in.text = read_bounded(std::cin, in.name, max_bytes);
    return in;
  }
  in.name = path;
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0) {
    if (S_ISDIR(st.st_mode)) throw open_error(path, "is a directory");
    if (S_ISREG(st.st_mode) && static_cast<std::uint64_t>(st.st_size) > max_bytes)
      throw data_error(path, 0, "file of " + std::to_string(st.st_size >> 20) + " MiB: larger than the " +
                                    std::to_string(max_bytes >> 20) + " MiB one input may hold");
  }
  std::ifstream f(path, std::ios::binary);
  if (!f) throw open_error(path, std::strerror(errno));
  in.text = read_bounded(f, path, max_bytes);
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

std::vector<std::string_view> split_lines(std::string_view text, const std::string& name) {
  // Counted before the views are built (16 bytes each: 256 MiB of newlines would take 4 GiB).
  const auto count = static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n'));
  if (count > limits::kLines)
    throw data_error(name, 0, std::to_string(count) + " lines: more than the " + std::to_string(limits::kLines) +
                                  " lines one input may hold");
  std::vector<std::string_view> lines = split_lines(text);
  for (std::size_t i = 0; i < lines.size(); ++i)
    if (lines[i].size() > limits::kLineBytes)
      throw data_error(name, static_cast<long>(i + 1), "line of " + std::to_string(lines[i].size()) +
                                                           " bytes: longer than the " +
                                                           std::to_string(limits::kLineBytes >> 10) +
                                                           " kB a line may hold");
  return lines;
}

std::string_view trim(std::string_view s) {
  const char* blanks = " \t\r\n";
  size_t b = s.find_first_not_of(blanks);
  if (b == std::string_view::npos) return {};
  size_t e = s.find_last_not_of(blanks);
  return s.substr(b, e - b + 1);
}

bool is_decimal(std::string_view t) {
  std::size_t i = 0;
  const auto digits = [&] {
    const std::size_t from = i;
    while (i < t.size() && t[i] >= '0' && t[i] <= '9') ++i;
    return i - from;
  };
  if (i < t.size() && (t[i] == '+' || t[i] == '-')) ++i;
  std::size_t mantissa = digits();
  if (i < t.size() && t[i] == '.') {
    ++i;
    mantissa += digits();
  }
  if (mantissa == 0) return false;
  if (i < t.size() && (t[i] == 'e' || t[i] == 'E')) {
    ++i;
    if (i < t.size() && (t[i] == '+' || t[i] == '-')) ++i;
    if (digits() == 0) return false;
  }
  return i == t.size();
}

bool parse_decimal(std::string_view token, double& out) {
  if (!is_decimal(token)) return false;
  const std::string t(token);
  out = std::strtod(t.c_str(), nullptr);
  return std::isfinite(out);
}

double parse_double(std::string_view token, const std::string& file, long line,
                    const std::string& what) {
  const std::string_view t = trim(token);
  if (t.empty()) throw data_error(file, line, what + ": empty field where a number is expected");
  double v = 0;
  if (parse_decimal(t, v)) return v;
  std::string word(t.substr(t[0] == '+' || t[0] == '-'));
  for (char& c : word) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (word == "nan" || word == "inf" || word == "infinity")
    throw data_error(file, line, what + ": " + quote(t) + " is not a finite number");
  if (!is_decimal(t)) throw data_error(file, line, what + ": " + quote(t) + " is not a number");
  throw data_error(file, line, what + ": " + quote(t) + " is not a finite number (out of range of a double)");
}

long parse_long(std::string_view token, const std::string& file, long line,
                const std::string& what) {
  const std::string t(trim(token));
  const std::size_t sign = !t.empty() && (t[0] == '+' || t[0] == '-');
  const bool digits = t.size() > sign && t.find_first_not_of("0123456789", sign) == std::string::npos;
  errno = 0;
  const long v = digits ? std::strtol(t.c_str(), nullptr, 10) : 0;
  if (!digits || errno == ERANGE) throw data_error(file, line, what + ": " + quote(t) + " is not an integer");
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
