// Fuzz target: a machine file built into its tracking model and tracked for at most two turns,
// as turnfit-track runs it: what validation lets through must not crash, hang or read out of
// bounds when the model is built and stepped. Paths resolve from ring8's folder; ring8's map,
// profiles and coil tables are read once and reused (a machine naming other files reads them).
// The integrator's own step settings are kept within what a run of seconds allows.
#include <algorithm>
#include <vector>

#include "fuzz.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/machine/machine.hpp"
#include "turnfit/track/model.hpp"
#include "turnfit/track/tracker.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const turnfit::ModelFiles files =
      turnfit::read_model_files(turnfit::load_machine(turnfit::fuzz::ring8_dir() + "/machine.json"));
  return turnfit::fuzz::guarded([&] {
    const std::string text(reinterpret_cast<const char*>(data), size);
    const turnfit::Machine m =
        turnfit::machine_from_json(turnfit::parse_json(text, "machine.json"), "machine.json", turnfit::fuzz::ring8_dir());
    if (!m.injection) return;  // nothing to track (a tool says so; the machine target reads it)
    const turnfit::TrackModel model = turnfit::make_track_model(m, {}, &files);
    turnfit::TrackSettings s = turnfit::machine_track_settings(m);
    s.turns = std::min(s.turns > 0 ? s.turns : 2.0, 2.0);
    if (s.integrator == "rk4") s.steps_per_turn = std::min(std::max(s.steps_per_turn, 0), 2880);
    if (s.step_deg > 0) s.step_deg = std::max(s.step_deg, 0.1);
    std::vector<turnfit::TurnRecord> turns;
    turnfit::track_particle(model, turnfit::injection_state(turnfit::effective_injection(m), m.particle.mass_MeV), s,
                            turns);
  });
}
