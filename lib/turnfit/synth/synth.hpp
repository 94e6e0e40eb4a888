// Synthetic measurements from a "truth" machine: wire-probe profiles of a tracked bunch with a
// detector model, and trim coil phase-shift scans (Adam & Joho 1974), as test and demo data.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/spacecharge/space_charge.hpp"
#include "turnfit/track/bunch.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit {

/// The wire probe and its electronics. Signals are in nA of beam current intercepted by the
/// wire (input-referred): the wire's own gain (secondary emission) scales signal and noise
/// alike and drops out of the normalized profile.
struct WireModel {
  double current_uA = 88;         ///< beam current; the paper's profiles: 88, repeatability runs 58 and 108
  double wire_mm = 0.033;         ///< width of the wire across the beam (carbon fibre)
  double electronic_nA = 0.5;     ///< rms electronic noise per reading, independent of the signal
  double shot_nA = 0.05;          ///< shot-like noise: variance shot_nA * signal (nA^2)
  double baseline_nA = 2;         ///< amplifier offset added to every reading
  double baseline_drift_nA = 1;   ///< rms of the baseline's linear drift over one scan (random per run)
};

/// Run-to-run machine drift: each run (seed) changes these settings by Gaussian amounts with
/// these rms values, so two runs of the same machine differ as two measurements do. The
/// defaults give the PSI Ring example (examples/psi-ring/aeo.json) per-turn RRL differences of
/// sigma 0.48 mm and MAE 0.44 mm between runs, averaged over 66 pairs of runs, where the paper
/// measured sigma 0.51 and 0.58 mm, MAE 0.40 mm (Frey et al., repeatability at 58/88/108 uA).
struct DriftModel {
  double r_mm = 0.65;         ///< injection radius (beam centring from the injector and its line)
  double pr_mrad = 0.3;       ///< injection angle p_r / p
  double voltage_rel = 1e-4;  ///< all cavity voltages together, relative (RF amplitude regulation)
};

/// Errors of one wire scan that change along the wire's travel, so that they move each turn's
/// peak by its own amount (unlike the drift, which moves all turns of a run coherently and which
/// a fit's design variables absorb). The wire is driven from the probe's start (s_min_mm) to its
/// end at a constant speed, so a length along the travel is a time: t = x / v_scan. Each source
/// is a stationary Gaussian process drawn from the run's seed in its own stream per probe; all
/// rms 0 (the default) is no scan error at all, and the profiles are those of a model without it.
/// Processes with a correlation length are Ornstein-Uhlenbeck processes in the travel x,
/// exponential covariance rms^2 exp(-|dx| / corr) (Gillespie 1996, Phys. Rev. E 54, 2084:
/// the exact update on a grid is the AR(1) step in ou_process()).
struct ScanErrorModel {
  double intensity_rel = 0;        ///< rms of the beam current's relative fluctuation f during the scan
  double intensity_corr_mm = 5;    ///< correlation length of f in wire travel [mm] (v_scan times its correlation time)
  double drive_mm = 0;             ///< rms of the drive error: the wire's true minus its recorded position [mm]
  double drive_corr_mm = 10;       ///< correlation length of the drive error along the travel [mm]
  double readout_mm = 0;           ///< rms of each reading's own position error (independent per reading) [mm]
  /// Whether any source is on (an rms above 0).
  bool active() const { return intensity_rel > 0 || drive_mm > 0 || readout_mm > 0; }
};

/// One scan's errors, drawn from a ScanErrorModel for the readings of one profile (or set by hand).
/// Indexed like SynthProfile::position_mm; an empty vector is no error of that kind.
struct ScanErrors {
  std::vector<double> drive_mm;          ///< smooth drive error at each reading [mm]
  std::vector<double> readout_mm;        ///< independent position error of each reading [mm]
  std::vector<double> intensity_factor;  ///< beam current at each reading relative to its mean: 1 + f
};

/// A named measurement-error setting: the scan errors and the run-to-run drift that belong
/// together, so that the total repeatability of repeated runs stays the paper's.
struct SynthPreset {
  std::string name;
  ScanErrorModel scan;
  DriftModel drift;
};

/// The preset called `name` ("none": today's drift, no scan error; "paper": per-turn scan errors
/// and a smaller drift, together the paper's repeatability, see turnfit-synth(1)).
/// EX_USAGE for an unknown name.
SynthPreset synth_preset(const std::string& name);

/// The names synth_preset() knows, in the order --help lists them.
std::vector<std::string> synth_preset_names();

/// One run's drift: the amounts drawn from a DriftModel.
struct Drift {
  double dr_mm = 0;
  double dpr_mrad = 0;
  double dvoltage_rel = 0;
};

