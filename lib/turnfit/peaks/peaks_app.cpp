// turnfit-peakfind: the turns of a wire-probe profile as a peaks table.
#include "turnfit/peaks/peaks_app.hpp"

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"

namespace turnfit {

void add_peakfind_options(CLI::App& app, PeakfindOptions& o) {
  app.description(
      "The turns in a probe profile (position_mm,intensity): downward zero-crossings of the smoothed\n"
      "first derivative with thresholds on height, area and slope, then a fit of Gaussian turn shapes\n"
      "that makes positions independent of the reading grid and splits turns that merge, and a refit\n"
      "with an inward tail and equal areas for the positions (the turns' means). Writes\n"
      "probe,turn,r_mm,height,area,width_mm,r_err_mm,flag (r_err_mm: the position's 1-sigma uncertainty, noise\n"
      "and systematic). Thresholds are fractions of the tallest peak (P).");
  app.add_option("profile", o.profile, "Probe profile CSV ('-' for stdin)")->capture_default_str();
  app.add_option("--probe", o.probe, "Probe name (default: the profile's '# probe=', else the file name)");
  app.add_option("--first-turn", o.first_turn, "Number of the first turn (default: the profile's '# first_turn=', else 1)")
      ->check(CLI::Range(1, 1000000000));
  app.add_option("--smooth", o.settings.smooth_mm, "Rms of the Gaussian smoothing [mm] (0: 0.5 mm, at least one step)")
      ->check(CLI::Range(0.0, 1e4))
      ->capture_default_str();
  app.add_option("--min-height", o.settings.min_height, "Smallest smoothed height above the baseline [fraction of P]")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  app.add_option("--min-area", o.settings.min_area, "Smallest area between the flanking minima [P * mm]")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app.add_option("--min-slope", o.settings.min_slope, "Smallest steepest flank of the smoothed profile [P / mm]")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app.add_option("--split-area", o.settings.split_area,
                 "A peak with this many times its neighbours' median area holds several turns (0: off)")
      ->check(CLI::Range(0.0, 100.0))
      ->capture_default_str();
  app.add_flag("--no-split", o.no_split, "Never split a peak of several turns' area (flag it 'wide', count its turns)");
  app.add_option("--gap-ratio", o.settings.gap_ratio,
                 "0: never skip turn numbers; else, in profiles of fewer than 12 peaks, a separation this many "
                 "times the mean one skips turn numbers (12 or more: the separation envelope and model decide)")
      ->check(CLI::Range(0.0, 100.0))
      ->capture_default_str();
  app.add_option("--position", o.position, "Reported position: the fitted centre or the deblended centroid")
      ->check(CLI::IsMember({"fit", "centroid"}))
      ->capture_default_str();
  cli::add_common_options(app, o.common, cli::kOutput | cli::kFormat, {"csv", "json"});
}

namespace {

/// A probe name from a file name: its stem ("runs/RRL.csv" -> "RRL").
std::string stem_of(const std::string& path) {
  if (path.empty() || path == "-") return {};
  return std::filesystem::path(path).stem().string();
}

/// A radius for a message: mm to 0.01 mm.
std::string mm(double r) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.2f", r);
  return buf;
}

bool valid_probe_name(const std::string& s) {
  return !s.empty() && s.find_first_of(",\"\r\n") == std::string::npos;
}

}  // namespace

