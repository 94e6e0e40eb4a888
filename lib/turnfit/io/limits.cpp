// Quoting a user's text in messages: short, printable, valid UTF-8, whatever the input held.
#include "turnfit/io/limits.hpp"

#include <algorithm>
#include <cstdio>

namespace turnfit {
namespace {

/// Length of the valid UTF-8 sequence at s[i] (1-4), or 0 if the bytes there are not one
/// (overlong forms, surrogates and code points past U+10FFFF are not).
std::size_t utf8_length(std::string_view s, std::size_t i) {
  const auto b = [&](std::size_t k) { return static_cast<unsigned char>(s[i + k]); };
  const unsigned char c = b(0);
  if (c < 0x80) return 1;
  std::size_t n = 0;
  unsigned lo = 0x80, hi = 0xBF;  // the allowed range of the second byte
  if (c >= 0xC2 && c <= 0xDF) n = 2;
  else if (c >= 0xE0 && c <= 0xEF) {
    n = 3;
    if (c == 0xE0) lo = 0xA0;
    if (c == 0xED) hi = 0x9F;
  } else if (c >= 0xF0 && c <= 0xF4) {
    n = 4;
    if (c == 0xF0) lo = 0x90;
    if (c == 0xF4) hi = 0x8F;
  } else {
    return 0;
  }
  if (i + n > s.size()) return 0;
  if (b(1) < lo || b(1) > hi) return 0;
  for (std::size_t k = 2; k < n; ++k)
    if (b(k) < 0x80 || b(k) > 0xBF) return 0;
  return n;
}

/// Appends s[from, to) with control characters (except those kept) and invalid UTF-8 escaped.
void append_printable(std::string& out, std::string_view s, std::size_t from, std::size_t to, bool keep_newlines) {
  char buf[8];
  for (std::size_t i = from; i < to;) {
    const unsigned char c = static_cast<unsigned char>(s[i]);
    const std::size_t n = utf8_length(s, i);
    const bool control = c < 0x20 || c == 0x7F;
    if (n == 0 || (control && !(keep_newlines && (c == '\n' || c == '\t')))) {
      std::snprintf(buf, sizeof buf, "\\x%02X", c);
      out += buf;
      ++i;
    } else {
      out.append(s.substr(i, n));
      i += n;
    }
  }
}

/// The start of the character at or before i (so a cut never splits a UTF-8 sequence).
std::size_t char_start(std::string_view s, std::size_t i) {
  // At most 3 steps: a UTF-8 sequence has at most 3 continuation bytes (a longer run of them is
  // not UTF-8, and is escaped byte by byte wherever it is cut).
  for (int k = 0; k < 3 && i > 0 && i < s.size() && (static_cast<unsigned char>(s[i]) & 0xC0) == 0x80; ++k) --i;
  return i;
}

}  // namespace

std::string quote(std::string_view text) {
  std::string out = "'";
  const std::size_t cut = char_start(text, std::min(text.size(), limits::kEcho));
  append_printable(out, text, 0, cut, false);
  out += "'";
  if (cut < text.size()) out += "... (" + std::to_string(text.size()) + " bytes)";
  return out;
}

std::string clip_message(std::string_view message) {
  std::string out;
  if (message.size() <= limits::kMessageBytes) {
    append_printable(out, message, 0, message.size(), true);
    return out;
  }
  const std::size_t head = char_start(message, limits::kMessageBytes * 3 / 4);
  const std::size_t tail = char_start(message, message.size() - limits::kMessageBytes / 4);
  append_printable(out, message, 0, head, true);
  out += " [... " + std::to_string(tail - head) + " bytes left out ...] ";
  append_printable(out, message, tail, message.size(), true);
  return out;
}

}  // namespace turnfit
