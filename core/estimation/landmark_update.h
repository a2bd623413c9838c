#ifndef CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_
#define CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_

#include <functional>
#include <limits>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/geo/local_frame.h"
#include "core/map/map_state.h"

namespace crowdmap {

struct LandmarkUpdateOptions {
  bool correlated = true;  // CC (joint prior, cross-covariances kept) or DC (2x2 priors only)
  double correlation_radius_m = std::numeric_limits<double>::infinity();
};

struct LandmarkUpdateStats {
  int updated = 0;      // landmarks of the graph already in the map
  int created = 0;      // landmarks of the graph new to the map
  int conditioned = 0;  // map landmarks outside the graph moved through their correlation
  double covariance_ms = 0.0;
};

// The map side of one (sub)graph solve (DESIGN section 5), for the graph's landmarks S = O u N
// (O: already in the map, N: new):
//   1. AddMapPrior: the CC prior on O (mean mu_O, information inverse of the MARGINAL Sigma_OO,
//      checked positive definite) or one DC prior per landmark.
//   2. the caller solves the problem;
//   3. Commit: Sigma'_SS from ceres::Covariance, then the Gaussian conditioning of the map
//      landmarks U outside the graph correlated with O, with A = Sigma_UO Sigma_OO^-1:
//        mu'_U = mu_U + A (mu'_O - mu_O),  Sigma'_US = A Sigma'_OS,
//        Sigma'_UU = Sigma_UU + A (Sigma'_OO - Sigma_OO) A^T,
//      all written to the map at a new version. Exact for linear-Gaussian problems.
// Everything is computed in the graph's local frame; covariances enter and leave it through
// the Jacobian of the East/North-at-landmark to local-frame map.
class LandmarkUpdate {
 public:
  // `map` is read for the prior and receives the changes.
  LandmarkUpdate(const LocalFrame& frame, MapOverlay* map, std::vector<LandmarkId> ids);

  int size() const { return static_cast<int>(ids_.size()); }
  LandmarkId id(int i) const { return ids_[i]; }
  bool in_map(int i) const { return in_map_[i]; }
  // Parameter block of landmark i (local frame, metres); map landmarks start at their map position.
  double* block(int i) { return positions_[i].data(); }

  // Adds the map prior for the landmarks already in the map. FailedPrecondition when the map's
  // covariance sub-block is not positive definite.
  absl::Status AddMapPrior(bool correlated, ceres::Problem* problem);

  // After a usable solve: with the graph landmarks' estimate in their blocks and `cov_ss` their
  // marginal covariance (GraphLinearization), conditions the correlated landmarks outside the
  // graph and writes every change at a new map version. `touch` is called on each record of the
  // graph's landmarks before it is written (counts).
  absl::StatusOr<LandmarkUpdateStats> Commit(const Eigen::MatrixXd& cov_ss, const LandmarkUpdateOptions& options,
                                             const std::function<void(Landmark*)>& touch);

 private:
  // Covariance of landmarks a and b in the local frame (zero when not stored).
  Eigen::Matrix2d LocalCross(LandmarkId a, const Eigen::Matrix2d& ra, LandmarkId b, const Eigen::Matrix2d& rb) const;
  // Writes one landmark record at `version` from its local-frame mean and covariance.
  void WriteLandmark(Landmark record, const Eigen::Vector2d& mean, const Eigen::Matrix2d& cov, int64_t version,
                     Eigen::Matrix2d* from_local);

  const LocalFrame& frame_;
  MapOverlay* map_;
  std::vector<LandmarkId> ids_;
  std::vector<bool> in_map_;
  std::vector<Eigen::Vector2d> positions_;
  std::vector<int> prior_index_;    // indices (into ids_) of the map landmarks O
  Eigen::VectorXd prior_mean_;      // mu_O, local frame
  Eigen::MatrixXd prior_cov_;       // Sigma_OO, local frame
  Eigen::LLT<Eigen::MatrixXd> prior_llt_;
  std::vector<Eigen::Matrix2d> to_local_;  // East/North at landmark -> local, for O
};

// Squared-distance check against the correlation radius.
bool WithinCorrelationRadius(const Eigen::Vector2d& a, const Eigen::Vector2d& b, double radius_m);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_