void warn_numbering_doubts(const cli::CommonOptions& common, const std::string& probe, const std::string& source,
                           const PeakResult& r) {
  constexpr size_t kMaxAmbiguous = 10;
  size_t ambiguous = 0;
  for (const auto& d : r.doubts) {
    const Peak& a = r.peaks[d.first];
    const Peak& b = r.peaks[d.last];
    if (d.kind == NumberingDoubt::kAmbiguousGap) {
      if (++ambiguous > kMaxAmbiguous) continue;
      const int diff = std::abs(d.alternative - d.missing);
      cli::warn(common, probe + " (" + source + "): turn " + std::to_string(a.turn) + " at r = " + mm(a.r_mm) +
                            " mm: the gap before it fits " + std::to_string(d.missing) + " or " +
                            std::to_string(d.alternative) + " missing turns alike; numbered with " +
                            std::to_string(d.missing) + " (flag 'ambiguous'): this and later turn numbers may be " +
                            (d.alternative > d.missing ? "short" : "over") + " by " + std::to_string(diff));
    } else if (d.kind == NumberingDoubt::kGapPlace) {
      const bool later = static_cast<size_t>(d.alternative) > d.first;
      const Peak& other = r.peaks[static_cast<size_t>(d.alternative)];
      cli::warn(common, probe + " (" + source + "): turns " + std::to_string(a.turn) +
                            (d.last > d.first ? "-" + std::to_string(b.turn) : std::string()) + " (r = " +
                            mm(a.r_mm) + (d.last > d.first ? " to " + mm(b.r_mm) : std::string()) +
                            " mm): the " + std::to_string(d.missing) + " missing turn(s) before turn " +
                            std::to_string(later ? a.turn : r.peaks[d.last + 1].turn) +
                            " fit about as well before the peak at r = " +
                            mm(later ? other.r_mm : a.r_mm) + " mm: these numbers may be " +
                            (later ? "over" : "short") + " by " + std::to_string(d.missing) + " (flag 'ambiguous')");
    } else {
      cli::warn(common, probe + " (" + source + "): turns " + std::to_string(a.turn) + "-" + std::to_string(b.turn) +
                            " (r = " + mm(a.r_mm) + " to " + mm(b.r_mm) +
                            " mm) may cross: the betatron oscillation brings turns within 0.15 of their "
                            "trend separation of each other from turn " + std::to_string(a.turn) +
                            " on, and a profile cannot show their order; numbered in order of position (flag 'cross')");
    }
  }
  if (ambiguous > kMaxAmbiguous)
    cli::warn(common, probe + " (" + source + "): " + std::to_string(ambiguous - kMaxAmbiguous) +
                          " more turns after gaps of ambiguous length (flag 'ambiguous')");
}

void write_peaks_csv(std::ostream& os, const std::string& probe, int first_turn, const PeakResult& r,
                     bool provenance) {
  if (provenance) os << cli::provenance_comment();
  int merged = 0, flagged = 0, ambiguous = 0, cross = 0;
  for (const auto& p : r.peaks) {
    merged += (p.flags & kPeakMerged) != 0;
    flagged += p.flags != 0;
    ambiguous += (p.flags & kPeakAmbiguous) != 0;
    cross += (p.flags & kPeakCross) != 0;
  }
  char buf[640];
  std::snprintf(buf, sizeof buf,
                "# probe=%s first_turn=%d peaks=%zu merged=%d flagged=%d skipped_turns=%d ambiguous=%d cross=%d "
                "smooth_mm=%.6g baseline=%.6g%+.6g*(x-x0) noise=%.4g scale=%.6g candidates=%d rejected=%d dropped=%d\n",
                probe.c_str(), first_turn, r.peaks.size(), merged, flagged, r.skipped_turns, ambiguous, cross,
                r.smooth_mm, r.baseline_at0, r.baseline_slope, r.noise, r.scale, r.candidates, r.rejected, r.dropped);
  os << buf << "probe,turn,r_mm,height,area,width_mm,r_err_mm,flag\n";
  for (const auto& p : r.peaks) {
    std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6g,%.6g,%.6f,%.6f,%s\n", probe.c_str(), p.turn, p.r_mm, p.height,
                  p.area, p.width_mm, p.r_err_mm, peak_flag_string(p.flags).c_str());
    os << buf;
  }
}

