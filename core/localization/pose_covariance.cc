#include "core/localization/pose_covariance.h"

#include <Eigen/Cholesky>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "core/map/selected_inverse.h"

namespace crowdmap {

// Marginal covariances of the poses at the solution, from the Gauss-Newton information J^T J
// = [A B; B^T C] (poses first, then the landmarks): (H^-1)_pp = A^-1 + W S^-1 W^T with W = A^-1 B
// and S = C - B^T W. A is the banded pose chain (its diagonal blocks by a selected inverse); the
// landmark block, dense under a correlated map prior, is only factorised densely, never filled
// into a sparse factor (which took seconds with a few hundred correlated landmarks). Without
// correlations one sparse selected inverse of the whole information is faster.
absl::StatusOr<std::vector<Eigen::Matrix3d>> PoseCovariances(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                             std::vector<Eigen::Vector2d>* landmarks,
                                                             bool dense_landmark_block) {
  ceres::Problem::EvaluateOptions evaluate;
  for (Pose2& p : *poses) evaluate.parameter_blocks.push_back(p.data());
  for (Eigen::Vector2d& l : *landmarks) {
    if (problem->HasParameterBlock(l.data())) evaluate.parameter_blocks.push_back(l.data());
  }
  evaluate.num_threads = 1;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(evaluate, nullptr, nullptr, nullptr, &crs)) {
    return absl::InternalError("localization covariance: the Jacobian could not be evaluated");
  }
  const Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>> jacobian(
      crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
      crs.values.data());
  const Eigen::SparseMatrix<double> jt = jacobian.transpose();
  const Eigen::SparseMatrix<double> h = jt * jacobian;
  const int np = 3 * static_cast<int>(poses->size()), nl = static_cast<int>(h.cols()) - np;
  std::vector<Eigen::Matrix3d> out(poses->size());
  auto pose_blocks = [&](const SelectedInverse& inverse) {
    for (size_t k = 0; k < poses->size(); ++k) {
      for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b) out[k](a, b) = inverse(static_cast<int>(3 * k) + a, static_cast<int>(3 * k) + b);
      }
    }
  };
  if (!dense_landmark_block) {
    // Sparse throughout: one selected inverse of the whole information.
    const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> llt(h);
    if (llt.info() != Eigen::Success) {
      return absl::FailedPreconditionError("localization covariance: the passage's information is rank deficient");
    }
    pose_blocks(SelectedInverse(llt));
    return out;
  }
  const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> a_llt(h.topLeftCorner(np, np));
  if (a_llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError("localization covariance: the pose chain's information is rank deficient");
  }
  pose_blocks(SelectedInverse(a_llt));
  if (nl == 0) return out;
  const Eigen::SparseMatrix<double> b = h.topRightCorner(np, nl);
  const Eigen::MatrixXd w = a_llt.solve(Eigen::MatrixXd(b));
  const Eigen::MatrixXd s = Eigen::MatrixXd(h.bottomRightCorner(nl, nl)) - b.transpose() * w;
  const Eigen::LLT<Eigen::MatrixXd> s_llt(0.5 * (s + s.transpose()));
  if (s_llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError("localization covariance: the landmarks are not observable");
  }
  // W S^-1 W^T = V^T V with V = L^-1 W^T (S = L L^T).
  const Eigen::MatrixXd v = s_llt.matrixL().solve(w.transpose());
  for (size_t k = 0; k < poses->size(); ++k) {
    const auto vk = v.middleCols(3 * k, 3);
    out[k] += vk.transpose() * vk;
  }
  return out;
}

}  // namespace crowdmap
