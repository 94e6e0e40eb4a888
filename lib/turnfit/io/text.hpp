// Reading whole inputs (files or stdin) and strict number parsing with file:line errors.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "turnfit/io/limits.hpp"

namespace turnfit {

/// The text of one input, with the name used in messages ("<stdin>" for "-").
struct InputText {
  std::string name;  ///< path as the user gave it, or "<stdin>"
  std::string text;  ///< whole content
};

/// Reads a file, or stdin when path is "-" (EX_NOINPUT if it cannot be opened,
/// EX_IOERR if reading fails, EX_DATAERR past max_bytes: limits::kInputBytes by default).
InputText read_input(const std::string& path, std::size_t max_bytes = limits::kInputBytes);

/// Splits text into lines (without "\n" or a trailing "\r").
std::vector<std::string_view> split_lines(std::string_view text);
/// The same for a line-based input: EX_DATAERR "name:line: ..." for a line longer than
/// limits::kLineBytes.
std::vector<std::string_view> split_lines(std::string_view text, const std::string& name);

/// Removes leading and trailing blanks (spaces, tabs, CR).
std::string_view trim(std::string_view s);

/// Whether t is a decimal number as turnfit's formats write them: [+-]digits[.digits][e[+-]digits]
/// (or .digits). Hex floats, "inf", "nan", blanks and anything after the number are not.
bool is_decimal(std::string_view t);

/// A decimal number (is_decimal) that is finite as a double into out; false otherwise.
bool parse_decimal(std::string_view token, double& out);

/// Parses a finite decimal number (is_decimal; blanks around it are trimmed); otherwise
/// EX_DATAERR "file:line: <what>: 'token' is not a number" (NaN, Inf and hex floats too).
double parse_double(std::string_view token, const std::string& file, long line,
                    const std::string& what);

/// Parses a whole-token integer, with the same error shape as parse_double.
long parse_long(std::string_view token, const std::string& file, long line,
                const std::string& what);

/// Splits on a single-character separator, trimming each field.
std::vector<std::string_view> split_fields(std::string_view line, char sep);

/// Splits on runs of blanks.
std::vector<std::string_view> split_blanks(std::string_view line);

/// Levenshtein distance, for "did you mean" hints on misspelt names.
size_t edit_distance(const std::string& a, const std::string& b);

/// Formats a double so that reading it back gives the same value (%.17g).
std::string format_exact(double v);

}  // namespace turnfit
