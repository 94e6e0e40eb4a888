// Test helpers shared by the turn-pattern problem tests: ring8's files, a machine's own turns as
// a peaks file, and a problem file loaded as a TurnPatternProblem.
#pragma once

#include <catch2/catch.hpp>

#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "../support.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/optimize/problem_file.hpp"
#include "turnfit/optimize/turn_problem.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit::test {

/// A file of the shipped ring8 machine.
inline std::string ring8(const std::string& file) {
  return std::string(TURNFIT_TEST_DIR) + "/../share/turnfit/ring8/" + file;
}

/// ring8 with each variable names[j] moved by frac[j] of its bound range; xt receives the values.
inline Machine moved_ring8(const std::vector<std::string>& names, const std::vector<double>& frac,
                           std::vector<double>& xt) {
  Machine m = load_machine(ring8("machine.json"));
  xt.clear();
  for (size_t j = 0; j < names.size(); ++j) {
    const DesignVariable& dv = m.dvars.at(names[j]);
    xt.push_back(dvar_value(m, names[j]) + frac[j] * (dv.upper - dv.lower));
  }
  set_dvars(m, names, xt);
  return m;
}

/// A machine's own turns as a peaks file (17 digits, so a problem at the machine matches exactly);
/// with `only_probe`, that probe's turns alone.
inline std::string turns_as_peaks(const Machine& m, const TempDir& tmp, const std::string& name,
                                  const std::string& only_probe = "") {
  const TrackModel model = make_track_model(m);
  std::vector<TurnRecord> turns;
  track_particle(model, injection_state(effective_injection(m), m.particle.mass_MeV), machine_track_settings(m),
                 turns);
  std::string csv = "probe,turn,r_mm,height,area,width_mm,flag\n";
  char buf[160];
  for (const auto& t : turns) {
    const std::string& probe = model.probes[static_cast<size_t>(t.probe)].name;
    if (!only_probe.empty() && probe != only_probe) continue;
    std::snprintf(buf, sizeof buf, "%s,%d,%.17g,1,1,1,ok\n", probe.c_str(), t.turn, t.r_mm);
    csv += buf;
  }
  return tmp.file(name, csv);
}

/// A problem file that must be a turn-pattern problem.
inline std::unique_ptr<TurnPatternProblem> load_turn_problem(const std::string& path) {
  LoadedProblem lp = load_problem(path, "", -1);
  auto* tp = dynamic_cast<TurnPatternProblem*>(lp.problem.get());
  REQUIRE(tp != nullptr);
  lp.problem.release();
  return std::unique_ptr<TurnPatternProblem>(tp);
}

}  // namespace turnfit::test
