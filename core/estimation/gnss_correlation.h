#ifndef CROWDMAP_CORE_ESTIMATION_GNSS_CORRELATION_H_
#define CROWDMAP_CORE_ESTIMATION_GNSS_CORRELATION_H_

// A passage that declares white GNSS noise while its receiver's errors are correlated over minutes
// (the common case: receivers report a per-fix covariance, not a process) would be solved as if
// its hundreds of fixes averaged their errors away. Its trajectory, and the landmarks it places,
// would then be metres off with a covariance of centimetres. The residuals of its fixes against
// its own odometry + GNSS trajectory tell: white errors leave residuals uncorrelated from one fix
// to the next, correlated ones leave a slow drift. Such a passage is estimated with a Gauss-Markov
// process instead (docs/estimation.md, "Undeclared correlated GNSS").

#include <optional>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"
#include "core/model/motion_model.h"

namespace crowdmap {

struct GnssObservation;

// The fixes' residuals against a trajectory, each normalised by its fix's declared covariance.
struct GnssResidualStats {
  int fixes = 0;  // residuals
  int pairs = 0;  // consecutive fixes (gaps over 3 typical intervals break the sequence)
  // Lag-1 correlation of the normalised residuals over the pairs: sum r_k . r_(k-1) over
  // sqrt(sum |r_k|^2 sum |r_(k-1)|^2). About 0 (within 1 / sqrt(2 pairs)) for white errors.
  double lag1 = 0.0;
  double mean_square = 0.0;        // mean of the normalised residuals' squares per axis
  // Mean square per axis of the pairs' differences r_k - r_(k-1): 2 (1 - alpha) for a first-order
  // process of unit variance and lag-1 correlation alpha, which a trajectory, smooth from one fix to
  // the next, hardly takes up (unlike the residuals' level and their correlation).
  double difference_mean_square = 0.0;
  double typical_interval_s = 0.0;  // median time between consecutive fixes
};

// `poses[node]` is the trajectory, `gnss` the fixes in time order (PassageGraph's).
GnssResidualStats MeasureGnssResiduals(const std::vector<GnssObservation>& gnss, const std::vector<Pose2>& poses,
                                       const Eigen::Vector2d& lever_arm_m);

struct CorrelatedGnssOptions {
  int min_pairs = 4;  // fewer consecutive fixes decide nothing
  // The errors' lag-1 correlation (CorrelatedGnssFromResiduals' alpha) that marks them as
  // correlated, and at least this many of the standard deviations (1 / sqrt(pairs)) that white
  // errors give it: 0.5 from 25 pairs on, 0.88 with 8. A white passage taken for a correlated one
  // is estimated with the alpha its residuals give, which errs on the conservative side.
  double min_lag1 = 0.5;
  double significance_sigmas = 2.5;
};

// The check a min_lag1 setting asks for (GraphOptions::detect_correlated_gnss): the defaults with
// that threshold, none for 0 (the declared noise taken as it is).
std::optional<CorrelatedGnssOptions> CorrelatedGnssCheck(double min_lag1);
// InvalidArgument naming `field` unless min_lag1 lies in [0, 1).
absl::Status ValidateCorrelatedGnssMinLag1(double min_lag1, const char* field);

// The process to estimate the passage with: its correlation time (s) and the factor that scales
// each fix's declared covariance into the process's stationary one.
struct CorrelatedGnss {
  GnssResidualStats residuals;
  double correlation_time_s = 0.0;
  double covariance_scale = 1.0;
};

// The Gauss-Markov process the residuals show, or nothing when they look white (alpha at most
// min_lag1). Its stationary covariance is each fix's declared one, scaled up to the residuals'
// where they are larger; its lag-1 correlation alpha the one the residuals' differences give
// against that variance (1 - difference_mean_square / (2 scale)), or the residuals' own lag-1
// correlation where that is larger: a trajectory fitted to the fixes takes up the slow part of
// their errors (on a short passage nearly all of it), so the residuals' correlation understates
// the errors', while their differences keep it. A process whose correlation time is wrong either way makes the passage over-confident
// (too long: its fix-to-fix changes are trusted too much; too short: its errors are taken to
// average out faster than they do).
std::optional<CorrelatedGnss> CorrelatedGnssFromResiduals(const GnssResidualStats& residuals,
                                                          const CorrelatedGnssOptions& options);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_GNSS_CORRELATION_H_
