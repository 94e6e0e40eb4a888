// Closing the loop (issue 5): ring8's truth coils -> phase scans (turnfit-synth) -> tc-fit ->
// fitted coils in the model; their fields against the truth coils' fields.
#include <catch2/catch.hpp>
#include <algorithm>
#include <cmath>
#include <map>

#include "turnfit/machine/machine.hpp"
#include "turnfit/synth/synth.hpp"
#include "turnfit/trimcoil/tcfit_app.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"

using namespace turnfit;

namespace {

const std::string kRing8 = std::string(TURNFIT_SOURCE_SHARE) + "/ring8/";

/// RMS over the window of (fitted shape - truth shape), the truth normalized to its peak on the
/// window (tc-fit normalizes there too: both peak at +1).
double shape_rms(const CoilFit& c, const TrimCoil& truth) {
  TrimCoil t = truth;
  t.bmax_T = 1;
  const TrimCoilField tf(t, 8);
  std::vector<double> r, st;
  double peak = 0;
  for (double x = c.r_lo_mm; x <= c.r_hi_mm + 1e-9; x += 2) {
    double s, ds;
    tf.shape_exact(x * 1e-3, s, ds);
    r.push_back(x);
    st.push_back(s);
    if (std::fabs(s) > std::fabs(peak)) peak = s;
  }
  double sum = 0;
  for (size_t i = 0; i < r.size(); ++i) {
    double s, ds;
    fitted_shape(c, r[i], s, ds);
    sum += std::pow(s - st[i] / peak, 2);
  }
  return std::sqrt(sum / static_cast<double>(r.size()));
}

/// Noiseless phase scans of every truth coil (the truth machine at its design-variable values).
std::vector<PhaseData> noiseless_scans(const Machine& truth) {
  const TrackSettings st = machine_track_settings(truth);
  PhaseModel pm;
  pm.noise_deg = 0;
  std::vector<PhaseData> out;
  for (size_t k = 0; k < truth.trimcoils.size(); ++k) {
    const PhaseScan ps = phase_scan(truth, k, st, pm, 1);
    PhaseData d;
    d.name = ps.coil;
    d.source = "synth";
    d.excitation_T = ps.excitation_T;
    d.r_mm = ps.r_mm;
    d.dsinphi = ps.dsinphi_true;
    for (size_t i = 0; i < d.r_mm.size(); ++i) d.lines.push_back(static_cast<long>(i + 1));
    out.push_back(d);
  }
  return out;
}

const TrimCoil* named(const std::vector<TrimCoil>& v, const std::string& n) {
  for (const auto& t : v)
    if (t.name == n) return &t;
  return nullptr;
}

struct CoilOutcome {
  std::string name;
  double tracked_rms, paper_rms, peak_T, expect_T;
};

struct LoopOutcome {
  std::vector<CoilOutcome> coils;
  int refused = 0;
  double mean_tracked = 0, mean_paper = 0;
};

/// Fits the noiseless scans of coils TC3-TC17 with the tracked and the paper model on `model`:
/// each fitted shape against the truth coil's, and the tracked fit's peak field against the
/// test excitation the coil saw in the truth.
LoopOutcome close_loop(const Machine& truth, const Machine& model, const std::vector<PhaseData>& scans) {
  TcFitOptions tracked;
  tracked.model = "tracked";
  tracked.degrees = "2/4";
  TcFitOptions paper;
  paper.model = "paper";
  paper.degrees = "2/4";
  std::map<std::string, std::vector<double>> cache;
  LoopOutcome out;
  for (const PhaseData& d : scans) {
    // TC1, TC2 and TC18 reach beyond the scanned radii (the beam starts at 2.04 m and leaves at
    // 4.43 m): their windows are cut where the field is still large.
    if (d.name == "TC1" || d.name == "TC2" || d.name == "TC18") continue;
    const TrimCoil* mc = named(model.trimcoils, d.name);
    const TrimCoil* tc = named(truth.trimcoils, d.name);
    REQUIRE(mc);
    REQUIRE(tc);
    const double lo = std::max(mc->rmin_mm, d.r_mm.front()), hi = std::min(mc->rmax_mm, d.r_mm.back());
    const LinearResponse lr = coil_response(model, mc, d.r_mm, lo, hi, 10, 0, 2, cache);
    const CoilFit ct = fit_coil(d, tracked, mc, nullptr, &lr);
    const CoilFit cp = fit_coil(d, paper, mc);
    INFO(d.name << ": " << ct.error << " " << cp.error);
    REQUIRE(cp.error.empty());
    if (!ct.error.empty()) {
      ++out.refused;
      continue;
    }
    // The strength: the fitted peak is the test excitation the scan applied, in tesla; coils
    // TC6-TC14 sit on the odd sectors only (a concealed effect), so they show half of it.
    double q, dq, d2q;
    ct.fit.eval(ct.peak_r_mm, q, dq, d2q);
    const int k = std::stoi(d.name.substr(2));
    out.coils.push_back({d.name, shape_rms(ct, *tc), shape_rms(cp, *tc), q,
                         (k >= 6 && k <= 14 ? 0.5 : 1.0) * d.excitation_T});
  }
  REQUIRE(!out.coils.empty());
  for (const auto& c : out.coils) {
    out.mean_tracked += c.tracked_rms / static_cast<double>(out.coils.size());
    out.mean_paper += c.paper_rms / static_cast<double>(out.coils.size());
  }
  return out;
}

/// The loop on ring8, once per process: with the nominal model (at_truth_dvars false) or with
/// the model at the truth's design-variable values.
const LoopOutcome& ring8_loop(bool at_truth_dvars) {
  static std::map<bool, LoopOutcome> done;
  auto it = done.find(at_truth_dvars);
  if (it != done.end()) return it->second;
  Machine truth = load_machine(kRing8 + "truth-machine.json");
  apply_dvars_file(truth, kRing8 + "truth-dvars.json");
  static const std::vector<PhaseData> scans = noiseless_scans(truth);
  Machine model = load_machine(kRing8 + "machine.json");
  if (at_truth_dvars) apply_dvars_file(model, kRing8 + "truth-dvars.json");
  return done[at_truth_dvars] = close_loop(truth, model, scans);
}

void report(const LoopOutcome& o) {
  for (const auto& c : o.coils)
    UNSCOPED_INFO(c.name << ": tracked shape rms " << c.tracked_rms << ", paper " << c.paper_rms << ", peak field "
                         << c.peak_T << " T (expected " << c.expect_T << ")");
  UNSCOPED_INFO("fitted " << o.coils.size() << ", refused " << o.refused << ", mean rms tracked " << o.mean_tracked
                          << ", paper " << o.mean_paper);
}

}  // namespace

