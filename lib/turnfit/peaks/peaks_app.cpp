// turnfit-peakfind: the turns of a wire-probe profile as a peaks table.
#include "turnfit/peaks/peaks_app.hpp"

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "turnfit/io/error.hpp"
#include "turnfit/io/output.hpp"

namespace turnfit {

void add_peakfind_options(CLI::App& app, PeakfindOptions& o) {
  app.description(
      "The turns in a probe profile (position_mm,intensity): downward zero-crossings of the smoothed\n"
      "first derivative with thresholds on height, area and slope, then a fit of Gaussian turn shapes\n"
      "that makes positions independent of the reading grid and splits turns that merge. Writes\n"
      "probe,turn,r_mm,height,area,width_mm,flag. Thresholds are fractions of the tallest peak (P).");
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
                 "A separation this many times the expected one skips turn numbers (0: never)")
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

bool valid_probe_name(const std::string& s) {
  return !s.empty() && s.find_first_of(",\"\r\n") == std::string::npos;
}

}  // namespace

void write_peaks_csv(std::ostream& os, const std::string& probe, int first_turn, const PeakResult& r,
                     bool provenance) {
  if (provenance) os << cli::provenance_comment();
  int merged = 0, flagged = 0;
  for (const auto& p : r.peaks) {
    merged += (p.flags & kPeakMerged) != 0;
    flagged += p.flags != 0;
  }
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "# probe=%s first_turn=%d peaks=%zu merged=%d flagged=%d skipped_turns=%d smooth_mm=%.6g "
                "baseline=%.6g%+.6g*(x-x0) noise=%.4g scale=%.6g candidates=%d rejected=%d dropped=%d\n",
                probe.c_str(), first_turn, r.peaks.size(), merged, flagged, r.skipped_turns, r.smooth_mm,
                r.baseline_at0, r.baseline_slope, r.noise, r.scale, r.candidates, r.rejected, r.dropped);
  os << buf << "probe,turn,r_mm,height,area,width_mm,flag\n";
  for (const auto& p : r.peaks) {
    std::snprintf(buf, sizeof buf, "%s,%d,%.6f,%.6g,%.6g,%.6f,%s\n", probe.c_str(), p.turn, p.r_mm, p.height, p.area,
                  p.width_mm, peak_flag_string(p.flags).c_str());
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
  doc["scale"] = r.scale;
  doc["candidates"] = r.candidates;
  doc["rejected"] = r.rejected;
  doc["dropped"] = r.dropped;
  doc["splits"] = r.splits;
  doc["skipped_turns"] = r.skipped_turns;
  json arr = json::array();
  for (const auto& p : r.peaks)
    arr.push_back({{"turn", p.turn},
                   {"r_mm", p.r_mm},
                   {"r_err_mm", p.r_err_mm},
                   {"height", p.height},
                   {"area", p.area},
                   {"width_mm", p.width_mm},
                   {"flag", peak_flag_string(p.flags)}});
  doc["peaks"] = arr;
  os << doc.dump(2) << "\n";
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
