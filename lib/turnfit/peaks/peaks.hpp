// Turns in a wire-probe profile: the paper's derivative detector, then a fit that splits merged turns.
#pragma once

#include <string>
#include <vector>

namespace turnfit {

/// A probe profile: readings along the probe with the metadata of its '#' lines.
struct ProbeProfile {
  std::string name;                  ///< input name, for messages
  std::vector<double> position_mm;   ///< strictly increasing, evenly spaced
  std::vector<double> intensity;     ///< any scale (normalized readings or counts)
  std::vector<long> line;            ///< source line of each reading (for messages)
  std::string probe;                 ///< metadata `probe=` (empty if absent)
  double step_mm = 0;                ///< metadata `step_mm=` (0 if absent)
  int first_turn = 0;                ///< metadata `first_turn=` (0 if absent)
};

/// Parses a profile CSV (columns position_mm,intensity; '#' lines carry `key=value` metadata).
/// EX_DATAERR naming file and line for a missing column, a bad number, positions that do not
/// increase or are not evenly spaced (within 1% of the mean step), or fewer than 5 readings.
ProbeProfile parse_profile(const std::string& text, const std::string& name);
/// Reads a profile from a file ("-" for stdin); see parse_profile.
ProbeProfile read_profile(const std::string& path);

/// Detector and fit settings. Thresholds are relative to the profile's tallest peak above the
/// baseline (P), so one setting serves normalized readings and histogram counts alike.
struct PeakSettings {
  double smooth_mm = 0;        ///< rms of the Gaussian smoothing (0: 0.5 mm, at least one step)
  double min_height = 0.01;    ///< smoothed height above baseline, fraction of P
  double min_area = 0.01;      ///< area above baseline between the flanking minima, in P * mm
  double min_slope = 0.002;    ///< steepest smoothed flank, in P per mm
  bool split = true;           ///< fit k turns into a peak of k turns' area (else flag it wide)
  double split_area = 1.5;     ///< a peak with this many times its neighbours' area holds more than one turn (0: never split)
  double gap_ratio = 1.8;      ///< 0: never skip turn numbers; else, under 12 peaks, this many mean separations skip numbers
  bool centroid = true;        ///< report the deblended centroid (false: the fitted centre)
};

/// Why a peak is less certain than a clean, isolated turn (bit flags; none means "ok").
enum PeakFlag : unsigned {
  kPeakMerged = 1u << 0,  ///< one of k turns split by the fit from a peak of k turns' area
  kPeakWide = 1u << 1,    ///< holds k turns' area but the fit could not separate them (counts as k turns)
  kPeakWeak = 1u << 2,    ///< small: below 2x the height threshold or half its neighbours' area
  kPeakGap = 1u << 3,     ///< first peak after a gap of about n expected separations (n-1 turns skipped)
  kPeakEdge = 1u << 4,    ///< within 3 widths of the end of the profile (partly outside)
  kPeakAmbiguous = 1u << 5,  ///< after a gap whose count (or place) of missing turns the data cannot decide
  kPeakCross = 1u << 6,      ///< from where turns first touch (0.15 trend separations) on: they may cross
};

/// "ok", or the flags' names joined by '+' (merged, wide, weak, gap, edge, ambiguous, cross).
std::string peak_flag_string(unsigned flags);

/// One detected turn.
struct Peak {
  int turn = 0;           ///< turn number (first turn + turns before it, plus numbers skipped at gaps)
  double r_mm = 0;        ///< position on the profile's position axis (see turnfit-peakfind(1))
  double r_err_mm = 0;    ///< total 1-sigma of r_mm: statistical and systematic parts (turnfit-peakfind(1), UNCERTAINTY)
  double r_err_stat_mm = 0;  ///< statistical 1-sigma of r_mm (the readings' noise only)
  double r_err_sys_mm = 0;   ///< systematic 1-sigma of r_mm (shape, overlap with neighbours, flags)
  double r_fit_mm = 0;    ///< the fitted Gaussian centre (r_mm is the deblended centroid unless --position fit)
  int turns = 1;          ///< turns this row stands for (more than 1 only for a wide peak)
  double height = 0;      ///< fitted amplitude above the baseline (intensity units)
  double area = 0;        ///< fitted area above the baseline (intensity * mm)
  double width_mm = 0;    ///< fitted rms width
  unsigned flags = 0;     ///< PeakFlag bits
};

/// A place where the turn numbering cannot be trusted (turnfit-peakfind(1), "Numbering").
struct NumberingDoubt {
  enum Kind {
    kAmbiguousGap,  ///< the gap before peak `first` fits `missing` or `alternative` missing turns alike
    kGapPlace,      ///< a gap of `missing` turns fits as well elsewhere: peaks first-last may be off by that
    kCross,         ///< peaks first-last: turns may cross (the numbering follows position)
  };
  Kind kind = kAmbiguousGap;
  size_t first = 0;     ///< index into PeakResult::peaks of the first peak concerned
  size_t last = 0;      ///< ... and of the last (inclusive)
  int missing = 0;      ///< kAmbiguousGap: turns taken as missing before peak `first`; kGapPlace: the gap's count
  int alternative = 0;  ///< kAmbiguousGap: the count that fits as well; kGapPlace: the peak after the other place
};

/// What a run found, with the numbers that explain it.
struct PeakResult {
  std::vector<Peak> peaks;       ///< in order of increasing position
  double step_mm = 0;            ///< reading spacing
  double smooth_mm = 0;          ///< smoothing used
  double baseline_at0 = 0;       ///< baseline at the first reading
  double baseline_slope = 0;     ///< baseline slope per mm
  double noise = 0;              ///< rms noise of one reading (robust estimate, for the detector's thresholds)
  double residual_noise = 0;     ///< rms noise of one reading left by the fit (for r_err_stat_mm; UNCERTAINTY)
  double scale = 0;              ///< P: tallest smoothed peak above the baseline
  int candidates = 0;            ///< downward zero-crossings of the smoothed derivative
  int rejected = 0;              ///< candidates below a threshold or without prominence
  int dropped = 0;               ///< accepted candidates that the fit reduced to nothing
  int splits = 0;                ///< peaks split into k turns by the fit
  int skipped_turns = 0;         ///< turn numbers skipped at gaps
  int model_judged = 0;          ///< intervals the position model had to judge (the envelope decided the rest)
  std::vector<NumberingDoubt> doubts;  ///< where the numbering cannot be trusted, in order of position
};

/// Finds the turns of a profile (turnfit-peakfind(1), ALGORITHM): baseline, smoothed derivative
/// zero-crossings with thresholds (the paper, Sec. "Peak detection of probe measurement"), a fit of
/// Gaussian turn shapes (Levenberg-Marquardt) for grid-independent positions, splitting of wide
/// peaks by the neighbours' width and separation, a refit of turn shapes with an inward tail and
/// the area every turn shares for the reported positions (the turns' means, turnfit-peakfind(1),
/// "Position reported"), then flags and turn numbers: a turn is missing
/// only where the envelope of the oscillating separations and a model of position against turn
/// (trend plus betatron oscillation) say so; doubts (ambiguous gaps, turns that may cross) are
/// flagged and listed in `doubts`.
/// EX_DATAERR if x and y differ in size, hold fewer than 5 readings or x is not increasing.
PeakResult find_peaks(const std::vector<double>& x_mm, const std::vector<double>& y,
                      const PeakSettings& settings, int first_turn);

}  // namespace turnfit