TEST_CASE("tc-fit closes the loop on ring8: at the truth's design variables the tracked model recovers the "
          "truth coils' shapes to the documented accuracy",
          "[tcfit][loop]") {
  // The pass after a perfect optimization: the model at the truth's design-variable values,
  // noiseless scans. Tolerances: bench/RESULTS.md, "Closing the loop", row "noiseless, truth +
  // its design variables" (referenced by turnfit-tc-fit(1)): mean shape rms 0.060 with the
  // tracked model, 0.096 with the paper's; 17 of 18 coils fitted. Those figures are from
  // --degrees auto over all coils; this loop fits TC3-TC17 at 2/4, a subset the documented
  // accuracy covers. Was a mean below 0.035 and a paper model 2.5 times worse (no source).
  // Measured: 0.026 and 0.085 (3.2 times), none refused. Per-coil figures, strengths and the
  // nominal model, which no page documents, are in the [regression] case below.
  const LoopOutcome& o = ring8_loop(true);
  report(o);
  CHECK(o.refused <= 1);            // 17 of 18 fitted
  CHECK(o.mean_tracked < 0.060);    // the documented mean, tracked model
  CHECK(o.mean_paper < 0.096);      // the documented mean, paper model
  // The paper's local relation B ~ -d(delta sin phi)/dr misses the lag of the phase behind the
  // field and the oscillation a coil starts: documented 0.096 against 0.060, 1.6 times.
  CHECK(o.mean_paper > 1.6 * o.mean_tracked);
  // The concealed effect shows in the strengths: bench/RESULTS.md (ten noisy seeds) has TC6-TC14,
  // on odd sectors only in the truth, at 0.26-0.35 mT against 0.55-0.74 mT for the all-sector
  // coils: the largest of the first at most 0.35/0.55 = 0.64 of the smallest of the second.
  double max_odd = 0, min_all = 1;
  for (const auto& c : o.coils) {
    const int k = std::stoi(c.name.substr(2));
    if (k >= 6 && k <= 14)
      max_odd = std::max(max_odd, c.peak_T);
    else
      min_all = std::min(min_all, c.peak_T);
  }
  CAPTURE(max_odd, min_all);
  CHECK(max_odd < 0.64 * min_all);
}

TEST_CASE("tc-fit closes the loop on ring8: per-coil shapes and strengths, nominal and at the truth's design "
          "variables (regression)",
          "[tcfit][loop][regression][heavy]") {
  // Values from this loop's own output (lib/ of this commit; TC3-TC17, --degrees 2/4, noiseless
  // scans), not an independent reference: no page documents per-coil shape errors, the tracked
  // model's strengths on noiseless scans of the truth at 2/4, or the nominal model (the first
  // pass, before voltages, injection and coil settings are fitted). Trusted because at the
  // truth's design variables the same loop meets the documented means (case above) and the
  // strengths show the concealed odd-sector effect; the nominal model differs from the truth
  // by its design variables, so it does worse. Guards: per-coil shapes and strengths (a fit
  // that trades one coil for another keeps the mean), and the nominal pass. Bounds: the
  // measured worst value plus about 10% of it, for rounding differences between compilers over
  // 182 turns of tracking and a nonlinear fit (no measured spread: an allowance, not a source).
  // Was each 0.09/0.05, mean 0.06/0.035, strengths 20%/12%, paper 1.4/2.5 times (no source).
  SECTION("the nominal model") {
    // Measured: each <= 0.0771 (TC15), mean 0.0462, strengths within 17.5% (TC15 0.588 mT; the
    // man page's noise-free figures at --degrees auto: TC15 0.54 mT), paper 1.68 times the mean,
    // one coil refused.
    const LoopOutcome& o = ring8_loop(false);
    report(o);
    CHECK(o.refused <= 1);
    for (const auto& c : o.coils) {
      INFO(c.name);
      CHECK(c.tracked_rms < 0.085);
      CHECK(c.peak_T == Approx(c.expect_T).epsilon(0.19));
    }
    CHECK(o.mean_tracked < 0.051);
    CHECK(o.mean_paper > 1.5 * o.mean_tracked);
  }
  SECTION("the model at the truth's design-variable values") {
    // Measured: each <= 0.0386 (TC6), mean 0.0265, strengths within 8.1% (TC6), paper 3.20
    // times the mean, none refused.
    const LoopOutcome& o = ring8_loop(true);
    report(o);
    CHECK(o.refused == 0);
    for (const auto& c : o.coils) {
      INFO(c.name);
      CHECK(c.tracked_rms < 0.042);
      CHECK(c.peak_T == Approx(c.expect_T).epsilon(0.09));
    }
    CHECK(o.mean_tracked < 0.029);
    CHECK(o.mean_paper > 2.9 * o.mean_tracked);
  }
}
