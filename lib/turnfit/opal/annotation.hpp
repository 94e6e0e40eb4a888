// The turnfit annotation of an exported OPAL input: comment lines that carry what OPAL's
// commands cannot say (names, descriptions, effects, bunches, exact values), used by an import
// only while the commands are the ones the export wrote.
#pragma once

#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

namespace turnfit {

/// The annotation's line prefix (a comment to OPAL).
constexpr const char* kAnnotationPrefix = "//turnfit| ";

/// What an annotation records.
struct Annotation {
  long line = 0;                ///< its first line
  nlohmann::json opal;          ///< the machine the commands import to (paths relative to the input's folder)
  nlohmann::json machine;       ///< the exported machine (paths relative to the input's folder)
};

/// The annotation lines of an exported input as comment text ("" for none).
std::string write_annotation(const nlohmann::json& opal_part, const nlohmann::json& machine);

/// The annotation in text, if any (EX_DATAERR naming the line when it is not turnfit's).
std::optional<Annotation> read_annotation(const std::string& text, const std::string& name);

/// The machine sections OPAL's commands describe: particle, field, rf, cavities, trimcoils,
/// probes, injection, tracking (name and description come from the import itself).
const std::vector<std::string>& opal_sections();

/// The sections of opal_sections() where the commands read now do not give exactly what the
/// annotation recorded: the sections edited since the export.
std::vector<std::string> changed_sections(const nlohmann::json& recorded, const nlohmann::json& now);

/// `path` (absolute, or relative to the current folder) relative to folder `dir` ("" is the
/// current folder), lexically; the absolute path when there is no relative one.
std::string relative_to(const std::string& path, const std::string& dir);

/// Rewrites a machine document's file paths (field map, profiles, coil tables, bunch file)
/// from relative to `from_dir` to relative to `to_dir` ("" is the current folder).
void rebase_paths(nlohmann::json& machine, const std::string& from_dir, const std::string& to_dir);

}  // namespace turnfit
