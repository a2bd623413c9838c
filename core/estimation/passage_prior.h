#ifndef CROWDMAP_CORE_ESTIMATION_PASSAGE_PRIOR_H_
#define CROWDMAP_CORE_ESTIMATION_PASSAGE_PRIOR_H_

#include <functional>
#include <unordered_map>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/map/map_state.h"
#include "core/map/map_window.h"

namespace crowdmap {

// A map landmark outside a graph whose estimate moved by less than this is not rewritten (a change
// of the conditioning far from the graph, below any use).
constexpr double kMinWrittenChangeM = 1e-6;

// The map's joint Gaussian over the landmarks one passage touches, kept exact as its subgraphs
// commit, so that a passage factorises the map's information once instead of twice per subgraph.
//
// Build takes the joint covariance of the map landmarks the passage sees, P, from one
// factorisation of a window of the map around them; exact when the window is closed (the whole
// connected map, hops 0). Each subgraph's
// factor touches only landmarks of P and new ones N, so the posterior over the tracked set
// T = P u N (plus the new landmarks) follows from T's joint covariance alone (Condition): with O
// the tracked landmarks the factor touches and R = T \ O,
//   S's posterior:  information Sigma_OO^-1 (on O) + the factor's, 
//   R's move:       Sigma_RO Sigma_OO^-1 (mu'_O - mu_O),
//   T's covariance: Sigma_RR - K (Sigma_OO - Sigma'_OO) K^T, Sigma'_RS = K Sigma'_OS, K = Sigma_RO Sigma_OO^-1.
// The rest of the map W is conditionally independent of every factor given P, so it moves once, at
// the end (Finish), by Sigma_WP Sigma_PP^-1 (mu'_P - mu_P) with the covariance from before the
// passage: a single solve with the factorisation Build made. Exact on a linear problem with the
// whole connected map as the window (tested against the batch solve). A bounded window (hops > 0)
// gives a conservative Sigma_PP (MapWindow; not where folded passages' information reaches outside
// it), and the window's other landmarks move with their conditional under it; the map beyond the
// window stays.
class PassagePrior {
 public:
  // Over the landmarks of `ids` found in `map` (the others are left to the subgraphs to create),
  // from a window of the map around them.
  static absl::StatusOr<PassagePrior> Build(const MapReaderInterface& map, const std::vector<LandmarkId>& ids,
                                            const MapWindowOptions& window);

  bool Tracks(LandmarkId id) const { return index_.count(id) > 0; }
  // Joint covariance of tracked `ids`, East/North at their anchors (m^2).
  absl::StatusOr<Eigen::MatrixXd> Covariance(const std::vector<LandmarkId>& ids) const;

  // Adds `factor` (just added to `map`, in its landmarks' anchor offsets; each landmark tracked
  // or new) to the tracked joint distribution and writes, at `version`, the records of its
  // landmarks (estimate and marginal; `touch` is called on each) and of the other tracked
  // landmarks it moves. Returns how many of the latter were written.
  absl::StatusOr<int> Condition(const MapFactor& factor, int64_t version, const std::function<void(Landmark*)>& touch,
                                MapOverlay* map);

  // After the last subgraph: moves the map landmarks outside the tracked set through their
  // correlation with P, writing those that moved at `version`. Returns how many were written.
  absl::StatusOr<int> Finish(int64_t version, MapOverlay* map) const;

 private:
  PassagePrior(MapWindow window, int seen);

  MapWindow window_;  // P's connected map, P first (its seeds)
  int seen_ = 0;      // |P|
  Eigen::LLT<Eigen::MatrixXd> seen_covariance_;  // Sigma_PP before the passage
  std::vector<LandmarkId> ids_;  // T: P, then the landmarks the passage created
  std::unordered_map<LandmarkId, int> index_;
  Eigen::VectorXd mean_;        // T's offsets from their anchors, 2 per landmark
  Eigen::MatrixXd covariance_;  // T's joint covariance
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_PASSAGE_PRIOR_H_
