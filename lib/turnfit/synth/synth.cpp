// Synthetic measurements: a bunch tracked through the truth machine seen by a wire probe with
// finite width, noise and baseline; phase-probe scans of each trim coil; run-to-run drift.
#include "turnfit/synth/synth.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>

#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/physics/azimuth_eom.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/model.hpp"

namespace turnfit {
namespace {

/// SplitMix64's finalizer (Steele, Lea, Flood 2014): a bijective mix, so hashing (seed,
/// stream, index) gives every random number its own address: the same numbers for any thread
/// count and any order of evaluation.
std::uint64_t mix64(std::uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

/// Uniform in (0, 1) at an address (never 0: log in Box-Muller).
double uniform_at(std::uint64_t seed, std::uint64_t stream, std::uint64_t index, std::uint64_t k) {
  const std::uint64_t h = mix64(mix64(mix64(mix64(seed) ^ stream) ^ index) ^ k);
  return (static_cast<double>(h >> 11) + 0.5) * 0x1.0p-53;
}

/// Standard normal at an address (Box-Muller, our own, so results do not depend on the
/// standard library). `which` picks independent variates at the same index.
double normal_at(std::uint64_t seed, std::uint64_t stream, std::uint64_t index, std::uint64_t which) {
  const double u1 = uniform_at(seed, stream, index, 2 * which), u2 = uniform_at(seed, stream, index, 2 * which + 1);
  return std::sqrt(-2 * std::log(u1)) * std::cos(2 * kPi * u2);
}

// Streams: separate sequences drawn from one seed.
constexpr std::uint64_t kDriftStream = 0x64726966;      // run-to-run drift
constexpr std::uint64_t kProfileStream = 0x70726f00;    // + probe index: wire noise, baseline
constexpr std::uint64_t kPhaseStream = 0x70686100;      // + coil index: phase-probe noise
constexpr std::uint64_t kIntensityStream = 0x73636900;  // + probe index: beam current during the scan
constexpr std::uint64_t kDriveStream = 0x73636400;      // + probe index: probe drive error
constexpr std::uint64_t kReadoutStream = 0x73637200;    // + probe index: per-reading position error

/// Standard normal distribution function.
double norm_cdf(double z) { return 0.5 * std::erfc(-z / std::sqrt(2.0)); }

/// A radial line for the phase probes over the whole field map, at the given azimuth.
ProbeLine phase_line(const TrackModel& model, double azimuth_deg) {
  ProbeLine l;
  l.name = "phase";
  l.phi_rad = azimuth_deg * kPi / 180;
  l.sin_phi = std::sin(l.phi_rad);
  l.cos_phi = std::cos(l.phi_rad);
  l.s_min_m = model.map.grid().r_min_m();
  l.s_max_m = model.map.grid().r_max_m();
  return l;
}

/// Beam phase relative to the crest of the fundamental-harmonic cavities at each crossing of
/// the phase line. A phase probe reads the arrival time against the RF; its zero is set so
/// that 0 is the crest. The particle reaches gap g a fraction dtheta_g of a turn later, h
/// dtheta_g of RF phase for an isochronous orbit, where the gap's phase is 2 pi f t - PHI0
/// (cavity.hpp): crest-relative phase = RF phase + h dtheta_g - PHI0_g, averaged over the gaps
/// (weighted by voltage). The slip within one turn is a common offset of both runs of a scan
/// and drops out of delta sin(phi) to first order.
std::vector<double> crest_phases(const Machine& m, const TrackModel& model, const ProbeLine& line,
                                 const std::vector<TurnRecord>& rec) {
  std::vector<double> out;
  for (const auto& tr : rec) {
    double c = 0, s = 0;
    for (size_t g = 0; g < m.cavities.size(); ++g) {
      const Cavity& cav = m.cavities[g];
      if (cav.harmonic_factor != 1 || cav.voltage_MV == 0) continue;
      const double th = model.gaps[g].crossing_azimuth(tr.r_mm * 1e-3 + line.shift_m);
      if (!std::isfinite(th)) continue;
      const double dth = std::fmod(th - line.phi_rad + 4 * kPi, 2 * kPi) * 180 / kPi;
      const double psi = (tr.phase_deg + model.harmonic * dth - cav.phase_deg) * kPi / 180;
      c += std::fabs(cav.voltage_MV) * std::cos(psi);
      s += std::fabs(cav.voltage_MV) * std::sin(psi);
    }
    out.push_back(c == 0 && s == 0 ? std::nan("") : std::atan2(s, c) * 180 / kPi);
  }
  return out;
}

/// Linear interpolation of y(r) at r0 between the first pair of crossings that brackets it
/// (turn radii grow; a pair that does not, inside a betatron wiggle, is skipped).
double interpolate(const std::vector<double>& r, const std::vector<double>& y, double r0) {
  for (size_t n = 0; n + 1 < r.size(); ++n) {
    if (!(r[n] <= r0 && r0 <= r[n + 1]) || r[n + 1] == r[n]) continue;
    if (!std::isfinite(y[n]) || !std::isfinite(y[n + 1])) return std::nan("");
    const double u = (r0 - r[n]) / (r[n + 1] - r[n]);
    return y[n] + u * (y[n + 1] - y[n]);
  }
  return std::nan("");
}

/// Radii and sin(crest phase) of the reference particle on the phase line.
void phase_history(const Machine& m, const TrackModel& model, const TrackSettings& st, std::vector<double>& r,
                   std::vector<double>& psi) {
  std::vector<TurnRecord> rec;
  // effective_injection: an injection-offset effect of the truth moves the start too.
  track_particle(model, injection_state(effective_injection(m), m.particle.mass_MeV), st, rec);
  const std::vector<double> ph = crest_phases(m, model, model.probes.front(), rec);
  r.clear();
  psi.clear();
  for (size_t n = 0; n < rec.size(); ++n) {
    r.push_back(rec[n].r_mm);
    psi.push_back(ph[n]);
  }
}

void check_phase_machine(const Machine& m) {
  if (!m.injection) throw data_error(m.path, 0, "/injection: phase scans track from the injection point; the machine has none");
  if (!(m.rf.frequency_MHz > 0))
    throw data_error(m.path, 0, "/rf/frequency_MHz: phase scans measure the beam phase against the RF; the machine has no RF");
  bool fundamental = false;
  for (const auto& c : m.cavities) fundamental = fundamental || (c.harmonic_factor == 1 && c.voltage_MV != 0);
  if (!fundamental)
    throw data_error(m.path, 0, "/cavities: phase scans need an accelerating cavity at the RF frequency (harmonic_factor 1) "
                                "to define the crest");
}

/// sin of phases in degrees.
std::vector<double> sines(const std::vector<double>& phase_deg) {
  std::vector<double> s(phase_deg.size());
  for (size_t i = 0; i < phase_deg.size(); ++i) s[i] = std::sin(phase_deg[i] * kPi / 180);
  return s;
}

/// The reference particle's history (radii, crest phases) with `coil` put into the model: at
/// index `slot` of its coils, or added when slot is past the end. Tabulated as make_track_model
/// builds its coils (unless the model keeps the formula).
void history_with(const Machine& m, const TrackModel& base, const TrimCoil& coil, size_t slot, const TrackSettings& st,
                  std::vector<double>& r, std::vector<double>& psi) {
  TrackModel exc = base;
  TrimCoilField f(coil, base.map.grid().symmetry);
  if (!base.opal_map) f.tabulate(base.map.grid().r_min_m(), base.map.grid().r_max_m());
  if (slot < exc.coils.size()) exc.coils[slot] = std::move(f);
  else exc.coils.push_back(std::move(f));
  exc.sum_coils(!base.opal_map);
  phase_history(m, exc, st, r, psi);
}

/// The scan of one coil, given the reference run's history (r0, p0: the same for every coil).
PhaseScan phase_scan_on(const Machine& m, const TrackModel& base, size_t coil, const TrackSettings& st,
                        const PhaseModel& pm, std::uint64_t seed, const std::vector<double>& r0,
                        const std::vector<double>& p0) {
  const TrimCoil& tc = m.trimcoils.at(coil);
  PhaseScan out;
  out.coil = tc.name;
  out.nominal_T = tc.bmax_T;
  out.excitation_T = pm.excitation_T;
  std::vector<double> r1, p1;
  // The coil as the model built it: effects (trimcoil-sectors) may have changed its sectors, and
  // the excitation must act where the coil does.
  TrimCoil excited = base.coils.at(coil).coil();
  excited.bmax_T += pm.excitation_T;
  history_with(m, base, excited, coil, st, r1, p1);
  if (r0.size() < 2 || r1.size() < 2)
    throw data_error(m.path, 0, "/trimcoils/" + std::to_string(coil) + ": the phase scan of " + tc.name +
                                    " saw fewer than two turns on the phase probes' line");
  // Phase probes every step_mm over the radii both runs crossed.
  const double lo = std::max(r0.front(), r1.front()), hi = std::min(*std::max_element(r0.begin(), r0.end()),
                                                                    *std::max_element(r1.begin(), r1.end()));
  const std::vector<double> s0 = sines(p0), s1 = sines(p1);
  const std::uint64_t stream = kPhaseStream + coil;
  size_t j = 0;
  for (double k = std::ceil(lo / pm.step_mm - 1e-9); k * pm.step_mm <= hi + 1e-9; k += 1) {
    const double r = k * pm.step_mm;
    const double a0 = interpolate(r0, p0, r), a1 = interpolate(r1, p1, r);
    const double t0 = interpolate(r0, s0, r), t1 = interpolate(r1, s1, r);
    if (!std::isfinite(a0) || !std::isfinite(a1) || !std::isfinite(t0) || !std::isfinite(t1)) continue;
    // Each probe reads each run once: two independent readings per radius. The phase is
    // interpolated, then read with noise (sin of the interpolated phase, not the interpolated
    // sine, for the noisy value: the probe measures a phase).
    const double n0 = pm.noise_deg * normal_at(seed, stream, j, 0), n1 = pm.noise_deg * normal_at(seed, stream, j, 1);
    out.r_mm.push_back(r);
    out.dsinphi_true.push_back(t1 - t0);
    out.dsinphi.push_back(t1 - t0 + (std::sin((a1 + n1) * kPi / 180) - std::sin(a1 * kPi / 180)) -
                          (std::sin((a0 + n0) * kPi / 180) - std::sin(a0 * kPi / 180)));
    ++j;
  }
  return out;
}

}  // namespace

SynthPreset synth_preset(const std::string& name) {
  SynthPreset p;
  p.name = name;
  if (name == "none") return p;  // today's measurement: the drift carries all of the repeatability
  if (name == "paper") {
    // The paper gives only the total scatter of repeated runs (sigma 0.51 and 0.58 mm): a third of
    // its variance stays coherent drift (0.64 of the default drift's amplitudes: sigma 0.31 mm of
    // the PSI example's RRL differences), two thirds are per-turn scan errors (sigma 0.44 mm of
    // differences, 0.31 mm in one run), almost all of it the drive error. Figures and the reasons
    // for the split: turnfit-synth(1) "Scan errors" and bench/synth_repeatability.py (RESULTS.md).
    p.scan.intensity_rel = 0.02;     // 2% current ripple (regulated CW beam; an assumption)
    p.scan.intensity_corr_mm = 5;    // 0.5 s at an assumed 10 mm/s scan
    p.scan.drive_mm = 0.36;          // calibrated: the per-turn share of the paper's sigma
    p.scan.drive_corr_mm = 10;       // about two turn separations at RRL's outer end
    p.scan.readout_mm = 0.05;        // a tenth of RRL's 0.5 mm step
    p.drift.r_mm = 0.42;
    p.drift.pr_mrad = 0.19;
    p.drift.voltage_rel = 6.5e-5;
    return p;
  }
  throw usage_error("--scan-errors: unknown preset '" + name + "' (known: none, paper)");
}

std::vector<std::string> synth_preset_names() { return {"none", "paper"}; }

Drift draw_drift(const DriftModel& model, std::uint64_t seed) {
  Drift d;
  d.dr_mm = model.r_mm * normal_at(seed, kDriftStream, 0, 0);
  d.dpr_mrad = model.pr_mrad * normal_at(seed, kDriftStream, 0, 1);
  d.dvoltage_rel = model.voltage_rel * normal_at(seed, kDriftStream, 0, 2);
  return d;
}

void apply_drift(Machine& m, const Drift& d) {
  using nlohmann::json;
  if (d.dr_mm == 0 && d.dpr_mrad == 0 && d.dvoltage_rel == 0) return;
  if (m.injection && m.doc.contains("injection")) {
    json& in = m.doc["injection"];
    const Injection& inj = *m.injection;
    in["r_mm"] = inj.r_mm + d.dr_mm;
    // An angle p_r / p, on the total momentum of the injection energy.
    const double P = kinematics(m.particle.mass_MeV, 1, inj.energy_MeV).betagamma;
    in["pr_betagamma"] = inj.pr_betagamma + P * d.dpr_mrad * 1e-3;
  }
  if (m.doc.contains("cavities"))
    for (auto& c : m.doc["cavities"])
      if (c.contains("voltage_MV")) c["voltage_MV"] = c["voltage_MV"].get<double>() * (1 + d.dvoltage_rel);
  revalidate(m);
}

BunchMean bunch_mean(const TrackModel& model, const Injection& inj, double mass_MeV,
                     const std::vector<BunchOffset>& offsets) {
  BunchMean bm;
  bm.particles = offsets.size();
  if (offsets.empty()) return bm;
  // Summed in order: the same mean for any thread count (offsets do not depend on it).
  BunchOffset& m = bm.offset;
  for (const auto& o : offsets) m += o;
  m = scaled(m, 1.0 / static_cast<double>(offsets.size()));
  bm.at_reference_time = m;
  bm.at_reference_time.dphase_deg = 0;
  if (m.dphase_deg == 0) return bm;
  // offset_state's conversion: the mean particle starts dt later at the injection azimuth.
  bm.dt_ns = m.dphase_deg / (360 * model.rf_MHz * 1e6) * 1e9;
  const ParticleState s = offset_state(inj, mass_MeV, model.rf_MHz, m);
  // Where the particle was dt earlier on its own path: d(r, p_r/p, z, p_z/p, t)/dphi of the
  // azimuth tracker (AzRhs in azimuth_integrator.cpp), so dphi = -dt / (dt/dphi); moving
  // backwards in time is moving backwards in azimuth (the tracker's azimuth grows).
  const double P = std::sqrt(s.px * s.px + s.py * s.py + s.pz * s.pz), th = std::atan2(s.y, s.x);
  const double r = std::hypot(s.x, s.y), x = (s.px * std::cos(th) + s.py * std::sin(th)) / P, xz = s.pz / P;
  const double brho = P * mass_MeV * 1e6 / (kSpeedOfLight * std::fabs(model.charge_e));
  const double inv_brho = (model.charge_e >= 0 ? 1.0 : -1.0) / brho, inv_v = std::sqrt(1 + P * P) / (P * kSpeedOfLight);
  FieldSample f;
  AzimuthDerivs d;
  if (!model.field(r, th, f) || !azimuth_eom(r, x, s.z, xz, f, inv_brho, inv_v, d) || !(d.dt > 0))
    throw Error(ExitCode::data, "bunch: the bunch's mean start (r = " + std::to_string(r * 1e3) +
                                    " mm) is outside the field map or has no azimuthal momentum");
  const double dphi = -bm.dt_ns * 1e-9 / d.dt;
  bm.dphi_deg = dphi * 180 / kPi;
  BunchOffset& a = bm.at_reference_time;
  a.dr_mm += d.dr * dphi * 1e3;
  a.dpr_mrad += d.dx * dphi * 1e3;
  a.dz_mm += d.dz * dphi * 1e3;
  a.dpz_mrad += d.dxz * dphi * 1e3;
  return bm;
}

double silverman_bandwidth(double sigma_mm, std::uint64_t n) {
  if (!(sigma_mm > 0) || n < 2) return 0;
  return 1.06 * sigma_mm * std::pow(static_cast<double>(n), -0.2);
}

std::vector<double> wire_signal(const std::vector<double>& x, const std::vector<double>& r,
                                const std::vector<double>& h, size_t particles, const WireModel& w) {
  return wire_signal(x, {}, r, h, particles, w);
}

std::vector<double> wire_signal(const std::vector<double>& x, const std::vector<double>& off,
                                const std::vector<double>& r, const std::vector<double>& h, size_t particles,
                                const WireModel& w) {
  std::vector<double> s(x.size(), 0.0);
  if (x.empty() || particles == 0) return s;
  if (!off.empty() && off.size() != x.size())
    throw Error(ExitCode::software, "wire_signal: " + std::to_string(off.size()) + " offsets for " +
                                        std::to_string(x.size()) + " readings");
  const double x0 = x.front(), dx = x.size() > 1 ? x[1] - x[0] : 1.0, half = 0.5 * w.wire_mm;
  const double share = w.current_uA * 1e3 / static_cast<double>(particles);  // nA per crossing
  // Readings whose wire sits off its grid point by up to `far` can see a crossing that far
  // beyond the usual reach (0 without offsets: exactly the grid's index range).
  double far = 0;
  for (double o : off) far = std::max(far, std::fabs(o));
  for (size_t i = 0; i < r.size(); ++i) {
    // The wire at x takes the part of this crossing's Gaussian (width h) in [x - w/2, x + w/2];
    // beyond 8 widths the share is below 1e-15.
    const double reach = half + 8 * h[i];
    const double lo = off.empty() ? r[i] - reach : r[i] - reach - far, hi = off.empty() ? r[i] + reach : r[i] + reach + far;
    const long k0 = std::max(0L, static_cast<long>(std::floor((lo - x0) / dx)));
    const long k1 = std::min(static_cast<long>(x.size()) - 1, static_cast<long>(std::ceil((hi - x0) / dx)));
    for (long k = k0; k <= k1; ++k) {
      const size_t kk = static_cast<size_t>(k);
      const double d = (off.empty() ? x[kk] : x[kk] + off[kk]) - r[i];
      double f;
      if (h[i] > 0) f = norm_cdf((d + half) / h[i]) - norm_cdf((d - half) / h[i]);
      else f = std::fabs(d) <= half ? 1.0 : 0.0;
      s[static_cast<size_t>(k)] += share * f;
    }
  }
  return s;
}

std::vector<double> ou_process(size_t n, double step, double rms, double corr, std::uint64_t seed,
                               std::uint64_t stream) {
  std::vector<double> v(n, 0.0);
  if (n == 0 || !(rms > 0)) return v;
  // Exact update of the OU process over one step (Gillespie 1996, Eq. 1.9 with no drift):
  // the AR(1) coefficient exp(-step/corr) and the innovation that keeps the variance rms^2.
  const double rho = corr > 0 ? std::exp(-std::fabs(step) / corr) : 0.0, innov = rms * std::sqrt(1 - rho * rho);
  v[0] = rms * normal_at(seed, stream, 0, 0);
  for (size_t k = 1; k < n; ++k) v[k] = rho * v[k - 1] + innov * normal_at(seed, stream, k, 0);
  return v;
}

ScanErrors draw_scan_errors(const ScanErrorModel& model, const std::vector<double>& x, std::uint64_t seed,
                            std::uint64_t stream) {
  ScanErrors e;
  const size_t n = x.size();
  // The wire's travel per reading: the grid's step (readings are taken at even steps).
  const double step = n > 1 ? x[1] - x[0] : 1.0;
  if (model.intensity_rel > 0) {
    e.intensity_factor = ou_process(n, step, model.intensity_rel, model.intensity_corr_mm, seed, kIntensityStream + stream);
    // A current never goes negative: a (physically absurd) fluctuation below -100% stops at 0.
    for (double& f : e.intensity_factor) f = std::max(0.0, 1 + f);
  }
  if (model.drive_mm > 0) e.drive_mm = ou_process(n, step, model.drive_mm, model.drive_corr_mm, seed, kDriveStream + stream);
  if (model.readout_mm > 0) e.readout_mm = ou_process(n, step, model.readout_mm, 0, seed, kReadoutStream + stream);
  return e;
}

void apply_scan_errors(SynthProfile& p, const std::vector<double>& r, const std::vector<double>& h, size_t particles,
                       const WireModel& w, const ScanErrors& e) {
  const size_t n = p.position_mm.size();
  for (const auto* v : {&e.drive_mm, &e.readout_mm, &e.intensity_factor})
    if (!v->empty() && v->size() != n)
      throw Error(ExitCode::software, "apply_scan_errors: " + std::to_string(v->size()) + " values for " +
                                          std::to_string(n) + " readings");
  // The wire's true position minus its recorded one, reading by reading.
  std::vector<double> off;
  if (!e.drive_mm.empty() || !e.readout_mm.empty()) {
    off.assign(n, 0.0);
    for (size_t k = 0; k < n; ++k)
      off[k] = (e.drive_mm.empty() ? 0.0 : e.drive_mm[k]) + (e.readout_mm.empty() ? 0.0 : e.readout_mm[k]);
  }
  p.signal_nA = wire_signal(p.position_mm, off, r, h, particles, w);
  // The wire intercepts a share of the beam current flowing at that moment.
  if (!e.intensity_factor.empty())
    for (size_t k = 0; k < n; ++k) p.signal_nA[k] *= e.intensity_factor[k];
  p.scan = e;
}

void measure_profile(SynthProfile& p, const WireModel& w, std::uint64_t seed, std::uint64_t stream) {
  const size_t n = p.signal_nA.size();
  const std::uint64_t st = kProfileStream + stream;
  p.baseline_nA = w.baseline_nA;
  p.drift_nA = w.baseline_drift_nA * normal_at(seed, st, 0, 7);
  std::vector<double> y(n);
  double top = 0;
  for (size_t k = 0; k < n; ++k) {
    const double sig = p.signal_nA[k];
    // Shot-like noise: variance proportional to the signal (a counting process whose counts
    // are signal / shot_nA); electronic noise: a constant rms, the amplifier's input noise.
    const double shot = std::sqrt(w.shot_nA * std::max(0.0, sig)) * normal_at(seed, st, k + 1, 0);
    const double elec = w.electronic_nA * normal_at(seed, st, k + 1, 1);
    const double base = p.baseline_nA + p.drift_nA * (n > 1 ? static_cast<double>(k) / static_cast<double>(n - 1) : 0.0);
    y[k] = sig + shot + elec + base;
    top = std::max(top, y[k]);
  }
  // Normalized as the paper's figures show the profiles: the highest reading is 1.
  p.scale_nA = top;
  p.intensity.resize(n);
  for (size_t k = 0; k < n; ++k) p.intensity[k] = top > 0 ? y[k] / top : y[k];
}

PhaseScan phase_scan(const Machine& m, size_t coil, const TrackSettings& st, const PhaseModel& pm,
                     std::uint64_t seed) {
  check_phase_machine(m);
  if (coil >= m.trimcoils.size()) throw Error(ExitCode::software, "phase_scan: no trim coil " + std::to_string(coil));
  TrackModel base = make_track_model(m);
  base.probes = {phase_line(base, pm.azimuth_deg)};
  std::vector<double> r0, p0;
  phase_history(m, base, st, r0, p0);
  return phase_scan_on(m, base, coil, st, pm, seed, r0, p0);
}

std::vector<std::vector<double>> phase_response(const Machine& m, const std::vector<TrimCoil>& fields,
                                                const std::vector<double>& r_mm, const TrackSettings& st,
                                                double azimuth_deg, unsigned threads) {
  check_phase_machine(m);
  TrackModel base = make_track_model(m);
  base.probes = {phase_line(base, azimuth_deg)};
  std::vector<double> r0, p0;
  phase_history(m, base, st, r0, p0);
  const std::vector<double> s0 = sines(p0);
  std::vector<std::vector<double>> out(fields.size());
  parallel_for(fields.size(), threads, [&](size_t k, unsigned) {
    std::vector<double> r1, p1;
    history_with(m, base, fields[k], base.coils.size(), st, r1, p1);
    const std::vector<double> s1 = sines(p1);
    std::vector<double>& o = out[k];
    for (double r : r_mm) o.push_back((interpolate(r1, s1, r) - interpolate(r0, s0, r)) / fields[k].bmax_T);
  });
  return out;
}

SynthResult synthesize(const Machine& truth, const SynthSettings& s) {
  if (!truth.injection) throw data_error(truth.path, 0, "/injection: the machine has no injection block to track from");
  SynthResult res;
  res.drift = draw_drift(s.drift, s.seed);
  Machine run = truth;
  apply_drift(run, res.drift);
  TrackModel model = make_track_model(run);
  for (const auto& p : model.probes) res.probe_names.push_back(p.name);

  if (s.profiles && !model.probes.empty()) {
    if (!run.bunch)
      throw data_error(run.path, 0, "/bunch: synthetic profiles need a beam: the machine's bunch block (emittances, "
                                    "sigma_E_MeV, sigma_phase_deg) or bunch.file");
    std::vector<BunchOffset> offs;
    std::vector<ParticleState> starts;
    if (!run.bunch->file.empty()) {
      const BunchFile file = read_bunch_file(run.bunch->file);
      starts = offset_states(effective_injection(run), run.particle.mass_MeV, model.rf_MHz, file, s.particles);
      offs.assign(file.offsets.begin(), file.offsets.begin() + static_cast<long>(starts.size()));
    } else {
      const Bunch& b = *run.bunch;
      if (b.emittance_r_mm_mrad == 0 && b.emittance_z_mm_mrad == 0 && b.sigma_E_MeV == 0 && b.sigma_phase_deg == 0)
        throw data_error(run.path, 0, "/bunch: the bunch has no spread (emittances, sigma_E_MeV, sigma_phase_deg all 0): "
                                      "a beam without width gives no profile");
      offs = gaussian_bunch(b, s.particles, s.seed);
      starts = offset_states(effective_injection(run), run.particle.mass_MeV, model.rf_MHz, offs);
    }
    res.bunch_mean = bunch_mean(model, effective_injection(run), run.particle.mass_MeV, offs);
    // Every particle's crossings, each in its own slot: filled concurrently, read in order.
    struct Hit {
      int probe, turn;
      double r_mm;
    };
    std::vector<std::vector<Hit>> hits(starts.size());
    const CrossingSink sink = [&](size_t i, const std::vector<TurnRecord>& turns) {
      auto& h = hits[i];
      h.reserve(turns.size());
      for (const auto& t : turns) h.push_back({t.probe, t.turn, t.r_mm});
    };
    std::unique_ptr<sc::SpaceChargeKick> sck;
    CollectiveKick ck;
    if (s.space_charge && s.wire.current_uA > 0) {
      sc::SpaceChargeSettings scs = s.sc;
      scs.current_uA = s.wire.current_uA;
      sck = std::make_unique<sc::SpaceChargeKick>(model, scs, starts.size(), s.threads);
      ck = sck->collective();
    }
    BunchResult br = track_bunch(model, starts, s.track, s.threads, {}, sink, sck ? &ck : nullptr);
    res.particles = br.particles;
    res.lost = br.lost.size();
    res.centroids = br.centroids;
    // Bandwidth per (probe, turn) from that turn's own spread.
    std::map<std::pair<int, int>, double> bw;
    for (const auto& c : br.centroids) bw[{c.probe, c.turn}] = silverman_bandwidth(c.r_rms_mm, c.particles);
    const std::vector<ProbeHistogram> grid = empty_histograms(model);
    for (size_t p = 0; p < model.probes.size(); ++p) {
      SynthProfile prof;
      prof.probe = model.probes[p].name;
      prof.step_mm = grid[p].step_mm;
      for (size_t k = 0; k < grid[p].counts.size(); ++k)
        prof.position_mm.push_back(grid[p].lo_mm + (static_cast<double>(k) + 0.5) * grid[p].step_mm);
      std::vector<double> r, h;
      for (const auto& ph : hits)
        for (const auto& x : ph)
          if (x.probe == static_cast<int>(p)) {
            r.push_back(x.r_mm);
            double b = bw[{x.probe, x.turn}];
            // A turn crossed by a single particle has no spread of its own: the wire step
            // keeps it visible on the sample grid.
            h.push_back(b > 0 ? b : grid[p].step_mm);
          }
      if (s.scan.active())
        apply_scan_errors(prof, r, h, starts.size(), s.wire, draw_scan_errors(s.scan, prof.position_mm, s.seed, p));
      else
        prof.signal_nA = wire_signal(prof.position_mm, r, h, starts.size(), s.wire);
      measure_profile(prof, s.wire, s.seed, p);
      res.profiles.push_back(std::move(prof));
    }
  }

  if (s.phases && !run.trimcoils.empty()) {
    check_phase_machine(run);
    TrackModel base = model;
    base.probes = {phase_line(base, s.phase.azimuth_deg)};
    std::vector<double> r0, p0;
    phase_history(run, base, s.track, r0, p0);
    for (size_t k = 0; k < run.trimcoils.size(); ++k)
      res.phases.push_back(phase_scan_on(run, base, k, s.track, s.phase, s.seed, r0, p0));
  }
  return res;
}

}  // namespace turnfit
