#include "core/localization/pose_covariance.h"

#include "core/map/selected_inverse.h"

namespace crowdmap {
namespace {

// The 3x3 diagonal blocks of the first `pose_count` poses (3 rows each, first).
std::vector<Eigen::Matrix3d> PoseBlocks(const SelectedInverse& inverse, int pose_count) {
  std::vector<Eigen::Matrix3d> out(pose_count);
  for (int k = 0; k < pose_count; ++k) {
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) out[k](a, b) = inverse(3 * k + a, 3 * k + b);
    }
  }
  return out;
}

}  // namespace

absl::StatusOr<std::vector<Eigen::Matrix3d>> PoseCovariances(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                             std::vector<Eigen::Vector2d>* landmarks,
                                                             const std::vector<double*>& others,
                                                             std::vector<double>* other_variances) {
  ceres::Problem::EvaluateOptions evaluate;
  for (Pose2& p : *poses) evaluate.parameter_blocks.push_back(p.data());
  for (Eigen::Vector2d& l : *landmarks) {
    if (problem->HasParameterBlock(l.data())) evaluate.parameter_blocks.push_back(l.data());
  }
  for (double* other : others) evaluate.parameter_blocks.push_back(other);
  evaluate.num_threads = 1;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(evaluate, nullptr, nullptr, nullptr, &crs)) {
    return absl::InternalError("localization covariance: the Jacobian could not be evaluated");
  }
  const Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>> jacobian(
      crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
      crs.values.data());
  const Eigen::SparseMatrix<double> jt = jacobian.transpose();
  const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> llt(jt * jacobian);
  if (llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError("localization covariance: the passage's information is rank deficient");
  }
  const SelectedInverse inverse(llt);
  if (other_variances != nullptr) {
    other_variances->clear();
    const int first = crs.num_cols - static_cast<int>(others.size());
    for (int k = first; k < crs.num_cols; ++k) other_variances->push_back(inverse(k, k));
  }
  return PoseBlocks(inverse, static_cast<int>(poses->size()));
}

std::vector<Eigen::Matrix3d> PoseBlocksOfInverse(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor,
                                                 int pose_count) {
  return PoseBlocks(SelectedInverse(factor), pose_count);
}

}  // namespace crowdmap
