#ifndef CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_
#define CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_

#include <vector>

#include <Eigen/Core>
#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/model/motion_model.h"

namespace crowdmap {

// Marginal 3x3 covariances of `poses` in a solved `problem` whose other blocks are `landmarks`
// (those not in the problem are skipped), from its Gauss-Newton information at the solution.
// `dense_landmark_block`: the landmarks are linked among themselves (a correlated prior).
// FailedPrecondition when the information is rank deficient.
absl::StatusOr<std::vector<Eigen::Matrix3d>> PoseCovariances(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                             std::vector<Eigen::Vector2d>* landmarks,
                                                             bool dense_landmark_block);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_
