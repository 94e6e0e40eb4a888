// Least-squares rational fits y ~ f(x)/g(x) (Ceres Levenberg-Marquardt): the trim coil
// phase-shift model of the paper (Sec. II.C, Eq. 2), with a root-free denominator.
#pragma once

#include <Eigen/Dense>
#include <limits>
#include <string>
#include <vector>

namespace turnfit {

/// What the rational function describes.
enum class RationalModel {
  value,     ///< the data themselves: y(x) = f/g (the paper's fit of delta sin(phi), Eq. 2)
  integral,  ///< the data's negative slope: y(x) = c - integral_{-1}^{x} f/g dx' (a field bump
             ///< fitted through the phase it leaves; f/g then decays where the field does)
  response,  ///< y_i = c + sum_j K_ij (f/g)(x_j): f/g a field sampled on a grid, K a known linear
             ///< response (e.g. tracked phase shifts per tesla of each grid basis function)
};

/// The linear response of the response model: rows = the data points given to fit_rational (all
/// of them, also those outside the window), columns = the grid radii.
struct LinearResponse {
  std::vector<double> r_grid;  ///< radii where f/g is sampled (units of r), inside the window
  Eigen::MatrixXd K;           ///< data points x grid
};

/// A rational function fitted on a window [r_lo, r_hi], held in the window's scaled variable
/// x = (r - centre) / half_width (x in [-1, 1]): monomials in x are well conditioned, monomials
/// in r at r ~ 4 m are not. f(x) = sum a_k x^k, g(x) = 1 + sum_{k>=1} b_k x^k (b_0 = 1 fixes the
/// scale that f/g leaves free).
struct RationalFit {
  RationalModel model = RationalModel::value;  ///< what f/g describes
  double offset = 0;            ///< integral model: the constant c (units of y)
  int n = 0;                    ///< numerator degree
  int m = 0;                    ///< denominator degree
  double centre = 0;            ///< window centre (units of the abscissa, e.g. mm)
  double half_width = 1;        ///< window half width (same units)
  std::vector<double> a;        ///< numerator coefficients in x (units of y), n + 1 of them
  std::vector<double> b;        ///< denominator coefficients in x, b[0] = 1, m + 1 of them
  Eigen::MatrixXd covariance;   ///< of (a_0..a_n, b_1..b_m[, c]): s^2 (J^T J)^-1
  std::vector<double> sigma;    ///< square roots of its diagonal, same order
  size_t points = 0;            ///< data points in the window
  double rss = 0;               ///< residual sum of squares
  double rms = 0;               ///< residual rms
  double max_abs = 0;           ///< largest |residual|
  double sigma_y = 0;           ///< residual standard error sqrt(rss / (N - p)) (0 if N = p)
  double condition = 0;         ///< 2-norm condition number of the Jacobian at the solution
  double min_denominator = 0;   ///< smallest g(x) on [-1, 1]
  double pole_distance = 0;     ///< distance (in x) from the nearest root of g to [-1, 1]
  double rss_at_pole_bound = std::numeric_limits<double>::quiet_NaN();  ///< a lower rss held at the
                                ///< pole bound, when the fit returned is a resolvable local optimum
  int iterations = 0;           ///< Levenberg-Marquardt iterations of the winning start
  std::string start;            ///< which start won: polynomial, linearized or lower degree
  std::vector<double> fitted_r;  ///< the data radii in the window
  std::vector<double> fitted_y;  ///< the fitted curve there
  double aicc = 0;              ///< corrected Akaike criterion (Gaussian residuals)
  double bic = 0;               ///< Bayesian criterion

  /// Number of free parameters, (n + 1) + m (+ 1 for the integral model's constant).
  int parameters() const { return n + 1 + m + (model != RationalModel::value ? 1 : 0); }
  /// Scaled abscissa of r.
  double x_of(double r) const { return (r - centre) / half_width; }
  /// The rational f/g and its first two derivatives with respect to r (not x).
  void eval(double r, double& q, double& dq_dr, double& d2q_dr2) const;
  /// The fitted curve y at r (f/g, or c minus its integral; the response model interpolates
  /// its fitted points, NaN outside them).
  double value(double r) const;
  /// Slope dy/dr of the fitted curve and its derivative d2y/dr2; for the response model the
  /// field -(f/g) / half_width (as the integral model's, so the field shape code is shared).
  void slope(double r, double& dy_dr, double& d2y_dr2) const;
  /// Standard deviation of the fitted value at r from the parameter covariance (delta method).
  double value_sigma(double r) const;
  /// Gradient of dy/dr (per unit of r) with respect to the parameters: with the covariance it
  /// gives the uncertainty of the field shape, which follows -dy/dr.
  Eigen::VectorXd slope_gradient(double r) const;
};

/// Fits f/g of degrees n/m to the points with r_lo <= r <= r_hi. Deterministic starts (no luck):
/// the polynomial least-squares fit (g = 1), the linearized fit f - y g = 0 reweighted by
/// 1/g (Sanathanan-Koerner), the same degree's numerator over every lower denominator degree
/// (a homotopy from the polynomial, so a higher m never fits worse), and any `starts` given
/// (e.g. a lower-degree fit, padded with zeros); if every start ends held at the pole bound
/// below, `extra_starts` more from denominators with roots placed away from the window (fixed seed) look
/// for a resolvable local optimum, which is returned (rss_at_pole_bound then says what the
/// unresolvable one reached). Each start runs Ceres' Levenberg-Marquardt
/// with analytic derivatives; a trial step whose denominator touches zero anywhere on
/// [r_lo, r_hi], or a root of g (complex ones too) within the median data spacing of the
/// window, is refused (Ceres treats it as an infinite cost and shrinks its region): the result
/// keeps g > 0 on the window and no feature narrower than the samples can resolve; the winner's
/// roots are checked exactly at the end.
/// Throws turnfit::Error (EX_DATAERR) with a complete message: fewer points than parameters,
/// non-increasing or duplicate r, no root-free convergence, or an optimum held at that bound
/// (the data ask for an unresolvable feature; the derivative of such a fit, the field, spikes).
RationalFit fit_rational(const std::vector<double>& r, const std::vector<double>& y, double r_lo, double r_hi,
                         int n, int m, const std::vector<RationalFit>& starts = {}, int max_iterations = 400,
                         RationalModel model = RationalModel::value, const LinearResponse* response = nullptr,
                         int extra_starts = 64);

/// Coefficients of p((r - centre) / half_width) as a polynomial in r (expanded in long double).
std::vector<double> polynomial_in_r(const std::vector<double>& c_x, double centre, double half_width);

/// Real roots of the polynomial c_0 + c_1 x + ... in [lo, hi] (companion matrix eigenvalues,
/// polished by Newton).
std::vector<double> real_roots_in(const std::vector<double>& c, double lo, double hi);

}  // namespace turnfit