/// The phase-probe scan of the trim coils.
struct PhaseModel {
  double step_mm = 25;         ///< radial spacing of the phase probes
  double azimuth_deg = 0;      ///< azimuth of the radial line the phase probes sit on
  double noise_deg = 0.15;     ///< rms noise of one phase reading
  double excitation_T = 5e-4;  ///< test excitation added to the coil's nominal bmax_T
};

/// Everything a synthesis needs besides the machine.
struct SynthSettings {
  TrackSettings track;      ///< integrator and turn count for every track
  size_t particles = 2000;  ///< bunch size for the profiles
  std::uint64_t seed = 1;   ///< one run: bunch, drift, noise
  unsigned threads = 1;
  WireModel wire;
  DriftModel drift;
  ScanErrorModel scan;      ///< per-turn errors of the wire scans (default: none)
  std::string preset = "none";  ///< the name of the preset scan and drift came from (for truth.json)
  PhaseModel phase;
  bool profiles = true;     ///< make probe profiles
  bool phases = true;       ///< make phase scans (needs RF and a fundamental-harmonic cavity)
  /// The bunch's own field in the profiles' tracking, at the beam current wire.current_uA (the
  /// phase scans track single particles: no space charge there).
  bool space_charge = false;
  sc::SpaceChargeSettings sc;  ///< grid, interval, halo cut (its current is wire.current_uA)
};

/// One probe's synthetic measurement.
struct SynthProfile {
  std::string probe;
  double step_mm = 0;
  std::vector<double> position_mm;  ///< wire positions (the recorded radius, as track --histograms)
  std::vector<double> signal_nA;    ///< noiseless intercepted current (at the wire's true position, times 1 + f)
  std::vector<double> intensity;    ///< measured: signal, noise and baseline, divided by its maximum
  double baseline_nA = 0;           ///< offset of this scan
  double drift_nA = 0;              ///< baseline change from the first reading to the last
  double scale_nA = 0;              ///< the maximum the intensity was divided by
  ScanErrors scan;                  ///< this scan's errors (empty without a scan-error model)
};

/// One trim coil's phase-shift scan: delta sin(phi) at the phase probes.
struct PhaseScan {
  std::string coil;
  double nominal_T = 0;     ///< the coil's bmax_T in the reference run
  double excitation_T = 0;  ///< added in the excited run
  std::vector<double> r_mm, dsinphi;
  std::vector<double> dsinphi_true;  ///< without phase-probe noise
};

/// The sample mean of the particles a synthesis tracked, as offsets from the reference particle
/// (the machine's effective injection): a finite bunch's mean is not the reference, so its
/// centroids move as an injection error would. The design variables have no start time, so the
/// mean is also given as the same start moved along its path to the reference's start time (a
/// bunch that starts late at the injection azimuth is one that starts on time a little behind it).
struct BunchMean {
  size_t particles = 0;  ///< how many offsets were averaged (0: no bunch was tracked)
  BunchOffset offset;    ///< mean of the particles' offsets (bunch_columns' units)
  double dt_ns = 0;      ///< the mean start-time offset, offset.dphase_deg / (360 f_rf)
  double dphi_deg = 0;   ///< azimuth of the mean start moved to the reference's start time
  /// The mean start at azimuth + dphi_deg and the reference's start time: the offsets
  /// moved by their derivatives along the path (dphase_deg 0; dE_MeV unchanged, no gap between).
  BunchOffset at_reference_time;
};

/// The mean of `offsets` about `inj` (as offset_state starts them) in `model`; the move to the
/// reference's start time is first order in dt: dphi = -dt / (dt/dphi) from the equations of
/// motion in azimuth (physics/azimuth_eom.hpp), r and p_r/p moved by their derivatives times
/// dphi. EX_DATAERR when the mean start is not in the field map; a zero mean for no offsets.
BunchMean bunch_mean(const TrackModel& model, const Injection& inj, double mass_MeV,
                     const std::vector<BunchOffset>& offsets);

/// What a synthesis produced.
struct SynthResult {
  Drift drift;
  BunchMean bunch_mean;  ///< of the particles tracked for the profiles
  std::vector<SynthProfile> profiles;
  std::vector<PhaseScan> phases;
  std::vector<Centroid> centroids;  ///< the true turn positions (bunch means) of this run
  std::vector<std::string> probe_names;
  size_t particles = 0;
  size_t lost = 0;
};

/// The drift of run `seed` (independent of the bunch and the noise drawn from the same seed).
Drift draw_drift(const DriftModel& model, std::uint64_t seed);

/// Applies a drift to a machine: injection radius and angle, every cavity's voltage.
/// A machine without injection keeps its (missing) injection; EX_DATAERR if the result is invalid.
void apply_drift(Machine& m, const Drift& d);

