#include "core/estimation/gnss_correlation.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>

#include "absl/strings/str_cat.h"
#include "core/estimation/graph_builder.h"

namespace crowdmap {

GnssResidualStats MeasureGnssResiduals(const std::vector<GnssObservation>& gnss, const std::vector<Pose2>& poses,
                                       const Eigen::Vector2d& lever_arm_m) {
  GnssResidualStats stats;
  std::vector<double> intervals;
  for (size_t k = 1; k < gnss.size(); ++k) intervals.push_back(gnss[k].t_s - gnss[k - 1].t_s);
  if (!intervals.empty()) {
    std::nth_element(intervals.begin(), intervals.begin() + static_cast<std::ptrdiff_t>(intervals.size() / 2),
                     intervals.end());
    stats.typical_interval_s = intervals[intervals.size() / 2];
  }
  std::vector<Eigen::Vector2d> normalised;
  normalised.reserve(gnss.size());
  double sum_squares = 0.0;
  for (const GnssObservation& o : gnss) {
    const Pose2& pose = poses[o.node];
    const double c = std::cos(pose.z()), s = std::sin(pose.z());
    const Eigen::Vector2d antenna =
        pose.head<2>() + Eigen::Vector2d(c * lever_arm_m.x() - s * lever_arm_m.y(), s * lever_arm_m.x() + c * lever_arm_m.y());
    // L^-1 r with cov = L L^T: unit covariance when the fix's declared covariance is right.
    const Eigen::Vector2d r = o.cov_m2.llt().matrixL().solve(antenna - o.position_m);
    normalised.push_back(r);
    sum_squares += r.squaredNorm();
  }
  stats.fixes = static_cast<int>(normalised.size());
  if (stats.fixes > 0) stats.mean_square = sum_squares / (2.0 * stats.fixes);
  double cross = 0.0, now_squares = 0.0, before_squares = 0.0, differences = 0.0;
  for (size_t k = 1; k < gnss.size(); ++k) {
    if (!(gnss[k].t_s - gnss[k - 1].t_s <= 3.0 * stats.typical_interval_s)) continue;
    cross += normalised[k].dot(normalised[k - 1]);
    now_squares += normalised[k].squaredNorm();
    before_squares += normalised[k - 1].squaredNorm();
    differences += (normalised[k] - normalised[k - 1]).squaredNorm();
    ++stats.pairs;
  }
  if (now_squares > 0.0 && before_squares > 0.0) stats.lag1 = cross / std::sqrt(now_squares * before_squares);
  if (stats.pairs > 0) stats.difference_mean_square = differences / (2.0 * stats.pairs);
  return stats;
}

std::optional<CorrelatedGnssOptions> CorrelatedGnssCheck(double min_lag1) {
  if (!(min_lag1 > 0.0)) return std::nullopt;
  CorrelatedGnssOptions options;
  options.min_lag1 = min_lag1;
  return options;
}

absl::Status ValidateCorrelatedGnssMinLag1(double min_lag1, const char* field) {
  if (min_lag1 >= 0.0 && min_lag1 < 1.0) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(field, ": must lie in [0, 1) (0 = off), got ", min_lag1));
}

std::optional<CorrelatedGnss> CorrelatedGnssFromResiduals(const GnssResidualStats& residuals,
                                                          const CorrelatedGnssOptions& options) {
  // Residuals larger than declared: the process's variance is at least theirs.
  const double covariance_scale = std::max(1.0, residuals.mean_square);
  const double from_differences = 1.0 - residuals.difference_mean_square / (2.0 * covariance_scale);
  const double alpha = std::max(from_differences, residuals.lag1);
  // White errors give alpha about 0 within 1 / sqrt(pairs): a short passage must show more.
  const double significant = options.significance_sigmas / std::sqrt(std::max(residuals.pairs, 1));
  if (residuals.pairs < options.min_pairs || !(alpha > std::max(options.min_lag1, significant)) ||
      !(residuals.typical_interval_s > 0.0)) {
    return std::nullopt;
  }
  CorrelatedGnss out;
  out.residuals = residuals;
  out.covariance_scale = covariance_scale;
  // alpha = exp(-dt / tau) for fixes dt apart.
  out.correlation_time_s = -residuals.typical_interval_s / std::log(std::min(alpha, 0.9999));
  return out;
}

}  // namespace crowdmap
