#include "core/localization/dense_prior_solver.h"

#include <cmath>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "core/estimation/factors.h"
#include "core/localization/pose_covariance.h"
#include "core/model/camera_model.h"

namespace crowdmap {
namespace {

// A short pose chain (odometry, GNSS) seeing three landmarks, without their prior: measurements
// of a true configuration with small errors, the estimate started a little off it.
// With `estimate_yaw`, the camera is turned by 0.01 rad and its yaw offset is a state with a prior
// of 0.02 rad (`yaw`).
struct SmallProblem {
  std::vector<Pose2> poses;
  std::vector<Eigen::Vector2d> landmarks;
  double yaw = 0.0;
  ceres::Problem problem;

  explicit SmallProblem(bool estimate_yaw = false) {
    const Calibration calib;
    const std::vector<Pose2> truth = {Pose2(0, 0, 0), Pose2(5, 0.3, 0.1), Pose2(10, 1.1, 0.15), Pose2(15, 2.0, 0.2)};
    const std::vector<Eigen::Vector2d> true_landmarks = {Eigen::Vector2d(30, 5), Eigen::Vector2d(35, -4),
                                                         Eigen::Vector2d(42, 9)};
    const double error[4] = {0.7, -1.1, 0.4, -0.2};  // measurement errors, in sigmas
    for (const Pose2& pose : truth) poses.push_back(pose + Pose2(0.4, -0.3, 0.02));
    for (size_t k = 0; k < truth.size(); ++k) {
      if (k + 1 < truth.size()) {
        RelativeMotion motion;
        motion.cov = Eigen::Vector3d(0.01, 0.02, 0.001).asDiagonal();
        const Eigen::Rotation2Dd to_k(-truth[k].z());
        motion.delta << to_k * (truth[k + 1].head<2>() - truth[k].head<2>()), truth[k + 1].z() - truth[k].z();
        motion.delta += 0.1 * error[k] * Pose2(0.1, 0.14, 0.03);
        problem.AddResidualBlock(OdometryFactor::Create(motion), nullptr, poses[k].data(), poses[k + 1].data());
      }
    }
    for (const Eigen::Vector2d& l : true_landmarks) landmarks.push_back(l + Eigen::Vector2d(-0.5, 0.6));
    for (size_t k = 0; k < truth.size(); ++k) {
      const Eigen::Rotation2Dd rotation(truth[k].z());
      const Eigen::Vector2d antenna = truth[k].head<2>() + rotation * calib.gnss_lever_arm_m;
      problem.AddResidualBlock(
          GnssFactor::Create(antenna + 2.0 * error[k] * Eigen::Vector2d(1, -1), 4.0 * Eigen::Matrix2d::Identity(),
                             calib.gnss_lever_arm_m),
          nullptr, poses[k].data());
      for (size_t l = 0; l < landmarks.size(); ++l) {
        Calibration turned = calib;
        if (estimate_yaw) turned.camera_yaw_rad += 0.01;
        double u_px = 0.0;
        EXPECT_TRUE(ProjectLandmark(truth[k].data(), true_landmarks[l].data(), turned, &u_px));
        AddCameraResidual(u_px + 2.0 * error[(k + l) % 4], 2.0, calib, nullptr, poses[k].data(), landmarks[l].data(),
                          estimate_yaw ? &yaw : nullptr, &problem);
      }
    }
    if (estimate_yaw) problem.AddResidualBlock(ScalarPriorFactor::Create(0.0, 0.02), nullptr, &yaw);
  }
};

DenseLandmarkPrior CorrelatedPrior() {
  DenseLandmarkPrior prior;
  prior.mean.resize(6);
  prior.mean << 30.4, 5.2, 34.7, -4.3, 42.2, 8.6;  // the truth (see SmallProblem) with errors
  prior.cov = 0.05 * Eigen::MatrixXd::Ones(6, 6) + 0.2 * Eigen::MatrixXd::Identity(6, 6);
  prior.cov(0, 1) = prior.cov(1, 0) = 0.08;
  return prior;
}

// The reference: the prior as one Ceres factor in `problem`, solved by Ceres to its tolerances' end.
ceres::Solver::Summary SolveWithThePriorAsAFactor(const DenseLandmarkPrior& prior, SmallProblem* problem) {
  std::vector<double*> blocks;
  for (Eigen::Vector2d& l : problem->landmarks) blocks.push_back(l.data());
  problem->problem.AddResidualBlock(new LandmarkPriorFactor(prior.mean, SqrtInformation(prior.cov)), nullptr, blocks);
  ceres::Solver::Options options;
  options.function_tolerance = options.gradient_tolerance = options.parameter_tolerance = 1e-14;
  options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem->problem, &summary);
  return summary;
}

// The same problem with the prior as one Ceres factor, solved by Ceres, with its covariances by
// a sparse selected inverse of the whole information: the same solution and marginals.
TEST(SolveWithDensePrior, MatchesCeresWithThePriorAsAFactor) {
  const DenseLandmarkPrior prior = CorrelatedPrior();
  SmallProblem dense, reference;
  std::vector<double*> blocks;
  for (Eigen::Vector2d& l : dense.landmarks) blocks.push_back(l.data());
  absl::StatusOr<DensePriorSolution> solution = SolveWithDensePrior(&dense.problem, &dense.poses, blocks, prior);
  ASSERT_TRUE(solution.ok()) << solution.status();
  EXPECT_LE(solution->factorizations, solution->iterations);

  const ceres::Solver::Summary summary = SolveWithThePriorAsAFactor(prior, &reference);
  ASSERT_TRUE(summary.IsSolutionUsable());
  absl::StatusOr<std::vector<Eigen::Matrix3d>> marginals =
      PoseCovariances(&reference.problem, &reference.poses, &reference.landmarks);
  ASSERT_TRUE(marginals.ok()) << marginals.status();

  EXPECT_NEAR(solution->cost, summary.final_cost, 1e-9 * summary.final_cost);
  for (size_t k = 0; k < dense.poses.size(); ++k) {
    EXPECT_LT((dense.poses[k] - reference.poses[k]).norm(), 1e-7) << "pose " << k;
    EXPECT_LT((solution->pose_covariances[k] - (*marginals)[k]).norm(), 1e-8 * (*marginals)[k].norm()) << "pose " << k;
  }
  for (size_t l = 0; l < dense.landmarks.size(); ++l) {
    EXPECT_LT((dense.landmarks[l] - reference.landmarks[l]).norm(), 1e-7) << "landmark " << l;
  }
}

// A camera yaw offset shared by every detection, with its prior in the problem: eliminated with the
// landmarks; the same solution, pose marginals and yaw variance as Ceres on the whole problem.
TEST(SolveWithDensePrior, EstimatesASharedAngleWithTheLandmarks) {
  const DenseLandmarkPrior prior = CorrelatedPrior();
  SmallProblem dense(/*estimate_yaw=*/true), reference(/*estimate_yaw=*/true);
  std::vector<double*> blocks;
  for (Eigen::Vector2d& l : dense.landmarks) blocks.push_back(l.data());
  absl::StatusOr<DensePriorSolution> solution =
      SolveWithDensePrior(&dense.problem, &dense.poses, blocks, prior, {}, {&dense.yaw});
  ASSERT_TRUE(solution.ok()) << solution.status();
  ASSERT_EQ(solution->angle_variances.size(), 1u);

  const ceres::Solver::Summary summary = SolveWithThePriorAsAFactor(prior, &reference);
  ASSERT_TRUE(summary.IsSolutionUsable());
  absl::StatusOr<std::vector<Eigen::Matrix3d>> marginals =
      PoseCovariances(&reference.problem, &reference.poses, &reference.landmarks, {&reference.yaw});
  ASSERT_TRUE(marginals.ok()) << marginals.status();
  ceres::Covariance covariance{ceres::Covariance::Options()};
  const std::vector<std::pair<const double*, const double*>> yaw_block = {{&reference.yaw, &reference.yaw}};
  ASSERT_TRUE(covariance.Compute(yaw_block, &reference.problem));
  double yaw_variance = 0.0;
  ASSERT_TRUE(covariance.GetCovarianceBlock(&reference.yaw, &reference.yaw, &yaw_variance));

  EXPECT_GT(std::abs(reference.yaw), 1e-3) << "the data move the offset off its prior";
  EXPECT_NEAR(dense.yaw, reference.yaw, 1e-9);
  EXPECT_NEAR(solution->angle_variances[0], yaw_variance, 1e-8 * yaw_variance);
  EXPECT_LT(yaw_variance, 0.02 * 0.02) << "the data inform the offset";
  EXPECT_NEAR(solution->cost, summary.final_cost, 1e-9 * summary.final_cost);
  for (size_t k = 0; k < dense.poses.size(); ++k) {
    EXPECT_LT((dense.poses[k] - reference.poses[k]).norm(), 1e-7) << "pose " << k;
    EXPECT_LT((solution->pose_covariances[k] - (*marginals)[k]).norm(), 1e-8 * (*marginals)[k].norm()) << "pose " << k;
  }
}

// With covariance tolerances the solve ends on a linearisation taken near the solution: the same
// optimum, covariances close to those at the optimum, fewer factorisations.
TEST(SolveWithDensePrior, CovarianceToleranceSavesTheLastFactorization) {
  const DenseLandmarkPrior prior = CorrelatedPrior();
  SmallProblem exact, tolerant;
  std::vector<double*> exact_blocks, tolerant_blocks;
  for (Eigen::Vector2d& l : exact.landmarks) exact_blocks.push_back(l.data());
  for (Eigen::Vector2d& l : tolerant.landmarks) tolerant_blocks.push_back(l.data());
  absl::StatusOr<DensePriorSolution> reference = SolveWithDensePrior(&exact.problem, &exact.poses, exact_blocks, prior);
  ASSERT_TRUE(reference.ok()) << reference.status();
  DensePriorSolverOptions options;
  options.covariance_tolerance_m = 1.0;
  options.covariance_tolerance_rad = 0.1;
  absl::StatusOr<DensePriorSolution> solution =
      SolveWithDensePrior(&tolerant.problem, &tolerant.poses, tolerant_blocks, prior, options);
  ASSERT_TRUE(solution.ok()) << solution.status();

  EXPECT_LT(solution->factorizations, reference->factorizations);
  EXPECT_NEAR(solution->cost, reference->cost, 1e-9 * reference->cost);
  for (size_t k = 0; k < exact.poses.size(); ++k) {
    EXPECT_LT((tolerant.poses[k] - exact.poses[k]).norm(), 1e-7) << "pose " << k;
    const Eigen::Matrix3d& cov = reference->pose_covariances[k];
    EXPECT_LT((solution->pose_covariances[k] - cov).norm(), 0.05 * cov.norm()) << "pose " << k;
    EXPECT_GT((solution->pose_covariances[k] - cov).norm(), 0.0) << "pose " << k << ": not from an earlier point";
  }
}

TEST(SolveWithDensePrior, RefusesAPriorThatIsNotPositiveDefinite) {
  DenseLandmarkPrior prior = CorrelatedPrior();
  prior.cov(2, 2) = -1.0;
  SmallProblem dense;
  std::vector<double*> blocks;
  for (Eigen::Vector2d& l : dense.landmarks) blocks.push_back(l.data());
  absl::StatusOr<DensePriorSolution> solution = SolveWithDensePrior(&dense.problem, &dense.poses, blocks, prior);
  ASSERT_FALSE(solution.ok());
  EXPECT_EQ(solution.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST(SolveWithDensePrior, RefusesAPriorOfTheWrongSize) {
  DenseLandmarkPrior prior = CorrelatedPrior();
  SmallProblem dense;
  std::vector<double*> blocks = {dense.landmarks[0].data(), dense.landmarks[1].data()};
  absl::StatusOr<DensePriorSolution> solution = SolveWithDensePrior(&dense.problem, &dense.poses, blocks, prior);
  ASSERT_FALSE(solution.ok());
  EXPECT_EQ(solution.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(DensePriorSolverOptions, RejectsInvalidValues) {
  DensePriorSolverOptions options;
  EXPECT_TRUE(options.Validate().ok());
  options.max_iterations = 0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.step_tolerance = 0.0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.covariance_tolerance_m = -1.0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.covariance_tolerance_rad = std::nan("");
  EXPECT_FALSE(options.Validate().ok());
}

}  // namespace
}  // namespace crowdmap
