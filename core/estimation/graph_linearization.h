#ifndef CROWDMAP_CORE_ESTIMATION_GRAPH_LINEARIZATION_H_
#define CROWDMAP_CORE_ESTIMATION_GRAPH_LINEARIZATION_H_

#include <memory>
#include <optional>
#include <unordered_map>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/map/selected_inverse.h"

namespace crowdmap {

// What some residual blocks say about some landmarks at the problem's current point once the
// other parameter blocks they involve are eliminated: their cost is, to second order,
// const + gradient^T d + 1/2 d^T information d in the landmarks' displacement d (2 per landmark,
// in the order given). Landmarks the blocks do not involve get zero rows. Other blocks to keep
// (a calibration state) may be passed among the landmarks, with their own sizes.
struct LandmarkInformation {
  Eigen::MatrixXd information;
  Eigen::VectorXd gradient;
};

absl::StatusOr<LandmarkInformation> EliminateToLandmarks(ceres::Problem* problem,
                                                         const std::vector<ceres::ResidualBlockId>& residuals,
                                                         const std::vector<double*>& landmarks);

struct BiasCorrectionStats {
  double max_landmark_shift_m = 0.0;
  int skipped_residual_blocks = 0;  // not evaluable near the solution (left out of the correction)
  double ms = 0.0;
};

// The Gauss-Newton linearization of a solved graph at its solution: information H = J^T J (with
// Ceres's loss weights) split into the other blocks x (the pose chain, sparse) and the landmarks L
// (2-D positions, a small dense block): H = [A B; B^T C]. The landmark marginal covariance is
// Sigma_LL = (C - B^T A^-1 B)^-1: a sparse Cholesky of the banded pose block and a small dense
// one, the same result as ceres::Covariance several times faster on these graphs. A
// rank-deficient graph fails at either factorisation.
class GraphLinearization {
 public:
  // `factor_leaves_out`: residual blocks whose information the landmarks' factor must not hold
  // (factor_covariance() and factor_gradient(): as if the problem did not have them); everything
  // else keeps them. A prior on one scalar block that is not a landmark (a calibration state's)
  // is taken out by a rank-one downdate; anything else by a second linearisation without it.
  static absl::StatusOr<GraphLinearization> Compute(ceres::Problem* problem, const std::vector<double*>& landmarks,
                                                    const std::vector<ceres::ResidualBlockId>& factor_leaves_out = {});

  // Marginal covariance of the landmarks, in the order given (2 x 2 blocks).
  const Eigen::MatrixXd& landmark_covariance() const { return sigma_ll_; }
  // The cost's gradient in the landmarks with the other blocks eliminated, at the point it was
  // computed at: zero at an exact optimum, the solver's shortfall otherwise.
  const Eigen::VectorXd& landmark_gradient() const { return landmark_gradient_; }
  // The same two without the residual blocks the factor leaves out (the same as the two above
  // when it leaves none out).
  const Eigen::MatrixXd& factor_covariance() const { return factor_ ? factor_->covariance : sigma_ll_; }
  const Eigen::VectorXd& factor_gradient() const { return factor_ ? factor_->gradient : landmark_gradient_; }
  // Marginal variance of a scalar parameter block that is not a landmark (e.g. a camera yaw
  // offset), in its two parts: given the landmarks, (A^-1)_uu, and what the landmarks'
  // uncertainty adds, w_u Sigma_LL w_u^T. One sparse solve.
  struct ScalarMarginal {
    double given_landmarks = 0.0;
    double from_landmarks = 0.0;
    double total() const { return given_landmarks + from_landmarks; }
  };
  ScalarMarginal MarginalVariance(const double* block) const;

  // Second-order bias correction of the solution (Box 1971): to order sigma^2 a nonlinear
  // least-squares (MAP) estimate is off its expectation by
  //   b = -1/2 H^-1 sum_k J_k^T tr(Sigma_k d2r_k),
  // r_k the whitened residuals, d2r_k their Hessians in the variables of residual block k and
  // Sigma_k = H^-1 on those variables; the trace is taken with central second differences along
  // the Cholesky columns of Sigma_k (exact for quadratic residuals). With the heading noise of
  // production odometry the MAP poses of one passage are decimetres off on average, the same way
  // on every passage of a road (`mapsim pose-bias`), so without this step the bias stays in the
  // map. Moves the estimate in `problem` (the problem this was computed from) by -b. Linear
  // residual blocks (the map prior) contribute nothing and are skipped.
  absl::Status CorrectSecondOrderBias(ceres::Problem* problem, BiasCorrectionStats* stats);

  // The redundancy (Foerstner) of each residual block the linearisation holds (all but the priors
  // on landmarks alone): its residuals' count minus its share of the parameters,
  // tr(J_k H^-1 J_k^T), with the loss's weights in J_k. Summed with the priors' they make the
  // residuals' count minus the parameters'. At the solution a group of blocks has a chi-square of
  // its redundancy on average when its noise is as weighted: the measure of each sensor's variance
  // factor (variance component estimation).
  std::unordered_map<ceres::ResidualBlockId, double> Redundancies();

 private:
  GraphLinearization() = default;
  // Over `residual_blocks` only (a subset of the problem's, in its order).
  static absl::StatusOr<GraphLinearization> ComputeOver(ceres::Problem* problem, const std::vector<double*>& landmarks,
                                                        std::vector<ceres::ResidualBlockId> residual_blocks);
  // Sigma = H^-1 at columns u, v (u, v on the pattern of H), once PrepareSigma has run.
  void PrepareSigma();
  double Sigma(int u, int v) const;
  // Sigma over `columns` (all on one residual block's variables), dense.
  Eigen::MatrixXd SigmaOver(const std::vector<int>& columns) const;
  struct LandmarkMarginal {
    Eigen::MatrixXd covariance;
    Eigen::VectorXd gradient;
  };
  // The landmarks' covariance and gradient without `prior`, a residual on one scalar block that is
  // not a landmark (Sherman-Morrison on A, then on the landmarks' Schur complement); nullopt when
  // the block is of another kind, or the rest of the problem leaves the scalar (or the landmarks)
  // too weakly determined for the downdate to be accurate.
  std::optional<LandmarkMarginal> WithoutScalarPrior(ceres::Problem* problem, ceres::ResidualBlockId prior) const;

  std::vector<double*> ordered_;                  // other blocks, then the landmarks
  std::unordered_map<const double*, int> offset_; // column of each block
  std::vector<ceres::ResidualBlockId> residuals_; // row order of the Jacobian
  std::vector<int> residual_rows_;                // the first row of each
  int other_dim_ = 0;
  int landmark_dim_ = 0;
  Eigen::SparseMatrix<double> jt_;                // J^T
  Eigen::SparseMatrix<double> b_;                 // B
  std::unique_ptr<Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>> a_llt_;
  std::unique_ptr<SelectedInverse> a_inv_;
  Eigen::MatrixXd w_;                             // A^-1 B
  Eigen::LLT<Eigen::MatrixXd> s_llt_;             // S = C - B^T A^-1 B
  Eigen::MatrixXd sigma_ll_;
  Eigen::VectorXd landmark_gradient_;
  Eigen::VectorXd other_gradient_;                // the cost's gradient in the other blocks
  Eigen::MatrixXd w_sigma_;                       // A^-1 B Sigma_LL
  bool sigma_ready_ = false;                      // a_inv_ and w_sigma_ computed
  std::optional<LandmarkMarginal> factor_;        // without the blocks the factor leaves out
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_GRAPH_LINEARIZATION_H_