void write_peaks_json(std::ostream& os, const std::string& probe, int first_turn, const PeakResult& r,
                      bool provenance) {
  using nlohmann::json;
  json doc;
  if (provenance) doc["provenance"] = cli::provenance();
  doc["format"] = "turnfit-peaks/1";
  doc["probe"] = probe;
  doc["first_turn"] = first_turn;
  doc["step_mm"] = r.step_mm;
  doc["smooth_mm"] = r.smooth_mm;
  doc["baseline"] = {{"at_first_reading", r.baseline_at0}, {"slope_per_mm", r.baseline_slope}};
  doc["noise"] = r.noise;
  doc["residual_noise"] = r.residual_noise;
  doc["scale"] = r.scale;
  doc["candidates"] = r.candidates;
  doc["rejected"] = r.rejected;
  doc["dropped"] = r.dropped;
  doc["splits"] = r.splits;
  doc["skipped_turns"] = r.skipped_turns;
  doc["model_judged"] = r.model_judged;
  json doubts = json::array();
  for (const auto& d : r.doubts) {
    const Peak& a = r.peaks[d.first];
    const Peak& b = r.peaks[d.last];
    if (d.kind == NumberingDoubt::kAmbiguousGap)
      doubts.push_back({{"kind", "ambiguous"}, {"turn", a.turn}, {"r_mm", a.r_mm}, {"missing", d.missing},
                        {"alternative", d.alternative}});
    else if (d.kind == NumberingDoubt::kGapPlace)
      doubts.push_back({{"kind", "gap_place"}, {"first_turn", a.turn}, {"last_turn", b.turn}, {"r_first_mm", a.r_mm},
                        {"r_last_mm", b.r_mm}, {"missing", d.missing},
                        {"other_place_r_mm", r.peaks[static_cast<size_t>(d.alternative)].r_mm}});
    else
      doubts.push_back({{"kind", "cross"}, {"first_turn", a.turn}, {"last_turn", b.turn}, {"r_first_mm", a.r_mm},
                        {"r_last_mm", b.r_mm}});
  }
  doc["numbering_doubts"] = doubts;
  json arr = json::array();
  for (const auto& p : r.peaks)
    arr.push_back({{"turn", p.turn},
                   {"r_mm", p.r_mm},
                   {"r_err_mm", p.r_err_mm},
                   {"r_err_stat_mm", p.r_err_stat_mm},
                   {"r_err_sys_mm", p.r_err_sys_mm},
                   {"r_fit_mm", p.r_fit_mm},
                   {"turns", p.turns},
                   {"height", p.height},
                   {"area", p.area},
                   {"width_mm", p.width_mm},
                   {"flag", peak_flag_string(p.flags)}});
  doc["peaks"] = arr;
  os << json_text(doc, 2) << "\n";
}

PeakResult peakfind(const ProbeProfile& profile, const PeakfindOptions& o, std::ostream& os) {
  std::string probe = o.probe;
  if (!probe.empty() && !valid_probe_name(probe))
    throw usage_error("--probe '" + probe + "': a probe name cannot hold a comma, quote or line break");
  if (probe.empty()) {
    probe = profile.probe;
    if (!probe.empty() && !valid_probe_name(probe))
      throw data_error(profile.name, 0, "'# probe=" + probe + "': a probe name cannot hold a comma or quote");
  }
  if (probe.empty()) probe = stem_of(o.profile);
  if (probe.empty() || !valid_probe_name(probe))
    throw usage_error("no probe name: the profile has no '# probe=' line; give --probe NAME");
  const int first = o.first_turn > 0 ? o.first_turn : profile.first_turn > 0 ? profile.first_turn : 1;
  const size_t n = profile.position_mm.size();
  const double step = (profile.position_mm[n - 1] - profile.position_mm[0]) / static_cast<double>(n - 1);
  if (profile.step_mm > 0 && std::abs(profile.step_mm - step) > 0.01 * step)
    cli::warn(o.common, profile.name + ": '# step_mm=" + cli::fmt(profile.step_mm) + "' but the readings are " +
                            cli::fmt(step, 6) + " mm apart (the readings' spacing is used)");
  PeakSettings s = o.settings;
  s.split = !o.no_split;
  s.centroid = o.position == "centroid";
  const PeakResult r = find_peaks(profile.position_mm, profile.intensity, s, first);
  if (r.peaks.empty()) cli::warn(o.common, profile.name + ": no peaks found");
  if (r.skipped_turns > 0)
    cli::warn(o.common, profile.name + ": " + std::to_string(r.skipped_turns) +
                            " turn number(s) skipped at gaps (flag 'gap'; --gap-ratio 0 numbers straight on)");
  warn_numbering_doubts(o.common, probe, profile.name, r);
  if (o.common.format == "json")
    write_peaks_json(os, probe, first, r, !o.common.no_provenance);
  else
    write_peaks_csv(os, probe, first, r, !o.common.no_provenance);
  return r;
}

int run_peakfind(const PeakfindOptions& o) {
  const ProbeProfile profile = read_profile(o.profile.empty() ? std::string("-") : o.profile);
  OutputFile out(o.common.output);
  peakfind(profile, o, out.stream());
  out.commit();
  return 0;
}

}  // namespace turnfit
