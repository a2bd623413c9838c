#ifndef CROWDMAP_CORE_LOCALIZATION_DENSE_PRIOR_SOLVER_H_
#define CROWDMAP_CORE_LOCALIZATION_DENSE_PRIOR_SOLVER_H_

#include <string>
#include <vector>

#include <Eigen/Core>
#include <ceres/ceres.h>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/model/motion_model.h"

namespace crowdmap {

// A joint Gaussian prior on some landmarks: mean and covariance, 2 entries per landmark in the
// order of the landmark blocks it is given with.
struct DenseLandmarkPrior {
  Eigen::VectorXd mean;
  Eigen::MatrixXd cov;
};

struct DensePriorSolverOptions {
  int max_iterations = 100;
  // Converged when no pose or landmark coordinate moves by more than this (m, rad).
  double step_tolerance = 1e-9;
  // A linearisation counts as taken at the current state when no position (of a pose or a
  // landmark) is further than `covariance_tolerance_m` from its point and no heading further than
  // `covariance_tolerance_rad`: the solve then ends on it, and its pose covariances are returned,
  // without a last factorisation at the solution. 0: always at the solution.
  double covariance_tolerance_m = 0.0;
  double covariance_tolerance_rad = 0.0;

  absl::Status Validate() const;
};

struct DensePriorSolution {
  std::vector<Eigen::Matrix3d> pose_covariances;  // marginal, one per pose
  std::vector<double> angle_variances;            // marginal, one per angle
  double cost = 0.0;                              // 1/2 the squared whitened residuals, prior included
  int iterations = 0;
  int factorizations = 0;

  std::string Brief() const;
};

// Gauss-Newton on `problem` (plain squared residuals, no loss functions, every block of `poses`,
// `landmarks` and `angles` in it, nothing else) with `prior` on `landmarks` added analytically: the
// correlated prior never enters Ceres, whose normal equations would hold its dense block over
// hundreds of landmarks at every iteration. The poses are eliminated on their sparse (banded)
// information, leaving one dense Schur complement on the landmarks, factorised once per
// linearisation; between factorisations the steps reuse the last one (chord steps on the exact
// gradient, so the fixed point is the exact optimum), and the final one is at the solution (or
// within the covariance tolerances of it). The
// pose covariances are the marginals of the Gauss-Newton information there:
// A^-1 + W S^-1 W^T (A the pose block, W = A^-1 B, S the Schur complement), the second term as
// the row blocks of A^-1 B L^-T (S = L L^T), with B sparse.
// `angles` are one-entry blocks shared by many residuals (a camera's yaw offset), whose own priors,
// if any, are residuals in `problem`: they are eliminated with the landmarks, and their steps are
// held to the covariance tolerance in radians.
// FailedPrecondition when the information or the prior is not positive definite.
absl::StatusOr<DensePriorSolution> SolveWithDensePrior(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                       const std::vector<double*>& landmarks,
                                                       const DenseLandmarkPrior& prior,
                                                       const DensePriorSolverOptions& options = {},
                                                       const std::vector<double*>& angles = {});

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_DENSE_PRIOR_SOLVER_H_
