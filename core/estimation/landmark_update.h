#ifndef CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_
#define CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_

#include <functional>
#include <string>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/geo/local_frame.h"
#include "core/map/map_state.h"
#include "core/map/map_window.h"

namespace crowdmap {

class PassagePrior;

struct LandmarkUpdateOptions {
  bool correlated = true;  // CC (joint prior, one joint factor) or DC (2x2 priors, one factor per landmark)
  // CC: where the prior and the conditioning come from. Given, the passage's tracked joint
  // distribution (exact; it must track every map landmark of the graph); otherwise a window of the
  // map around the graph's landmarks, factorised for the prior and again after the factor is added.
  PassagePrior* passage_prior = nullptr;
  MapWindowOptions window;
  std::string vehicle_id;  // provenance of the factor
  std::string passage_id;
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
//      recovered from the map's information) or one DC prior per landmark.
//   2. the caller solves the problem;
//   3. Commit: with the graph's information about S at the solution (the inverse of its marginal
//      covariance) Lambda' and its bias-corrected estimate x', the graph's own factor is what it
//      adds to the prior P:
//        information Lambda' - P,   information vector Lambda' x' - P mu_O,
//      the information of its measurements once its poses are eliminated (less the cost's
//      remaining gradient g, so that the factor does not depend on how far the solver got:
//      information vector Lambda' x' - P mu_O - g). It is added to the map
//      (in the landmarks' anchor offsets) and the map is re-solved around S, which moves the
//      correlated landmarks outside the graph as exact Gaussian conditioning would. DC keeps one
//      factor per landmark from the 2x2 marginals, so its map holds no correlations.
class LandmarkUpdate {
 public:
  // `map` is read for the prior and receives the changes.
  LandmarkUpdate(const LocalFrame& frame, MapOverlay* map, std::vector<LandmarkId> ids);

  int size() const { return static_cast<int>(ids_.size()); }
  LandmarkId id(int i) const { return ids_[i]; }
  bool in_map(int i) const { return in_map_[i]; }
  // Parameter block of landmark i (local frame, metres); map landmarks start at their map position.
  double* block(int i) { return positions_[i].data(); }
  const Eigen::Vector2d& position(int i) const { return positions_[i]; }

  // Adds the map prior for the landmarks already in the map (options.correlated,
  // options.passage_prior, options.window). FailedPrecondition when the map's information around
  // them is not positive definite.
  absl::Status AddMapPrior(const LandmarkUpdateOptions& options, ceres::Problem* problem);

  // For a map landmark after the solve: the squared Mahalanobis length of its move from the prior
  // mean, in the prior's marginal covariance (0 for a new landmark). The move of an honest update
  // has covariance prior - posterior, smaller than the prior, so this is a conservative test.
  double PriorShiftMahalanobis2(int i) const;

  // After a usable solve: with the graph landmarks' estimate in their blocks, `cov_ss` their
  // marginal covariance and `gradient_ss` the cost's reduced gradient where it was taken
  // (GraphLinearization), adds the graph's factor to the map, re-solves it and writes every change
  // at a new map version. `touch` is called on each record of the graph's landmarks before it is
  // written (counts).
  absl::StatusOr<LandmarkUpdateStats> Commit(const Eigen::MatrixXd& cov_ss, const Eigen::VectorXd& gradient_ss,
                                             const LandmarkUpdateOptions& options,
                                             const std::function<void(Landmark*)>& touch);

 private:
  const LocalFrame& frame_;
  MapOverlay* map_;
  std::vector<LandmarkId> ids_;
  std::vector<bool> in_map_;
  std::vector<Eigen::Vector2d> positions_;
  std::vector<int> prior_index_;    // indices (into ids_) of the map landmarks O
  Eigen::VectorXd prior_mean_;      // mu_O, local frame
  Eigen::MatrixXd prior_information_;  // P on O, local frame
  std::vector<Eigen::Matrix2d> prior_marginals_;  // the 2x2 marginals of P's inverse
};

// Adds `factor` (whose information is over the graph's local-frame positions `local`, stacked as
// the factor's landmarks) to the map in the landmarks' anchor offsets, creating the records of new
// landmarks at their position in `local`. Returns the factor's id. Exposed for the joint solve.
int64_t AddLocalFactor(const LocalFrame& frame, const Eigen::VectorXd& local, MapFactor factor, MapOverlay* map);

// How ResolveAround refreshes the stored marginal covariances.
struct MarginalRefresh {
  // The seeds' new marginals (East/North at their anchors), when the caller has them (a graph's
  // posterior); empty: recovered from the window.
  std::vector<Eigen::Matrix2d> seeds;
  // Also recover the marginals of the other landmarks the window re-estimates. Needed when
  // information was removed (their stored marginals would be too small); otherwise they stay as
  // they were, which only information added since can have made larger than the exact ones.
  bool others = false;
};

// Re-solves the map around `seeds` after factors changed, writing the records that changed at
// `version` (the seeds always; others when they moved by more than a micrometre or their marginal
// was refreshed); `touch` is called on the seeds' records. Returns how many landmarks other than
// the seeds were written.
absl::StatusOr<int> ResolveAround(const std::vector<LandmarkId>& seeds, const MarginalRefresh& refresh,
                                  const MapWindowOptions& window, int64_t version,
                                  const std::function<void(Landmark*)>& touch, MapOverlay* map);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_LANDMARK_UPDATE_H_
