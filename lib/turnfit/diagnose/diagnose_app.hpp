// turnfit-diagnose as a library: options, the diagnosis of a turn-pattern problem, and its
// outputs (JSON report turnfit-diagnosis/1, Markdown, the machine with the effects, figures).
#pragma once

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <string>

#include "turnfit/cli/common.hpp"
#include "turnfit/diagnose/current_dependence.hpp"
#include "turnfit/diagnose/diagnose.hpp"

namespace turnfit {

/// Everything turnfit-diagnose is asked to do.
struct DiagnoseOptions {
  cli::CommonOptions common;  ///< -o: the JSON report; --threads, -q
  std::string problem;        ///< the turn-pattern problem file
  std::string start;          ///< --start: dvars file, nsga front or population log
  std::string pick = "linf";
  std::string effects = "all";  ///< --effects: all or a comma list of types
  std::string markdown;       ///< --markdown: report for people
  std::string machine_out;    ///< --machine-out: the machine with the effects and the fitted variables
  std::string figures;        ///< --figures: folder for the figures
  std::string scan_noise;     ///< --scan-noise DRIVE_MM[,CORR_MM]: the probe drive's correlated error (overrides the problem's)
  std::string weak_prior_centre = "machine";  ///< --weak-prior-centre start|machine (DiagnoseSettings::weak_prior_at_machine)
  DiagnoseSettings settings;
  /// --measured-at I=PEAKS (repeatable): the same machine measured at beam current I; two or
  /// more make space charge a candidate (current_dependence.hpp).
  std::vector<std::string> measured_at;
  int sc_particles = 2000;    ///< --sc-particles: the bunch the signature tracks
  std::string sc_grid = "16";  ///< --sc-grid: its solver grid
};

/// Registers turnfit-diagnose's options.
void add_diagnose_options(CLI::App& app, DiagnoseOptions& o);

/// The effect types an --effects value names ("all": empty, every type). EX_USAGE for an
/// unknown type, naming the known ones.
std::vector<std::string> parse_effect_types(const std::string& spec);

/// The report (turnfit-diagnosis/1) of a diagnosis.
nlohmann::json diagnosis_report(const TurnPatternProblem& p, const Diagnosis& d, const std::string& start,
                                bool provenance);

/// The Markdown report for people.
std::string diagnosis_markdown(const TurnPatternProblem& p, const nlohmann::json& report);

/// A machine document written to `out_path`: its relative file paths (field map, voltage
/// profiles, trim coil tables, bunch file), which resolve from `from_dir`, rewritten to resolve
/// from out_path's folder.
nlohmann::json relocate_machine_paths(nlohmann::json doc, const std::string& from_dir, const std::string& out_path);

/// Runs turnfit-diagnose; returns the exit code.
int run_diagnose(const DiagnoseOptions& o);

}  // namespace turnfit
