// Fuzz target: a problem file (turnfit-problem(5)), loaded as turnfit-nsga, turnfit-localsearch
// and turnfit-diagnose load it. It sits in a folder where "ring8" is the embedded machine's
// folder, so a seed can name "ring8/machine.json" and ring8's turns as its peaks. A turn-pattern
// problem that would follow the bunch's centre is loaded with "bunch": "reference": the centre
// costs a tracked quadrature at load (seconds under the sanitizers), which is tracking, not
// reading, and would make every execution time out.
#include <filesystem>

#include "fuzz.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/optimize/problem_file.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const bool linked = [] {
    std::filesystem::create_directory_symlink(turnfit::fuzz::ring8_dir(), turnfit::fuzz::work_dir() + "/ring8");
    return true;
  }();
  (void)linked;
  return turnfit::fuzz::guarded([&] {
    std::string path = turnfit::fuzz::as_file(data, size, "problem.json");
    nlohmann::json j = turnfit::read_json(path);
    if (j.is_object() && j.contains("machine") && (!j.contains("bunch") || j["bunch"] == "centroid")) {
      j["bunch"] = "reference";
      const std::string text = turnfit::json_text(j);
      path = turnfit::fuzz::as_file(reinterpret_cast<const std::uint8_t*>(text.data()), text.size(), "problem.json");
    }
    turnfit::load_problem(path, "", -1, 0, 0);
  });
}
