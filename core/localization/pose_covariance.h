#ifndef CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_
#define CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_

#include <vector>

#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/model/motion_model.h"

namespace crowdmap {

// Marginal 3x3 covariances of `poses` in a solved `problem` whose other blocks are `landmarks`
// (those not in the problem are skipped) and `others` (e.g. a camera's yaw offset), from its
// Gauss-Newton information at the solution (and, when asked, the marginal variances of `others`): one
// sparse selected inverse (the landmarks are not linked among themselves, or by a few factors; a
// correlated map's dense prior is SolveWithDensePrior's). FailedPrecondition when the
// information is rank deficient.
absl::StatusOr<std::vector<Eigen::Matrix3d>> PoseCovariances(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                             std::vector<Eigen::Vector2d>* landmarks,
                                                             const std::vector<double*>& others = {},
                                                             std::vector<double>* other_variances = nullptr);

// The 3x3 diagonal blocks of A^-1, for the first `pose_count` poses (3 rows each, first) of the
// factorised A (a selected inverse).
std::vector<Eigen::Matrix3d> PoseBlocksOfInverse(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor,
                                                 int pose_count);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_POSE_COVARIANCE_H_