/// Wire signal [nA] at the positions for crossings r_mm of the probe, each standing for a
/// 1/particles share of the beam and smoothed by the bandwidth of its turn (bandwidth_mm,
/// indexed like r_mm): the share of a Gaussian of that width inside the wire's width.
std::vector<double> wire_signal(const std::vector<double>& position_mm, const std::vector<double>& r_mm,
                                const std::vector<double>& bandwidth_mm, size_t particles, const WireModel& w);

/// wire_signal with the wire at position_mm[k] + offset_mm[k] for reading k (offset_mm empty, or
/// indexed like position_mm; position_mm an even grid): the true positions of a scan whose
/// recorded positions are position_mm. An empty offset gives exactly wire_signal's numbers.
std::vector<double> wire_signal(const std::vector<double>& position_mm, const std::vector<double>& offset_mm,
                                const std::vector<double>& r_mm, const std::vector<double>& bandwidth_mm,
                                size_t particles, const WireModel& w);

/// n values of a stationary Ornstein-Uhlenbeck process of rms `rms` and correlation length
/// `corr` sampled every `step` (same unit): x_0 = rms z_0, x_k = rho x_(k-1) + rms sqrt(1 - rho^2) z_k,
/// rho = exp(-step / corr), z_k standard normal at address (seed, stream, k) (corr 0: white
/// noise). The exact discretization, so the covariance is rms^2 rho^|k - j| for any step.
std::vector<double> ou_process(size_t n, double step, double rms, double corr, std::uint64_t seed,
                               std::uint64_t stream);

/// The errors of one scan (a profile read at the grid position_mm) under `model`, drawn from
/// `seed` in streams of their own for probe `stream` (none of them is the wire noise's, the
/// drift's or the bunch's, so switching scan errors on changes nothing else). Empty vectors for
/// the sources whose rms is 0.
ScanErrors draw_scan_errors(const ScanErrorModel& model, const std::vector<double>& position_mm, std::uint64_t seed,
                            std::uint64_t stream);

/// Puts a scan's errors into a profile before its noise: the wire reading k sits at
/// position_mm[k] + drive_mm[k] + readout_mm[k] (recorded at position_mm[k]), and the beam
/// current at that moment is intensity_factor[k] times its mean, so
///   signal_k = (1 + f_k) * signal(position_k + drive_k + readout_k)
/// with signal() wire_signal's sum over the crossings r_mm of widths bandwidth_mm. Sets
/// p.signal_nA and p.scan. A peak at r appears at the recorded x where x + drive(x) = r, i.e.
/// moved by about -drive(r); a gradient of f across a Gaussian turn of rms s moves its centroid
/// by s^2 d ln(1 + f)/dx.
void apply_scan_errors(SynthProfile& p, const std::vector<double>& r_mm, const std::vector<double>& bandwidth_mm,
                       size_t particles, const WireModel& w, const ScanErrors& e);

/// Silverman's rule-of-thumb bandwidth (Silverman 1986, Eq. 3.28) for n crossings of rms
/// spread sigma_mm: the smoothing that stands the macro-particles in for the continuous beam.
double silverman_bandwidth(double sigma_mm, std::uint64_t n);

/// The measured profile: signal plus shot-like and electronic noise plus baseline, divided by its
/// maximum. `stream` separates the noise of different probes drawn from one seed.
void measure_profile(SynthProfile& p, const WireModel& w, std::uint64_t seed, std::uint64_t stream);

/// The phase scan of trim coil `coil` (index into m.trimcoils): the reference particle tracked
/// with the coil at its nominal and at nominal + excitation; beam phase from the main RF crest
/// interpolated onto the phase probes' radii.
PhaseScan phase_scan(const Machine& m, size_t coil, const TrackSettings& st, const PhaseModel& pm,
                     std::uint64_t seed);

/// The linear response of a phase scan to extra radial fields: for each `fields[k]` (a trim
/// coil added to the machine's own at its bmax_T), delta sin(phi) at the radii r_mm against the
/// machine as it is, divided by that bmax_T (so per tesla of the coil's shape). The reference
/// particle is tracked and read exactly as phase_scan does (phase line at azimuth_deg, linear
/// interpolation between turns); NaN where a run did not reach a radius. Threads over fields.
std::vector<std::vector<double>> phase_response(const Machine& m, const std::vector<TrimCoil>& fields,
                                                const std::vector<double>& r_mm, const TrackSettings& st,
                                                double azimuth_deg, unsigned threads);

/// The whole synthesis of one run (seed) on a truth machine: draws and applies the run's drift,
/// tracks the bunch for the profiles and the reference particle for the phase scans.
SynthResult synthesize(const Machine& truth, const SynthSettings& s);

}  // namespace turnfit
