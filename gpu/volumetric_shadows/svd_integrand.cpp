// Truncated SVD of the spot light's integrand factor (see svd_integrand.h).
#include "svd_integrand.h"

#include <algorithm>
#include <cmath>
#include <numbers>

#include <Eigen/Dense>
#include <Eigen/SVD>

namespace visq::gpu {

double SpotIntegrandFactor(double alpha, double phi, double sigma_t_d, double g, double max_depth) {
  const double cos_theta = std::cos(alpha + phi);
  const double denom = 1.0 + g * g - 2.0 * g * cos_theta;
  const double phase = (1.0 - g * g) / (4.0 * std::numbers::pi * denom * std::sqrt(denom));
  if (sigma_t_d == 0.0) return phase;
  // sigma_t (l + s - d), written without cancellation, clamped at the
  // deepest point the medium holds (beyond: no point, any value will do, and
  // the clamp keeps f continuous).
  const double c = std::cos(0.5 * (alpha + phi));
  const double s = 2.0 * sigma_t_d * std::sin(0.5 * alpha) * std::sin(0.5 * phi);
  const double depth = c > 0.0 && s < max_depth * c ? s / c : max_depth;
  return phase * std::exp(-depth);
}

double DirectionalIntegrandFactor(double alpha, double p, double sigma_t) {
  // cot(alpha / 2) = sin(alpha) / (1 - cos(alpha)), finite for alpha > 0.
  return std::exp(-sigma_t * p * std::sin(alpha) / (1.0 - std::cos(alpha)));
}

namespace {

// The truncated SVD of f over alpha in [alpha_lo, alpha_hi] and x in
// [0, x_hi]; the error is measured where `valid` holds (at a node; at a
// cell's center when all four corners are valid).
template <typename F, typename Valid>
SvdIntegrandTable BuildTable(const F& fn, const Valid& valid, double alpha_lo, double alpha_hi, double x_hi,
                             double tolerance, int max_rank) {
  constexpr int n = kSvdGrid;
  const double step = x_hi / (n - 1);
  const double a0 = alpha_lo, a_step = (alpha_hi - alpha_lo) / (n - 1);
  auto alpha = [&](double i) { return a0 + i * a_step; };
  Eigen::Matrix<bool, Eigen::Dynamic, Eigen::Dynamic> ok(n, n);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) ok(i, j) = valid(alpha(i), j * step);
  // The table at the nodes, and the exact f at the cells' centers.
  Eigen::MatrixXd f(n, n);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) f(i, j) = fn(alpha(i), j * step);
  Eigen::MatrixXd mid(n - 1, n - 1);
  for (int i = 0; i + 1 < n; ++i)
    for (int j = 0; j + 1 < n; ++j) mid(i, j) = fn(alpha(i + 0.5), (j + 0.5) * step);
  double max_f = 0;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      if (ok(i, j)) max_f = std::max(max_f, f(i, j));

  const Eigen::BDCSVD<Eigen::MatrixXd> svd(f, Eigen::ComputeThinU | Eigen::ComputeThinV);
  const Eigen::VectorXd& sigma = svd.singularValues();
  const int most = std::clamp(max_rank, 1, std::min<int>(n, static_cast<int>(sigma.size())));

  // Add rank-one terms until the residual is small enough.
  SvdIntegrandTable table;
  table.max_f = max_f;
  table.alpha0 = a0;
  table.alpha_step = a_step;
  table.x_step = step;
  Eigen::MatrixXd reconstruction = Eigen::MatrixXd::Zero(n, n);
  int rank = 0;
  double error = 0;
  while (rank < most) {
    reconstruction += sigma(rank) * svd.matrixU().col(rank) * svd.matrixV().col(rank).transpose();
    ++rank;
    error = 0;
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        if (ok(i, j)) error = std::max(error, std::abs(reconstruction(i, j) - f(i, j)));
    for (int i = 0; i + 1 < n; ++i)
      for (int j = 0; j + 1 < n; ++j) {
        if (!(ok(i, j) && ok(i + 1, j) && ok(i, j + 1) && ok(i + 1, j + 1))) continue;
        // Linear interpolation of U and V = the bilinear mean of the nodes.
        const double r = 0.25 * (reconstruction(i, j) + reconstruction(i + 1, j) + reconstruction(i, j + 1) +
                                 reconstruction(i + 1, j + 1));
        error = std::max(error, std::abs(r - mid(i, j)));
      }
    if (max_f == 0 || error <= tolerance * max_f) break;
  }
  table.rank = rank;
  table.relative_error = max_f > 0 ? error / max_f : 0.0;
  table.u.resize(size_t(n) * rank);
  table.v.resize(size_t(n) * rank);
  for (int i = 0; i < n; ++i)
    for (int k = 0; k < rank; ++k) {
      table.u[size_t(i) * rank + k] = static_cast<float>(svd.matrixU()(i, k) * sigma(k));
      table.v[size_t(i) * rank + k] = static_cast<float>(svd.matrixV()(i, k));
    }
  return table;
}

}  // namespace

SvdIntegrandTable BuildSpotSvdTable(double sigma_t_d, double g, double max_depth, double alpha_lo, double alpha_hi,
                                    double tolerance, int max_rank) {
  return BuildTable([&](double a, double phi) { return SpotIntegrandFactor(a, phi, sigma_t_d, g, max_depth); },
                    [](double a, double phi) { return a + phi < std::numbers::pi - 1e-12; }, alpha_lo, alpha_hi,
                    std::numbers::pi, tolerance, max_rank);
}

SvdIntegrandTable BuildDirectionalSvdTable(double sigma_t, double p_max, double alpha_lo, double alpha_hi,
                                           double tolerance, int max_rank) {
  return BuildTable([&](double a, double p) { return DirectionalIntegrandFactor(a, p, sigma_t); },
                    [](double, double) { return true; }, alpha_lo, alpha_hi, p_max, tolerance, max_rank);
}

}  // namespace visq::gpu
