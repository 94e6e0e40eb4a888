// Diagnosis of a turn-pattern mismatch (turnfit-diagnose): after a fit of the design variables,
// where the residual lies and what shape it has, which effect of the catalogue
// (turnfit-machine(5) EFFECTS) explains it, modelled and refitted, with detection limits.
#pragma once

#include <Eigen/Dense>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "turnfit/optimize/localsearch.hpp"
#include "turnfit/optimize/turn_problem.hpp"

namespace turnfit {

/// One free parameter of a candidate effect, bound to keys of its machine-file entries.
struct EffectParam {
  std::string key;              ///< turnfit-machine(5) key it sets ("amplitude_T", "relative", ...)
  std::string unit;
  std::vector<size_t> entries;  ///< the candidate's entries it sets (the same value in each)
  double step = 0;              ///< finite-difference step of its linear signature
  double lower = 0, upper = 0;  ///< bounds in a refit
  double absent = 0;            ///< the value at which the effect is absent (or its shape's start)
};

/// A candidate: one effect of the catalogue at one place, with its free parameters.
struct Candidate {
  std::string type;                    ///< turnfit-machine(5) type
  std::string label;                   ///< for people: "field-harmonic n=1 at 3100 mm (width 500 mm)"
  nlohmann::json instance;             ///< what fixes the place: n, r_mm, width_mm, sector, cavity, probe, coils, sectors
  std::vector<nlohmann::json> entries; ///< machine-file effect entries, free keys at their absent values
  std::vector<EffectParam> params;     ///< linear parameters: screened, and fitted in a refit
  std::vector<EffectParam> shape;      ///< further parameters freed in the nonlinear refit (a bump's r_mm, width_mm)
  /// trimcoil-sectors: no continuous parameter; the entry is on or off and its signature is
  /// the sum of its coils' single-coil signatures (`atoms`, indices into the atom list).
  bool discrete = false;
  std::vector<size_t> atoms;
  /// A curved signature (one parameter): screened along a path, its signature at sizes of
  /// +-1/8 to +-2 times curve_step with the variables moved along the valley its tangent
  /// opens, instead of on the tangent at absent (0: linear, the tangent). A gap bow's is: at
  /// the crest its energy gain changes with the square of the bow, and the variables take up
  /// nearly all of the tangent.
  double curve_step = 0;
};

/// The catalogue of effects (turnfit-machine(5) EFFECTS) as candidates for this problem:
/// field-harmonic n = 0, 1, 2 on a grid of radii and widths over the measured radii (and
/// n = 1, 2 at every radius), sector-strength of each sector, gap-bow and voltage-tilt of each
/// cavity, probe-offset of each measured probe and injection-offset, each with only the
/// parameters no problem variable already sets (`not_candidates` gets the rest, with the
/// variables that represent them), and trimcoil-sectors of contiguous coil groups on the odd or
/// the even sectors (their atoms: one per coil and parity, `atoms` below). `types` limits the
/// types (empty: all). Effects the machine already has on the same element are not candidates.
struct Catalogue {
  std::vector<Candidate> candidates;
  std::vector<Candidate> atoms;           ///< trimcoil-sectors of single coils (the groups' building blocks)
  nlohmann::json not_candidates = nlohmann::json::array();  ///< [{type, instance, reason, variables}]
};
Catalogue effect_catalogue(const TurnPatternProblem& p, const std::vector<std::string>& types);

/// A trim-coil group (a trimcoil-sectors candidate) moved onto its sectors at the mean field
/// its coils had on all of them: each coil's bmax times N / |sectors| (2 for the odd or the
/// even sectors), which is where the diagnosis takes the group's signature column and starts its
/// refit. The variables fitted without the effect carry the group's mean field. The effect alone
/// would halve it, a change of millimetres in every turn that the variables then take back;
/// in a signature column (one finite step) the curvature of that round trip swamped the part
/// they cannot take back, the group's azimuthal pattern. (A blind tuning case: TC4-TC12 on the
/// even sectors at 1.1 mT screened at a gain of 0.09 in chi2, while single coils and an n = 2
/// bump gained 60-75.) At the same mean the column is the pattern.
/// `x` (the design of `vars`) gets the factor on each variable that sets nothing but bmax of
/// the group's coils, within the variable's bounds (a coil the bounds stop keeps part of its mean
/// change: the group as the problem allows it), and those indices are returned; the group's bmax
/// values in m's document get the factor too (they count for coils no variable sets, or that a
/// variable adds to); the caller revalidates m (the diagnosis appends the effect's entries next,
/// which does). A variable that also sets anything else is left alone. Any other candidate:
/// nothing changes.
std::vector<size_t> same_mean_field(const Candidate& c, Machine& m, const std::vector<TurnVariable>& vars,
                                    std::vector<double>& x);

/// Every effect type of the catalogue, in report order.
const std::vector<std::string>& catalogue_types();

/// The per-probe noise of a residual estimated from its own scatter, free of smooth structure:
/// second differences along consecutive turns, d_i = e_{i-1} - 2 e_i + e_{i+1}, have variance
/// s_{i-1}^2 + 4 s_i^2 + s_{i+1}^2 with s_i^2 = s_p^2 + u_i^2 (u_i the peak's own uncertainty,
/// peakfind's r_err_mm, 0 without it). s_p is found by the method of moments on the median
/// (robust to single bad peaks): the median of d_i^2 / var_i is that of chi2 with one degree of
/// freedom, 0.4549. With peak uncertainties, sigma_i^2 = s_p^2 + c_p^2 u_i^2: for each trust c_p
/// on a grid (0.5-3) s_p from that median condition, and c_p by the likelihood of the second
/// differences (each capped at 4 sigma); with fewer than 40 differences c_p = 1. A smooth trend
/// (any polynomial of degree 1 over three turns) leaves no second difference; an oscillation of
/// q cycles per turn is amplified by 4 sin^2(pi q).
/// With the probe drive's correlated error (`scan`, the problem's scan_noise), each second
/// difference's variance gains drive^2 (6 - 4 rho_01 - 4 rho_12 + 2 rho_02), rho_ab =
/// exp(-|r_a - r_b| / corr) of the three turns' radii, and s_p is the independent part beside it
/// (the drive error itself is given, not estimated: one scan cannot tell a slow drive error
/// from a smooth effect). The outlier test then counts the drive error in the turn's sigma.
struct NoiseEstimate {
  std::vector<std::string> probes;
  std::vector<double> scatter_mm;     ///< s_p per probe
  std::vector<double> trust;          ///< c_p per probe (1 without peak uncertainties)
  std::vector<size_t> differences;    ///< second differences it rests on
  std::vector<double> sigma_mm;       ///< per measured point: sqrt(s_p^2 + c_p^2 u_i^2)
  std::vector<unsigned char> outlier; ///< per point: single outliers (beyond 5 sigma of the running median of 5)
  ScanNoise scan;                     ///< the correlated drive error beside sigma_mm (inactive: none)
};
NoiseEstimate estimate_noise(const TurnTable& measured, const std::vector<double>& residual_mm,
                             const std::vector<unsigned char>& matched, const ScanNoise& scan = ScanNoise{},
                             double floor_mm = 1e-4);

/// Radial tune against the radius of the closed orbit (its mean radius), for the oscillation
/// search: closed orbits of the machine's field at energies over its radius range.
struct TuneTable {
  std::vector<double> r_mm, nu_r;
  /// nu_r at radius r (linear interpolation, held at the ends); NaN when the table is empty.
  double at(double r_mm) const;
};
TuneTable radial_tunes(const Machine& m, unsigned threads);

/// Where a residual is significant and what shape it has, per probe: an offset, a smooth trend
/// (Legendre polynomials in turn number, degree by BIC), a coherent oscillation at the radial
/// tune's fractional frequency (phase advance 2 pi nu_r(r) a turn, amplitude linear in the
/// turn), a step, single outliers, and the turn and radius ranges where the smoothed residual
/// exceeds its noise. Each shape's significance is its chi2 gain against the noise, beyond
/// `threshold` plus k ln N (k its parameters). Returns the JSON list and whether anything was
/// significant; chi2 and dof over the used points.
struct Located {
  nlohmann::json findings = nlohmann::json::array();
  bool significant = false;
  double chi2 = 0;
  size_t points = 0;
  double chi2_p_value = 1;  ///< of chi2 against its degrees of freedom (Wilson-Hilferty)
};
Located locate(const TurnTable& measured, const std::vector<double>& residual_mm,
               const std::vector<unsigned char>& matched, const NoiseEstimate& noise, const TuneTable& tunes,
               double dof, double threshold);

/// How the diagnosis runs.
struct DiagnoseSettings {
  unsigned threads = 0;
  std::vector<std::string> types;   ///< effect types to try (empty: all)
  LocalSearchSettings fit;          ///< the base fit (localsearch's defaults, no minimax polish)
  /// Extra chi2 an effect must gain beyond BIC's k ln N (look-elsewhere over ~100 candidates:
  /// a k = 2 candidate on pure noise passes k ln N + 10 with probability ~3e-5).
  double margin = 10;
  double ambiguity = 6;             ///< Delta BIC within which a competitor is ambiguous (Kass and Raftery: "strong" evidence)
  int max_effects = 4;
  int refits = 3;                   ///< nonlinear refits of the strongest distinct candidates per round
  /// Other instances of a picked candidate's type (sectors, cavities, coil groups, bumps) whose
  /// linear screen gains at least `sibling_fraction` of that type's best pick are refitted too, at
  /// most `siblings` of them: the screen ranks look-alike instances by less than its own
  /// linearization error (0: none).
  int siblings = 6;
  /// A fit that ended for want of iterations is taken on from where it stopped, at most this
  /// many times (0: never): the state before each screen, the null refits, the elimination fits
  /// and the refits below.
  int polish_passes = 3;
  /// Each round refits the model as it is, as a candidate's refit is made (its own centroid
  /// shift, the refits' settings), and measures every candidate's gain against it.
  bool null_refit = true;
  /// Refits taken on to convergence per round: those within `polish_window` in chi2 of the
  /// round's best and those that gained less than `screen_trust` of their screen.
  int polish_refits = 8;
  double polish_window = 30;
  double sibling_fraction = 0.5;
  /// Round 1: a refitted candidate whose refit from the base fit gains less than
  /// `from_start_shortfall` times its linearized screen's gain, and whose signature the
  /// variables take up all but `from_start_visible` of, is fitted a second time from the
  /// machine's values (0: never).
  double from_start_shortfall = 0.9;
  double from_start_visible = 0.1;
  /// Round 1: while the best refit gains less than `screen_trust` times the linear screen of
  /// the next distinct candidate, that one is refitted too, at most `extra_refits` (0: never).
  int extra_refits = 4;
  double screen_trust = 0.5;
  /// Round 1: when two or more refits gain at least `whole_fraction` of the round's best gain,
  /// each of them (whose signature the variables take up all but `from_start_visible` of) is
  /// fitted whole as well, the best first, at most `whole_fits` (0: never): the base fit may have
  /// half absorbed a large effect, and from there the true instance's valley is out of reach.
  int whole_fits = 10;
  double whole_fraction = 0.7;
  /// Round 1: when a whole fit (from the machine's values) comes within `challenge_fraction`
  /// of the round's best chi2 gain, up to `challengers` refits within that fraction that had
  /// none (and whose signature the variables take up all but `from_start_visible` of) are
  /// fitted whole as well, so that look-alikes are compared at their valley floors (0: never).
  int challengers = 4;
  double challenge_fraction = 0.1;
  /// Every round: the unrefitted ring neighbours (sector k - 1 and k + 1) of each sector whose
  /// refit comes within `neighbour_fraction` of the round's best chi2 gain are refitted too, at
  /// most `neighbour_refits` (0: never): two sectors either side of the truth fit nearly as
  /// well as it does, and the screen may not have ranked the truth high enough to be refitted.
  int neighbour_refits = 2;
  double neighbour_fraction = 0.1;
  int folds = 5;                    ///< interleaved held-out folds
  /// Round 1: the linear detection limit of each continuous candidate that does not pass,
  /// checked nonlinearly at up to this many sizes (0: linear limits only): the base model with
  /// the effect at that size is taken as the measurement, the variables are fitted to it, and
  /// the chi2 they cannot take up is compared with the threshold (a refit per size: costly).
  int limit_checks = 0;
  /// Where the diagnosis's fits hold the weak prior (variables without a problem prior; a
  /// tenth of a bound range): false at each fit's start, localsearch's own rule (the base fit
  /// at --start, a refit at its candidate's linear step, a fit taken on where the last
  /// stopped); true at the machine's values for the base fit and every fit after it, where the
  /// linear model holds it, so that every fit minimizes one objective. True by default since
  /// 2026-11-30: in 15 paired blind cases (11 with free variables, where it matters) the two
  /// settings differed in 3 outcomes, each time with the machine's centre naming the concealed
  /// effect right (bench/RESULTS.md, "The weak prior's centre: run AA").
  bool weak_prior_at_machine = true;
  bool verbose = false;
  std::function<void(const std::string&)> log;  ///< progress lines (may be empty)
};

/// A candidate that passed beside a selected one in its round (a refit, or a screen whose refit
/// fell short or never was).
struct Rival {
  nlohmann::json info;  ///< label, type, instance, from ("refit" or "screen")
  double gap_chi2 = 0;  ///< the selected one's chi2 gain less this one's
  double dchi2 = 0;     ///< this one's chi2 gain
  int k = 0;            ///< its parameters
  int group = 0;        ///< rivals of one distinct effect share it (a refit and its screen, bumps within a width)
};

/// A curved candidate's path (one parameter whose signature is not linear in it, a gap bow's):
/// its signature sampled at sizes b (ascending, one of them 0 with a zero column), the columns
/// of S in that order, linear between samples; the signature at size x (clamped to the ends).
Eigen::VectorXd path_at(const Eigen::MatrixXd& S, const std::vector<double>& b, double x);

/// The minimum of ||u + s(x)||^2 along a path (PS: its columns projected off the variables'
/// span, as u is), exact on each segment, where it is a quadratic in x; `info` is that
/// segment's curvature (the information on x at unit noise). Never above ||u||^2 (x = 0).
struct PathMin {
  double x = 0, g = 0, info = 0;
};
PathMin path_min(const Eigen::VectorXd& u, const Eigen::MatrixXd& PS, const std::vector<double>& b);

/// The size, whatever its sign, from which a path's signature gains T in chi2: the larger of
/// the first crossings on each side of 0. NaN when one side stays below T over the sizes sampled.
/// With `sides`: each side's crossing, the positive side's first (NaN where it stays below T).
double path_limit(const Eigen::MatrixXd& PS, const std::vector<double>& b, double T, double* sides = nullptr);

/// The rivals ambiguous with a selected effect of k_selected parameters when every chi2 is divided
/// by the overdispersion c (at least 1; quasi-likelihood, QBIC = chi2 / c + k ln N): those that
/// pass on their own on that scale (Delta QBIC above margin) and whose QBIC lies within `window`
/// of the selected one's, the first of each group in the order given. Each entry is the rival's
/// info with its delta_bic on that scale.
nlohmann::json ambiguous_rivals(const std::vector<Rival>& rivals, int k_selected, double overdispersion, double log_n,
                                double margin, double window);

/// A fit's figures with the diagnosis's noise.
struct FitFigures {
  double linf_mm = 0, rms_mm = 0, chi2 = 0, chi2_per_dof = 0, dof = 0;
  double held_out_chi2_per_point = 0;  ///< cross-validated (linearized, interleaved folds), with that round's noise
  size_t points = 0;
  double held_out_rms_mm = 0;          ///< the same predictions' errors in mm (independent of the noise estimate)
};

/// What the diagnosis found (the report's content; the app writes it).
struct Diagnosis {
  std::string verdict;                 ///< nothing-missing | missing-physics | unexplained
  NoiseEstimate noise;                 ///< the last round's (estimated anew each round from the residual left)
  std::vector<std::vector<double>> noise_rounds;  ///< each round's per-probe scatter
  double before_first_noise_chi2 = 0;  ///< the base fit's chi2 with the first round's noise
  Located located_before, located_after;
  nlohmann::json effects = nlohmann::json::array();     ///< selected: machine-file entries with sigma and scores
  nlohmann::json ambiguous = nlohmann::json::array();  ///< judged on the final model's scale (overdispersion)
  /// The final model's chi2 per degree of freedom, at least 1: the elimination's losses and the
  /// ambiguity's distances are divided by it (quasi-likelihood).
  double overdispersion = 1;
  /// How the effects' sigmas were formed (the final fit's sandwich: per probe the residual's
  /// lag-1 correlation and the median of the variables' kernel bandwidths), and what bounds the
  /// effects' bias_unseen (each catalogue effect not named, at its detection limit, taken up by
  /// the final model's linear refit; each candidate row's bias_at_limit holds its moves); null
  /// without a selected effect.
  nlohmann::json uncertainty;
  nlohmann::json candidates = nlohmann::json::array();  ///< every candidate tried, with its scores
  nlohmann::json not_candidates = nlohmann::json::array();
  nlohmann::json rounds = nlohmann::json::array();      ///< greedy rounds: refits and choice
  nlohmann::json eliminations = nlohmann::json::array(); ///< backward elimination: each effect taken out, its chi2 loss
  nlohmann::json variables_after = nlohmann::json::array();  ///< design variables of the final fit
  FitFigures before, after;
  LocalSearchResult base_fit;          ///< the base fit of the design variables
  std::vector<double> x_base;          ///< its design (with the diagnosis's noise)
  std::vector<double> x_after;         ///< the design variables after the refit with the effects
  nlohmann::json machine_after;        ///< the machine document with the effects and x_after
  std::vector<double> residual_before_mm, residual_after_mm;  ///< per measured point (NaN: unmatched)
  /// Per selected effect: its own signature at the fitted size [mm] per measured point (the
  /// after-model minus the after-model without it, design variables refitted linearly).
  std::vector<std::vector<double>> signatures_mm;
  size_t evaluations = 0;
  double wall_s = 0;
  /// Designs and wall time of round 1's nonlinear checks of the detection limits.
  size_t limit_check_designs = 0;
  double limit_check_wall_s = 0;
  bool weak_prior_at_machine = false;  ///< the setting the fits ran with (DiagnoseSettings)
};

/// Diagnoses problem p from design x0: base fit, noise, locate, screen every candidate in the
/// model linearized at the fit, refit the strongest nonlinearly, select greedily by BIC and
/// held-out gain, refit. EX_DATAERR if x0 cannot be simulated.
Diagnosis diagnose(TurnPatternProblem& p, const std::vector<double>& x0, const DiagnoseSettings& s);

}  // namespace turnfit
