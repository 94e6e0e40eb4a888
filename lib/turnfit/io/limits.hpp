// Resource limits of every reader, in one place: hostile or broken input is refused with the
// limit it hit, before it can exhaust memory, the stack or time (turnfit(1), LIMITS).
#pragma once

#include <cstddef>
#include <string>
#include <string_view>

namespace turnfit::limits {

/// Bytes one input (a file or stdin) may hold. Inputs are read whole; this bounds their memory
/// (a JSON document costs about 10 times its text once parsed). The largest real inputs are
/// field maps of a few MB.
constexpr std::size_t kInputBytes = std::size_t(256) << 20;
/// Bytes a population log (turnfit-nsga --resume) may hold: a long run's own checkpoint, records
/// of about 1.5 kB per evaluation, so 2 million evaluations.
constexpr std::size_t kLogBytes = std::size_t(4) << 30;
/// Bytes one line of a line-based format (CSV, maps, logs) may hold.
constexpr std::size_t kLineBytes = std::size_t(1) << 20;
/// Nesting depth of a JSON document (turnfit's own files nest 5 deep).
constexpr int kJsonDepth = 64;
/// Points of a field map grid (ring8: 21060, the PSI Ring's: 141 x 360). A map's spline costs
/// about 200 bytes per point.
constexpr long kGridPoints = 1L << 22;
/// Lines of one line-based input (its line views cost 16 bytes each).
constexpr std::size_t kLines = 20000000;
/// Data rows of one CSV table (a bunch of 10 million particles).
constexpr std::size_t kTableRows = 10000000;
/// Characters of a user's text echoed back in a message.
constexpr std::size_t kEcho = 60;
/// Bytes of a whole error message.
constexpr std::size_t kMessageBytes = 2000;

}  // namespace turnfit::limits

namespace turnfit {

/// A user's text as a message quotes it: 'text', cut to limits::kEcho characters with its full
/// length named, control characters and bytes that are not UTF-8 escaped (\xNN).
std::string quote(std::string_view text);

/// A message made safe to print: control characters other than newline and tab and invalid
/// UTF-8 escaped, and cut in the middle to limits::kMessageBytes with the bytes left out named.
std::string clip_message(std::string_view message);

}  // namespace turnfit
