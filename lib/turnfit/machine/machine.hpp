// The machine file (turnfit-machine/1): one JSON document describing a cyclotron.
#pragma once

#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

namespace turnfit {

/// The tracked particle species.
struct Particle {
  std::string species = "proton";  ///< "proton", "deuteron", "alpha", "h2+", or "custom"
  double mass_MeV = 938.27208816;  ///< rest energy [MeV] (CODATA 2018 for the named species)
  double charge_e = 1.0;           ///< charge in units of e (positive: bent as a proton)
};

/// The named species' particle (CODATA 2018 masses): proton, deuteron, alpha, h2+; nullopt for
/// any other name ("custom" included: it has no fixed mass).
std::optional<Particle> named_particle(const std::string& species);

/// The main (sector magnet) field.
struct FieldSpec {
  std::string map;                     ///< path of the map, resolved against the machine file
  std::string format = "psi-ring";     ///< "psi-ring" (OPAL RING) or "turnfit"
  int symmetry = 0;                    ///< sector count; 0: take it from the map file
  double scale = 1.0;                  ///< factor applied to the map (e.g. -1 to flip polarity)
  double trimcoil_threshold_T = 0.0;   ///< trim coils act only where |Bz| exceeds this
};

/// The RF system the particle is synchronous with.
struct RfSystem {
  int harmonic = 1;          ///< harmonic number h
  double frequency_MHz = 0;  ///< RF frequency [MHz]; 0: no RF (static machine)
};

/// A single-gap RF cavity (OPAL RFCAVITY TYPE="SINGLEGAP").
struct Cavity {
  std::string name;
  std::string type = "single-gap";
  double voltage_MV = 0;       ///< peak gap voltage [MV] (times the radial profile)
  std::string profile;         ///< radial voltage profile file (resolved path; empty: flat 1)
  double harmonic_factor = 1;  ///< frequency = harmonic_factor * rf.frequency_MHz (3 for a flat-top)
  double phase_deg = 0;        ///< PHI0 [deg]
  double angle_deg = 0;        ///< azimuth of the gap line [deg]
  double pdis_mm = 0;          ///< displacement of the gap line from the centre [mm]
  double rmin_mm = 0;          ///< start of the gap along its line [mm]
  double rmax_mm = 0;          ///< end of the gap along its line [mm]
  double gap_width_mm = 0;     ///< gap width for the transit-time factor [mm]
  double rshift_mm = 0;        ///< radial shift of the gap line (the paper's rmainshift/rftshift)
};

/// A trim coil (see physics.md for the four models).
struct TrimCoil {
  std::string name;
  std::string type = "psi-bfield";  ///< psi-bfield | psi-phase | psi-bfield-mirrored | table
  double rmin_mm = 0;
  double rmax_mm = 0;
  double bmax_T = 0;
  std::vector<double> coefnum;      ///< numerator coefficients a_0, a_1, ... (r in m)
  std::vector<double> coefdenom;    ///< denominator coefficients b_0, b_1, ... (empty: g = 1)
  double slope_per_mm = 0;          ///< SLPTC, psi-bfield-mirrored only
  std::string table;                ///< profile file (type table): r_mm,b_shape
  std::vector<int> sectors;         ///< 1-based sector magnets it sits on (empty: all)
  double phimin_deg = 0;            ///< azimuth window start [deg]
  double phimax_deg = 360;          ///< azimuth window end [deg]
  double coef_origin_mm = 0;        ///< coefnum/coefdenom are polynomials in (r - origin) [m]
  std::vector<double> table_r_mm{};   ///< type table given in memory (no file; not in JSON)
  std::vector<double> table_shape{};  ///< its shape values
  std::vector<double> table_slope{};  ///< its slopes [1/mm] (empty: monotone Fritsch-Carlson slopes)
};

/// A radial wire probe: points s*(cos phi, sin phi) + a*(sin phi, -cos phi), s in [s_min, s_max],
/// the whole probe moved outwards by shift_mm (paper Eq. 1).
struct Probe {
  std::string name;
  double phi_deg = 0;
  double a_mm = 0;
  double s_min_mm = 0;
  double s_max_mm = 0;
  double shift_mm = 0;
  double step_mm = 0.5;  ///< wire step of the measurement
};

/// Where and how the particle starts.
struct Injection {
  double energy_MeV = 0;
  double r_mm = 0;
  double pr_betagamma = 0;  ///< radial momentum in units of m c
  double phi_deg = 0;
  double z_mm = 0;
  double pz_betagamma = 0;
  double t_ns = 0;          ///< start time (RF phase reference: t = 0)
};

/// A bunch around the injection point: a Gaussian in the six phase-space coordinates, or
/// a file of offsets. Emittances are rms and geometric, in the Twiss form
/// sigma = sqrt(emittance beta) (radial: dr and p_r/p; vertical: dz and p_z/p).
struct Bunch {
  int particles = 0;                 ///< default count for --particles (0: none given)
  double emittance_r_mm_mrad = 0;    ///< rms, geometric
  double beta_r_m = 0;
  double alpha_r = 0;
  double emittance_z_mm_mrad = 0;
  double beta_z_m = 0;
  double alpha_z = 0;
  double sigma_E_MeV = 0;            ///< rms energy spread
  double sigma_phase_deg = 0;        ///< rms RF phase width (a time spread at injection)
  double cutoff_sigma = 3;           ///< truncation of each normal variate (0: none)
  std::string file;                  ///< CSV of offsets (resolved path); overrides the Gaussian
};

/// The bunch's own field (machine-file `space_charge`, turnfit-machine(5)): a bunch run of a
/// machine with this block feels it (turnfit-track, turnfit-synth).
struct SpaceChargeSpec {
  double current_uA = 0;     ///< beam current; the bunch charge is current / f_rf (0: none)
  int grid[3] = {32, 32, 32};  ///< the Poisson solver's grid points (radial, vertical, longitudinal)
  int every_steps = 1;       ///< one solve every this many integration steps
  double halo_sigma = 8;     ///< particles beyond this many rms of the bunch see its monopole only (0: none)
};

/// Tracking settings.
struct Tracking {
  std::string integrator;   ///< empty: the tool's default
  int steps_per_turn = 0;   ///< 0: the integrator's default
  double step_deg = 0;      ///< azimuth integrator's largest step [deg]; 0: its default
  int turns = 0;            ///< 0: until extraction or loss
};

/// Physics beyond the base model, for a "truth" machine the fitting model does not know about
/// (machine-file `effects`, turnfit-machine(5) "EFFECTS"). Every entry keeps `index`, its place
/// in the `effects` array, so later checks (e.g. a sector number against the map's sector
/// count) can name the JSON path.

/// `field-harmonic`: b += amplitude exp(-(r - r0)^2 / (2 width^2)) cos(n (theta - phase)).
struct FieldHarmonicEffect {
  size_t index = 0;
  int n = 1;                 ///< harmonic number (0: an azimuthally uniform bump)
  double amplitude_T = 0;    ///< peak added bending field [T] (> 0 strengthens at theta = phase)
  double phase_deg = 0;      ///< azimuth of the maximum of the first lobe [deg]
  double r_mm = 0;           ///< centre of the radial Gaussian [mm]
  double width_mm = 0;       ///< rms width of the radial Gaussian [mm]; 0: the same at every radius
};

/// `sector-strength`: sector magnet `sector` (1-based; sector 1 centred on azimuth 0) scaled by
/// 1 + relative, switched on and off in the valleys over `transition_deg`.
struct SectorStrengthEffect {
  size_t index = 0;
  int sector = 1;
  double relative = 0;        ///< fractional change of the magnet's field (0.001 = 0.1 %)
  double transition_deg = 0;  ///< full width of the switch, centred on each valley; 0: a quarter pitch
};

/// `trimcoil-sectors`: the named coils act only on the listed sector magnets, whatever their
/// `trimcoils[].sectors` say.
struct TrimcoilSectorsEffect {
  size_t index = 0;
  std::vector<std::string> coils;
  std::vector<int> sectors;   ///< 1-based
};

/// `gap-bow`: a cavity's gap line bowed into a parabola through its two ends, moved along the
/// gap normal by `sagitta_mm` at the middle of [rmin, rmax] (> 0: downstream).
struct GapBowEffect {
  size_t index = 0;
  std::string cavity;
  double sagitta_mm = 0;
};

/// `voltage-tilt`: a cavity's radial voltage profile multiplied by 1 + slope (rho_n - pivot).
struct VoltageTiltEffect {
  size_t index = 0;
  std::string cavity;
  double slope = 0;           ///< relative change per unit rho_n (0.02: 2 % more at the outer end)
  double pivot_rho_n = 0.5;   ///< where the profile is unchanged
};

/// `probe-offset`: a probe placed elsewhere than the machine file says, unknown to its readout:
/// rotated by dphi (about the machine centre, or about its point at s = pivot_s_mm), moved
/// sideways by da and along itself by ds.
struct ProbeOffsetEffect {
  size_t index = 0;
  std::string probe;
  double dphi_deg = 0;
  double da_mm = 0;
  double ds_mm = 0;
  std::optional<double> pivot_s_mm;  ///< rotation centre along the probe; none: the machine centre
};

/// `injection-offset`: the beam starts away from the machine file's injection point (a coherent
/// betatron oscillation and/or an energy or phase error). Same offsets as a bunch file's columns.
struct InjectionOffsetEffect {
  size_t index = 0;
  double dr_mm = 0;
  double dpr_mrad = 0;        ///< change of p_r / p
  double dz_mm = 0;
  double dpz_mrad = 0;        ///< change of p_z / p
  double dE_MeV = 0;
  double dphase_deg = 0;      ///< main RF phase; positive starts later
};

/// All effects of a machine, by type, validated.
struct Effects {
  std::vector<FieldHarmonicEffect> field_harmonics;
  std::vector<SectorStrengthEffect> sector_strengths;
  std::vector<TrimcoilSectorsEffect> trimcoil_sectors;
  std::vector<GapBowEffect> gap_bows;
  std::vector<VoltageTiltEffect> voltage_tilts;
  std::vector<ProbeOffsetEffect> probe_offsets;
  std::optional<InjectionOffsetEffect> injection_offset;
  /// True when there is no effect at all.
  bool empty() const {
    return field_harmonics.empty() && sector_strengths.empty() && trimcoil_sectors.empty() && gap_bows.empty() &&
           voltage_tilts.empty() && probe_offsets.empty() && !injection_offset;
  }
};

/// A design variable: a named, bounded number that sets or shifts places in the machine.
struct DesignVariable {
  struct Target {
    std::string pointer;  ///< JSON pointer into the machine document
    double scale = 1.0;   ///< machine value = scale * dvar value (+ base value when add)
    bool add = false;     ///< add to the base value instead of replacing it
  };
  std::string name;
  std::string unit;
  std::string description;
  std::vector<Target> targets;
  double lower = 0;
  double upper = 0;
};

/// A whole machine, validated. `doc` is the normalized document the fields came from
/// (design variables act on it; the structs are rebuilt from it).
struct Machine {
  std::string path;  ///< the machine file ("" when built in memory)
  std::string dir;   ///< folder relative paths are resolved against
  std::string name;
  Particle particle;
  FieldSpec field;
  RfSystem rf;
  std::vector<Cavity> cavities;
  std::vector<TrimCoil> trimcoils;
  std::vector<Probe> probes;
  std::optional<Injection> injection;
  std::optional<Bunch> bunch;
  std::optional<SpaceChargeSpec> space_charge;
  Tracking tracking;
  nlohmann::json effects = nlohmann::json::array();  ///< the `effects` section as loaded (normalized)
  Effects effect_set;                                ///< the same, validated and typed
  std::map<std::string, DesignVariable> dvars;       ///< built-in and file-defined
  nlohmann::json doc;                                ///< the document as loaded (paths unresolved)
  /// Current values of the additive design variables (all 0 at load). The document holds
  /// base + scale * offset at each add target; keeping the offset, not the base, lets a
  /// re-set replace the previous shift instead of piling up on it.
  std::map<std::string, double> dvar_offsets;
};

/// Reads and validates a machine file. Unknown keys, keys with a wrong unit suffix,
/// wrong types and out-of-range values are EX_DATAERR naming the file and key path.
Machine load_machine(const std::string& path);

/// Validates a machine document; `name` is used in messages, `dir` resolves paths.
Machine machine_from_json(const nlohmann::json& doc, const std::string& name,
                          const std::string& dir);

/// Re-validates m.doc after it was changed in place and rebuilds the structs, keeping
/// path, dir, the design variables (bounds stay those of the loaded machine) and their
/// offsets. Errors are EX_DATAERR as for machine_from_json; m is unchanged on error.
void revalidate(Machine& m);

/// Applies `--set NAME=VALUE` assignments (NAME a design variable, or a JSON pointer
/// starting with '/') in order, then re-validates. Bad names, values or bounds: EX_USAGE.
void apply_sets(Machine& m, const std::vector<std::string>& assignments);

/// Applies a JSON object {name: value} of design-variable values read from a file
/// ("-" for stdin). Unknown names or values out of bounds: EX_DATAERR naming the file.
void apply_dvars_file(Machine& m, const std::string& path);

/// Sets one design variable (bounds checked; EX_USAGE on violation) and re-validates.
void set_dvar(Machine& m, const std::string& name, double value);

/// Sets several design variables at once, each within its bounds (EX_USAGE naming the first
/// that is not), and re-validates once: an optimizer's form (one validation per design, not
/// one per variable). m is unchanged on error.
void set_dvars(Machine& m, const std::vector<std::string>& names, const std::vector<double>& values);

/// The current value of a design variable, read back from the document.
double dvar_value(const Machine& m, const std::string& name);

/// The built-in design variables of the paper (appendix table) that this machine's
/// elements support: main cavities named main1..main4, flat-top "ft", probes RRI2 and RRL,
/// trim coils TC1..TC16. Bounds default to nominal +- a span per kind (documented).
std::map<std::string, DesignVariable> builtin_dvars(const Machine& m);

}  // namespace turnfit
