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

/// Fits the noiseless scans of coils TC3-TC17 with the tracked and the paper model on `model`;
/// checks each tracked shape against `each`, the mean against `mean`, the strengths within
/// `strength` (relative), and that the paper model's mean error is `paper_factor` times larger.
void close_loop(const Machine& truth, const Machine& model, const std::vector<PhaseData>& scans, double each,
                double mean, double strength, double paper_factor, int refusals_allowed) {
  TcFitOptions tracked;
  tracked.model = "tracked";
  tracked.degrees = "2/4";
  TcFitOptions paper;
  paper.model = "paper";
  paper.degrees = "2/4";
  std::map<std::string, std::vector<double>> cache;
  double sum_tracked = 0, sum_paper = 0;
  int n = 0, refused = 0;
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
      ++refused;
      continue;
    }
    const double et = shape_rms(ct, *tc), ep = shape_rms(cp, *tc);
    // The strength: the fitted peak is the test excitation the scan applied, in tesla; coils
    // TC6-TC14 sit on the odd sectors only (a concealed effect), so they show half of it.
    double q, dq, d2q;
    ct.fit.eval(ct.peak_r_mm, q, dq, d2q);
    const int k = std::stoi(d.name.substr(2));
    const double expect = (k >= 6 && k <= 14 ? 0.5 : 1.0) * d.excitation_T;
    INFO(d.name << ": tracked shape rms " << et << ", paper " << ep << ", peak field " << q << " T (expected " << expect
                << ")");
    CHECK(et < each);
    CHECK(q == Approx(expect).epsilon(strength));
    sum_tracked += et;
    sum_paper += ep;
    ++n;
  }
  CHECK(refused <= refusals_allowed);
  REQUIRE(n > 0);
  CAPTURE(n, sum_tracked / n, sum_paper / n);
  CHECK(sum_tracked / n < mean);
  // The local relation B ~ -d(delta sin phi)/dr of the paper's model misses the lag of the phase
  // behind the field and the oscillation a coil starts.
  CHECK(sum_paper / n > paper_factor * sum_tracked / n);
}

}  // namespace

TEST_CASE("tc-fit closes the loop on ring8: the tracked model recovers the truth coils' shapes and strengths",
          "[tcfit][loop]") {
  Machine truth = load_machine(kRing8 + "truth-machine.json");
  apply_dvars_file(truth, kRing8 + "truth-dvars.json");
  const std::vector<PhaseData> scans = noiseless_scans(truth);
  Machine model = load_machine(kRing8 + "machine.json");
  SECTION("the nominal model (the first pass: voltages, injection, coil settings not yet fitted)") {
    close_loop(truth, model, scans, 0.09, 0.06, 0.2, 1.4, 1);
  }
  SECTION("the model at the truth's design-variable values (the pass after a perfect optimization)") {
    apply_dvars_file(model, kRing8 + "truth-dvars.json");
    close_loop(truth, model, scans, 0.05, 0.035, 0.12, 2.5, 0);
  }
}
