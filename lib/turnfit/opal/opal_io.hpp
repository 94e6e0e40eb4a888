// OPAL-cycl inputs to turnfit machines and back (turnfit-import-opal, turnfit-export-opal).
#pragma once

#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/cli/common.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/opal/opal_input.hpp"

namespace turnfit {

/// The OPAL version an import reads as by default (OPALVERSION of 2022.1.0).
constexpr double kDefaultOpalVersion = 20220100;

/// What an import gives: the machine document (paths relative to `out_dir`) and the remarks
/// about the input (every line read but not used, with the reason; unexplained ones too).
struct OpalImport {
  nlohmann::json machine;
  std::vector<opal::Note> notes;
  bool from_annotation = false;  ///< the turnfit annotation of an export restored the machine
  std::map<std::string, long> lines;  ///< JSON pointer of the machine -> the input line it came from
  long annotation_line = 0;           ///< first line of the annotation used (0: none)
  std::vector<std::string> restored;  ///< sections the annotation restored
};

/// Reads OPAL-cycl input text. `name` is used in messages, `in_dir` resolves its file names
/// (FMAPFN, FNAME: OPAL reads them from the folder it runs in, taken as the input's), and the
/// machine's paths are written relative to `out_dir` (the folder of the machine file; "" for
/// the current folder). Errors are EX_DATAERR naming the line and token; a missing map or
/// profile file is one too (check_files = false: an export checking its own text before the
/// files it names are written).
OpalImport import_opal(const std::string& text, const std::string& name, const std::string& in_dir,
                       const std::string& out_dir, double opal_version = kDefaultOpalVersion,
                       bool check_files = true);

/// The machine of an import, loaded (turnfit-machine(5)); a refusal is EX_DATAERR naming the
/// input line the refused value came from (its command, or the annotation).
Machine validate_import(const OpalImport& r, const std::string& name, const std::string& out_dir);

/// Options of turnfit-export-opal.
struct ExportOpalOptions {
  std::string map_out;   ///< write the main field here in OPAL's RING format (needed for turnfit-format maps)
  std::string dist_out;  ///< write the one-particle FROMFILE distribution here
};

/// The OPAL-cycl input of a machine, for a file in folder `out_dir` ("" the current folder).
/// `warnings` receives what OPAL will not do as turnfit does (effects, sector lists, ...).
/// `map_file` / `dist_file`: the names the input uses for them (relative to out_dir).
std::string export_opal(const Machine& m, const std::string& out_dir, const std::string& map_file,
                        const std::string& dist_file, std::vector<std::string>& warnings);

/// Options of turnfit-import-opal.
struct ImportOpalOptions {
  std::string input;                      ///< OPAL input file ('-' for stdin)
  cli::CommonOptions common;
  bool strict = false;                    ///< anything not understood is an error
  std::string opal_version = "2022.1";
};

/// Adds turnfit-import-opal's options to app.
void add_import_opal_options(CLI::App& app, ImportOpalOptions& o);
/// Runs turnfit-import-opal; returns the exit code.
int run_import_opal(const ImportOpalOptions& o);

/// Options of turnfit-export-opal (machine, --set/--dvars, outputs).
struct ExportOpalCliOptions {
  std::string machine;                ///< machine file ('-' for stdin)
  std::vector<std::string> sets;      ///< --set NAME=VALUE
  std::string dvars;                  ///< --dvars FILE
  ExportOpalOptions files;
  cli::CommonOptions common;
};

/// Adds turnfit-export-opal's options to app.
void add_export_opal_options(CLI::App& app, ExportOpalCliOptions& o);
/// Runs turnfit-export-opal; returns the exit code.
int run_export_opal(const ExportOpalCliOptions& o);

}  // namespace turnfit
