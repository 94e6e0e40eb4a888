// Covariance of a probe's turns under the scan's drive error, and whitening by it.
#include "turnfit/metrics/scan_noise.hpp"

#include <cmath>
#include <cstdlib>

#include "turnfit/io/error.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

double ScanNoise::covariance(double a_mm, double b_mm) const {
  if (!active()) return 0;
  return drive_mm * drive_mm * std::exp(-std::fabs(a_mm - b_mm) / corr_mm);
}

ScanNoise scan_noise_from_text(const std::string& text, const std::string& where) {
  ScanNoise s;
  auto number = [&](const std::string& t) {
    double v = 0;
    if (!parse_decimal(t, v))
      throw usage_error(where + ": " + quote(t) + " is not a number (expected DRIVE_MM or DRIVE_MM,CORR_MM)");
    return v;
  };
  const size_t comma = text.find(',');
  s.drive_mm = number(text.substr(0, comma));
  if (comma != std::string::npos) s.corr_mm = number(text.substr(comma + 1));
  if (s.drive_mm < 0) throw usage_error(where + ": the drive error's rms must not be negative");
  if (!(s.corr_mm > 0)) throw usage_error(where + ": the correlation length must be positive");
  return s;
}

Eigen::MatrixXd scan_covariance(const std::vector<double>& r_mm, const std::vector<double>& sigma_mm,
                                const ScanNoise& noise) {
  const auto n = static_cast<Eigen::Index>(r_mm.size());
  Eigen::MatrixXd C(n, n);
  for (Eigen::Index a = 0; a < n; ++a)
    for (Eigen::Index b = 0; b <= a; ++b) {
      double c = noise.covariance(r_mm[static_cast<size_t>(a)], r_mm[static_cast<size_t>(b)]);
      if (a == b) c += sigma_mm[static_cast<size_t>(a)] * sigma_mm[static_cast<size_t>(a)];
      C(a, b) = C(b, a) = c;
    }
  return C;
}

Whitener::Whitener(const TurnTable& meas, const std::vector<size_t>& points, const std::vector<double>& sigma_mm,
                   const ScanNoise& noise)
    : size_(points.size()), points_(points), diagonal_(!noise.active()) {
  for (size_t i : points)
    if (!(sigma_mm[i] > 0) || !std::isfinite(sigma_mm[i]))
      throw Error(ExitCode::software, "Whitener: a sigma that is not positive");
  if (diagonal_) {
    sigma_.resize(static_cast<Eigen::Index>(size_));
    for (size_t k = 0; k < size_; ++k) sigma_[static_cast<Eigen::Index>(k)] = sigma_mm[points[k]];
    return;
  }
  size_t k = 0;
  while (k < size_) {
    const int probe = meas.points[points[k]].probe;
    size_t e = k;
    std::vector<double> r, s;
    while (e < size_ && meas.points[points[e]].probe == probe) {
      r.push_back(meas.points[points[e]].r_mm);
      s.push_back(sigma_mm[points[e]]);
      ++e;
    }
    Block b;
    b.begin = static_cast<Eigen::Index>(k);
    b.n = static_cast<Eigen::Index>(e - k);
    Eigen::LLT<Eigen::MatrixXd> llt(scan_covariance(r, s, noise));
    if (llt.info() != Eigen::Success) throw Error(ExitCode::software, "Whitener: covariance not positive definite");
    b.L = llt.matrixL();
    blocks_.push_back(std::move(b));
    k = e;
  }
}

void Whitener::whiten(Eigen::Ref<Eigen::VectorXd> v) const {
  if (diagonal_) {
    v.array() /= sigma_.array();
    return;
  }
  for (const auto& b : blocks_) b.L.triangularView<Eigen::Lower>().solveInPlace(v.segment(b.begin, b.n));
}

void Whitener::whiten_columns(Eigen::Ref<Eigen::MatrixXd> M) const {
  if (diagonal_) {
    M.array().colwise() /= sigma_.array();
    return;
  }
  for (const auto& b : blocks_) b.L.triangularView<Eigen::Lower>().solveInPlace(M.middleRows(b.begin, b.n));
}

void Whitener::color(Eigen::Ref<Eigen::VectorXd> v) const {
  if (diagonal_) {
    v.array() *= sigma_.array();
    return;
  }
  for (const auto& b : blocks_) v.segment(b.begin, b.n) = (b.L.triangularView<Eigen::Lower>() * v.segment(b.begin, b.n)).eval();
}

void Whitener::color_columns(Eigen::Ref<Eigen::MatrixXd> M) const {
  if (diagonal_) {
    M.array().colwise() *= sigma_.array();
    return;
  }
  for (const auto& b : blocks_)
    M.middleRows(b.begin, b.n) = (b.L.triangularView<Eigen::Lower>() * M.middleRows(b.begin, b.n)).eval();
}

Eigen::VectorXd Whitener::whitened(const std::vector<double>& e_full) const {
  Eigen::VectorXd z(static_cast<Eigen::Index>(points_.size()));
  for (size_t k = 0; k < points_.size(); ++k) z[static_cast<Eigen::Index>(k)] = e_full[points_[k]];
  whiten(z);
  return z;
}

}  // namespace turnfit
