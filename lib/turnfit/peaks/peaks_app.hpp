// turnfit-peakfind as a library function: options, run, the peaks table it writes.
#pragma once

#include <CLI/CLI.hpp>
#include <ostream>
#include <string>

#include "turnfit/cli/common.hpp"
#include "turnfit/peaks/peaks.hpp"

namespace turnfit {

/// Everything turnfit-peakfind is asked to do.
struct PeakfindOptions {
  cli::CommonOptions common;
  std::string profile = "-";   ///< input profile ("-" for stdin)
  std::string probe;           ///< empty: the profile's `probe=`, else the file name's stem
  int first_turn = 0;          ///< 0: the profile's `first_turn=`, else 1
  PeakSettings settings;
  bool no_split = false;       ///< --no-split
  std::string position = "centroid";  ///< centroid or fit
};

/// Registers turnfit-peakfind's options.
void add_peakfind_options(CLI::App& app, PeakfindOptions& o);

/// Finds the peaks of a parsed profile with the options' settings and writes them to os in
/// the options' format (csv or json). Returns the result (for tests and summaries).
PeakResult peakfind(const ProbeProfile& profile, const PeakfindOptions& o, std::ostream& os);

/// Runs turnfit-peakfind: reads the profile, writes the peaks atomically; returns the exit code.
int run_peakfind(const PeakfindOptions& o);

/// Warns on stderr (unless quiet) where the turn numbering cannot be trusted: each turn after a
/// gap of ambiguous length (the first ten), and each run of turns that may cross; naming the
/// probe, the input, the turn and its radius.
void warn_numbering_doubts(const cli::CommonOptions& common, const std::string& probe, const std::string& source,
                           const PeakResult& r);

/// Writes peaks as CSV: probe,turn,r_mm,height,area,width_mm,r_err_mm,flag (architecture.md's peaks
/// table plus the total position uncertainty and the flag), after '#' provenance and a '#' summary line.
void write_peaks_csv(std::ostream& os, const std::string& probe, int first_turn, const PeakResult& r,
                     bool provenance);

/// Writes peaks as one JSON document (the summary; per peak also r_err_mm, the CSV's, and its parts).
void write_peaks_json(std::ostream& os, const std::string& probe, int first_turn, const PeakResult& r,
                      bool provenance);

}  // namespace turnfit
