// turnfit-import-opal and turnfit-export-opal: options and runs.
#include <filesystem>
#include <iostream>
#include <memory>
#include <sstream>

#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/opal/annotation.hpp"
#include "turnfit/opal/opal_io.hpp"

namespace turnfit {
namespace {

namespace fs = std::filesystem;

// A path as the file system resolves it (symbolic links followed), for comparing outputs with inputs.
std::string canonical_path(const std::string& p) {
  std::error_code ec;
  const fs::path c = fs::weakly_canonical(fs::absolute(p), ec);
  return ec ? fs::absolute(p).lexically_normal().string() : c.string();  // a pipe's /dev/stdout has no path
}

// Whether an output path is a regular file (or not there yet): not a device, FIFO or folder.
bool regular_or_new(const std::string& p) {
  std::error_code ec;
  const auto st = fs::status(p, ec);
  return ec || !fs::exists(st) || fs::is_regular_file(st);
}

// The files a machine reads (its map, profiles, coil tables, bunch file), which no output may replace.
std::vector<std::string> files_read(const Machine& m) {
  std::vector<std::string> out = {m.field.map};
  for (const auto& c : m.cavities) out.push_back(c.profile);
  for (const auto& t : m.trimcoils) out.push_back(t.table);
  if (m.bunch) out.push_back(m.bunch->file);
  return out;
}

// The folder a file is written to or read from ("" for stdin/stdout: the current folder).
std::string folder_of(const std::string& path) {
  if (path.empty() || path == "-") return {};
  return fs::path(path).parent_path().string();
}

// The machine as people read it: sections in turnfit-machine(5)'s order, each element's name
// and type first (nlohmann's objects sort their keys).
nlohmann::ordered_json in_reading_order(const nlohmann::json& m) {
  auto element = [](const nlohmann::json& e) {
    nlohmann::ordered_json o = nlohmann::ordered_json::object();
    if (!e.is_object()) return nlohmann::ordered_json(e);
    for (const char* k : {"name", "type"})
      if (e.contains(k)) o[k] = e[k];
    for (const auto& it : e.items())
      if (!o.contains(it.key())) o[it.key()] = it.value();
    return o;
  };
  nlohmann::ordered_json out = nlohmann::ordered_json::object();
  for (const char* k : {"format", "name", "description", "particle", "field", "rf", "cavities", "trimcoils", "probes",
                        "injection", "bunch", "space_charge", "tracking", "effects", "dvars"}) {
    if (!m.contains(k)) continue;
    if (m[k].is_array() && std::string(k) != "effects") {
      nlohmann::ordered_json a = nlohmann::ordered_json::array();
      for (const auto& e : m[k]) a.push_back(element(e));
      out[k] = a;
    } else {
      out[k] = m[k];
    }
  }
  for (const auto& it : m.items())
    if (!out.contains(it.key())) out[it.key()] = it.value();
  return out;
}

}  // namespace

void add_import_opal_options(CLI::App& app, ImportOpalOptions& o) {
  app.description(
      "Reads an OPAL-cycl input (CYCLOTRON, RFCAVITY, TRIMCOIL, PROBE, BEAM, LINE, TRACK/RUN, variables\n"
      "and IF blocks) and writes the turnfit machine it describes. Every line read but not used is\n"
      "listed on stderr with the reason; lines it does not understand are marked 'not understood'.");
  app.add_option("input", o.input, "OPAL input file ('-' for stdin)")->required();
  app.add_flag("--strict", o.strict, "Anything not understood is an error (exit 65), not a warning");
  app.add_option("--opal-version", o.opal_version,
                 "OPAL version the input is read as: OPALVERSION in IF conditions and the trim coils' azimuth "
                 "window (default 2022.1)");
  cli::add_common_options(app, o.common, cli::kOutput);
}

int run_import_opal(const ImportOpalOptions& o) {
  const double version = opal::parse_opal_version(o.opal_version);
  const InputText in = read_input(o.input);
  const std::string out_dir = folder_of(o.common.output);
  OpalImport r = import_opal(in.text, in.name, folder_of(o.input), out_dir, version);
  const opal::Note* first_unexplained = nullptr;
  size_t unexplained = 0;
  for (const auto& n : r.notes) {
    if (!n.explained) {
      ++unexplained;
      if (!first_unexplained) first_unexplained = &n;
    }
    if (!o.common.quiet || (!n.explained && !o.strict))
      std::cerr << "turnfit-import-opal: " << clip_message(in.name + ":" + std::to_string(n.line) + ": " +
                                                           (n.explained ? "note: " : "warning: ") + n.text)
                << "\n";
  }
  if (o.strict && first_unexplained)
    throw data_error(in.name, first_unexplained->line,
                     first_unexplained->text + " (--strict; " + std::to_string(unexplained) + " line" +
                         (unexplained == 1 ? "" : "s") + " not understood in all)");
  const Machine machine = validate_import(r, in.name, out_dir);
  // The machine must not land on a file it or the import reads (the input, its map, ...).
  if (o.common.output != "-") {
    const std::string out = canonical_path(o.common.output);
    std::vector<std::string> reads = files_read(machine);
    if (o.input != "-") reads.push_back(o.input);
    for (const auto& p : reads)
      if (!p.empty() && canonical_path(p) == out)
        throw usage_error("-o " + quote(o.common.output) + " is a file the import reads: it would be overwritten");
  }
  write_output(o.common.output, json_text(in_reading_order(r.machine), 1) + "\n");
  return 0;
}

void add_export_opal_options(CLI::App& app, ExportOpalCliOptions& o) {
  app.description(
      "Writes a turnfit machine as an OPAL-cycl input: field map, cavities, trim coils, probes,\n"
      "injection and the tracking block, for OPAL 2022.1. A fit applies with --set or --dvars first.\n"
      "What OPAL cannot express travels in comment lines that turnfit-import-opal reads back.");
  app.add_option("machine", o.machine, "Machine file ('-' for stdin)")->required();
  app.add_option("--set", o.sets, "Set a design variable or JSON pointer first: NAME=VALUE (repeatable)")
      ->allow_extra_args(false);
  app.add_option("--dvars", o.dvars, "JSON file of design-variable values to apply first (e.g. a fit's best.json)");
  app.add_option("--map-out", o.files.map_out,
                 "Also write the main field in OPAL's RING format to this file and use it (needed for turnfit-format maps)");
  app.add_option("--dist-out", o.files.dist_out,
                 "Write OPAL's one-particle FROMFILE distribution here (default: <output stem>-dist.dat beside "
                 "the output; for stdout the input names dist1.dat, which you provide)");
  cli::add_common_options(app, o.common, cli::kOutput);
}

int run_export_opal(const ExportOpalCliOptions& o) {
  if ((o.machine == "-") + (o.dvars == "-") > 1) throw usage_error("only one input can be stdin (machine, --dvars)");
  for (const std::string* f : {&o.files.map_out, &o.files.dist_out})
    if (*f == "-") throw usage_error("--map-out and --dist-out need a file name ('-' is the input's output)");
  Machine m = load_machine(o.machine);
  if (!o.sets.empty()) apply_sets(m, o.sets);
  if (!o.dvars.empty()) apply_dvars_file(m, o.dvars);
  const bool to_file = o.common.output != "-" && regular_or_new(o.common.output);
  for (const auto& [opt, f] : {std::pair<const char*, const std::string&>{"--map-out", o.files.map_out},
                               {"--dist-out", o.files.dist_out}})
    if (!f.empty() && !regular_or_new(f))
      throw usage_error(std::string(opt) + " " + quote(f) + " must be a regular file (OPAL reads it by name)");
  const std::string out_dir = folder_of(o.common.output);
  // The distribution: as asked, else beside a file output (<stem>-dist.dat), else named only.
  std::string dist_out = o.files.dist_out;
  if (dist_out.empty() && to_file)
    dist_out = (fs::path(o.common.output).parent_path() / (fs::path(o.common.output).stem().string() + "-dist.dat")).string();
  // No output may land on another output or on a file the machine reads (a measured map
  // overwritten by its 9-digit copy would be lost without a word).
  std::vector<std::pair<std::string, std::string>> outs;
  if (to_file) outs.push_back({"-o", o.common.output});
  else if (o.common.output == "-" && fs::exists("/dev/stdout")) outs.push_back({"-o", "/dev/stdout"});  // where stdout goes
  if (!o.files.map_out.empty()) outs.push_back({"--map-out", o.files.map_out});
  if (!dist_out.empty()) outs.push_back({o.files.dist_out.empty() ? "the distribution file" : "--dist-out", dist_out});
  std::vector<std::string> inputs = files_read(m);
  if (o.machine != "-") inputs.push_back(o.machine);
  if (!o.dvars.empty() && o.dvars != "-") inputs.push_back(o.dvars);
  for (size_t i = 0; i < outs.size(); ++i) {
    for (size_t j = 0; j < i; ++j)
      if (canonical_path(outs[i].second) == canonical_path(outs[j].second))
        throw usage_error(outs[i].first + " and " + outs[j].first + " name the same file " + quote(outs[i].second));
    for (const auto& in : inputs)
      if (!in.empty() && canonical_path(in) == canonical_path(outs[i].second))
        throw usage_error(outs[i].first + " " + quote(outs[i].second) + " is a file the machine reads: it would be overwritten");
  }
  const std::string map_file = o.files.map_out.empty() ? std::string() : relative_to(o.files.map_out, out_dir);
  const std::string dist_file = dist_out.empty() ? std::string("dist1.dat") : relative_to(dist_out, out_dir);
  std::vector<std::string> warnings;
  if (dist_out.empty())
    warnings.push_back("the input reads its particle from 'dist1.dat' in the folder OPAL runs in: two lines, '1' and "
                       "'0 0 0 0 0 0' (or use --dist-out)");
  const std::string text = export_opal(m, out_dir, map_file, dist_file, warnings);
  // Every file output is created (as a temporary) before any is committed, so a refusal (an
  // unwritable folder) leaves none of them behind; stdout or a device gets the input last,
  // after the files it names are in place.
  std::vector<std::pair<std::unique_ptr<OutputFile>, std::string>> files;
  std::unique_ptr<OutputFile> main_out;
  if (to_file) main_out = std::make_unique<OutputFile>(o.common.output);
  if (!o.files.map_out.empty()) {
    std::ostringstream ms;
    write_psi_ring(ms, read_field_map(m.field.map, parse_map_format(m.field.format), m.field.symmetry));
    files.emplace_back(std::make_unique<OutputFile>(o.files.map_out), ms.str());
  }
  if (!dist_out.empty()) files.emplace_back(std::make_unique<OutputFile>(dist_out), "1\n0.0 0.0 0.0 0.0 0.0 0.0\n");
  for (auto& [f, content] : files) f->stream() << content;
  for (auto& [f, content] : files) f->commit();
  if (!main_out) main_out = std::make_unique<OutputFile>(o.common.output);
  main_out->stream() << text;
  main_out->commit();
  for (const auto& w : warnings) cli::warn(o.common, "note: " + w);
  return 0;
}

}  // namespace turnfit
