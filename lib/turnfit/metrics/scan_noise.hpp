// Correlated errors of a wire scan in a fit: the probe drive's error moves neighbouring turns
// together, so the turns of one probe are not independent. Their covariance, and the whitening
// that turns residuals with it into independent unit-variance ones.
#pragma once

#include <Eigen/Dense>
#include <string>
#include <vector>

#include "turnfit/metrics/metrics.hpp"

namespace turnfit {

/// The drive error of a probe's wire scan, as a fit models it (turnfit-problem(5) "scan_noise"):
/// a stationary process along the wire's travel of rms `drive_mm` and exponential correlation
/// over `corr_mm` (turnfit-synth(1) "Scan errors" draws it so). Two peaks of one probe at radii
/// r_i and r_j then share the error covariance drive^2 exp(-|r_i - r_j| / corr); peaks of
/// different probes share none. drive_mm 0: the turns are independent (the diagonal sigma alone).
struct ScanNoise {
  double drive_mm = 0;
  double corr_mm = 10;
  bool active() const { return drive_mm > 0; }
  /// The correlated covariance of two peaks at radii a and b [mm^2].
  double covariance(double a_mm, double b_mm) const;
};

/// Reads {"drive_mm": d, "corr_mm": l} (corr_mm optional, default 10), or the text "D" or "D,L"
/// of a command-line option; EX_DATAERR / EX_USAGE naming `where`.
ScanNoise scan_noise_from_text(const std::string& text, const std::string& where);

/// Whitening of the residuals of a set of measured points by their covariance
/// C = diag(sigma_i^2) + the scan noise's correlated part, one block per probe: C = L L^T
/// (Cholesky, L lower triangular in the points' order, i.e. by turn), and z = L^-1 e. Because L
/// is lower triangular in turn order, a turn's whitened residual depends on it and the probe's
/// earlier turns only. Without scan noise L = diag(sigma) and z_i = e_i / sigma_i exactly.
class Whitener {
 public:
  Whitener() = default;
  /// `points`: the measured points included (indices into meas.points, increasing); `sigma_mm`:
  /// per measured point (indexed like meas.points). EX_SOFTWARE for a sigma that is not positive.
  Whitener(const TurnTable& meas, const std::vector<size_t>& points, const std::vector<double>& sigma_mm,
           const ScanNoise& noise);
  /// Points included, in order (the rows of every vector and matrix below).
  size_t size() const { return size_; }
  bool diagonal() const { return diagonal_; }
  /// v <- L^-1 v (v over the included points).
  void whiten(Eigen::Ref<Eigen::VectorXd> v) const;
  /// Each column of M <- L^-1 column (M's rows: the included points).
  void whiten_columns(Eigen::Ref<Eigen::MatrixXd> M) const;
  /// v <- L v (back from whitened units to mm).
  void color(Eigen::Ref<Eigen::VectorXd> v) const;
  /// Each column of M <- L column.
  void color_columns(Eigen::Ref<Eigen::MatrixXd> M) const;
  /// Whitened residual of e (indexed like meas.points) over the included points.
  Eigen::VectorXd whitened(const std::vector<double>& e_full) const;

 private:
  struct Block {
    Eigen::Index begin = 0, n = 0;
    Eigen::MatrixXd L;  ///< lower Cholesky factor of the block's covariance
  };
  size_t size_ = 0;
  std::vector<size_t> points_;  ///< the included points
  bool diagonal_ = true;
  Eigen::VectorXd sigma_;     ///< per included point (diagonal case)
  std::vector<Block> blocks_;  ///< per probe (correlated case)
};

/// The covariance of the included points of one probe: sigma_i^2 on the diagonal plus the scan
/// noise's correlated part, radii r_mm.
Eigen::MatrixXd scan_covariance(const std::vector<double>& r_mm, const std::vector<double>& sigma_mm,
                                const ScanNoise& noise);

}  // namespace turnfit
