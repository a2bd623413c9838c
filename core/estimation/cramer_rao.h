#ifndef CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_
#define CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_

// The Cramer-Rao bound of a map: the smallest covariance any unbiased estimator can reach from
// the passages' measurements, the inverse of their Fisher information about the landmarks.
// Passages share no poses, so the map's Fisher information is the sum of each passage's, taken at
// the truth with its poses eliminated (the information form's factors, at the true values).

#include <functional>
#include <map>
#include <optional>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/estimation/graph_builder.h"
#include "core/model/passage.h"

namespace crowdmap {

// One passage's Fisher information about the landmarks it detects, in the graph frame of
// `options.frame_origin` (East/North, metres), from the estimator's own graph (`options`: the
// same nodes, detections and noise model) evaluated at the true poses and landmark positions.
// Coloured GNSS noise declared by the passage (NoiseModel::gnss_correlation_time_s) is whitened
// with the Cholesky factor of the fixes' full correlation matrix, not with the estimator's
// factors, so that the bound checks them.
struct PassageFisherInformation {
  std::vector<LandmarkId> landmarks;
  Eigen::MatrixXd information;  // 2 rows per landmark, in `landmarks` order
};

// `true_pose(t)` is the vehicle's true pose at t (s since the passage start) and
// `true_landmark(id)` a landmark's true position, both in the frame at options.frame_origin
// (which must be set). Detections of landmarks without a true position are left out.
absl::StatusOr<PassageFisherInformation> PassageLandmarkInformation(
    const Passage& passage, const GraphOptions& options, const std::function<Pose2(double)>& true_pose,
    const std::function<std::optional<Eigen::Vector2d>(LandmarkId)>& true_landmark);

// Sums passages' Fisher information and gives the bound.
class CramerRaoBound {
 public:
  void Add(const PassageFisherInformation& passage);
  // The bound on each landmark seen so far: its 2x2 block of the inverse of the summed
  // information. FailedPrecondition when the information is singular (a landmark the passages do
  // not determine).
  absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> Covariances() const;

 private:
  std::map<LandmarkId, int> index_;
  Eigen::MatrixXd information_;
};

// Expected distance |e| of a zero-mean 2-D Gaussian error with covariance `cov`: the bound's
// counterpart of a landmark's distance error.
double ExpectedDistance(const Eigen::Matrix2d& cov);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_
