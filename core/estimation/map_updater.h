#ifndef CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_
#define CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_

#include <limits>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"

namespace crowdmap {

// How the current map enters a passage's graph (thesis section 4.4.3).
enum class UpdateStrategy {
  kCorrelated,            // "cc": one joint prior on the graph's map landmarks, whole passage at once
  kDecorrelated,          // "dc": one 2x2 prior per landmark; the map keeps no cross-covariances
  kCorrelatedSubdivided,  // "cc-gsd": cc on subgraphs of bounded state dimension (default)
};

absl::StatusOr<UpdateStrategy> ParseUpdateStrategy(std::string_view name);
const char* UpdateStrategyName(UpdateStrategy strategy);

struct MapUpdateOptions {
  UpdateStrategy strategy = UpdateStrategy::kCorrelatedSubdivided;
  // Largest state dimension (3 per pose + 2 per landmark) of one subgraph with cc-gsd.
  int max_subgraph_dim = 500;
  // Detections used per landmark and passage: the last K (0 = all).
  int detections_per_landmark = 5;
  // Cross-covariance blocks are kept only between landmarks closer than this (infinity = dense).
  double correlation_radius_m = std::numeric_limits<double>::infinity();
  int max_solver_iterations = 100;
  // Adaptive covariance inflation: when a (sub)graph solve's chi-square (2 x final cost) exceeds
  // its degrees of freedom by more than this many standard deviations (sqrt(2 dof)), the data
  // contradict the noise model (e.g. coloured GNSS errors); the passage's measurement covariances
  // are then scaled by the variance factor chi2/dof and the solve is repeated, so the passage
  // enters the map with an honest weight. 0 disables it.
  double inflation_test_sigmas = 4.0;
  // A solve whose chi2 per degree of freedom (after any inflation) exceeds this is refused rather
  // than committed. 0 disables the check.
  double max_chi2_per_dof = 0.0;
  // Remove the second-order bias of each (sub)graph's MAP solution before it is committed (see
  // CorrectSecondOrderBias): the MAP poses of one passage are decimetres off on average, the same
  // way on every passage of a road, which would otherwise accumulate in the map.
  bool bias_correction = true;

  absl::Status Validate() const;
};

// What applying one passage did; Brief() is a key=value log line.
struct PassageUpdateSummary {
  int nodes = 0;
  int subgraphs = 0;
  int landmarks_updated = 0;      // already in the map and seen by the passage
  int landmarks_created = 0;      // new to the map
  int landmarks_conditioned = 0;  // outside the passage, moved through their correlation
  int detections_used = 0;
  int detections_dropped = 0;     // e.g. behind the camera at the initial guess
  int solver_iterations = 0;
  double final_cost = 0.0;
  double max_variance_factor = 1.0;  // largest inflation applied to a subgraph (1 = none)
  double solve_ms = 0.0;
  double covariance_ms = 0.0;
  double bias_correction_ms = 0.0;
  double max_bias_correction_m = 0.0;  // largest landmark shift by the bias correction
  double total_ms = 0.0;
  int64_t map_version = 0;  // version after the update

  std::string Brief() const;
};

struct PassageUpdate {
  MapDelta delta;
  PassageUpdateSummary summary;
};

// Computes the map change one passage brings: builds its factor graph, subdivides it (cc-gsd),
// adds the map prior, solves with Ceres, recovers the landmark covariance and conditions the
// correlated landmarks outside the graph. `map` is only read; apply the returned delta to commit.
// The passage must have passed ValidatePassage. Errors: InvalidArgument for options or a passage
// that cannot be used (e.g. no landmark observable); Internal when the solver or the covariance
// fails (nothing is half-applied: the delta is returned only on success).
absl::StatusOr<PassageUpdate> ComputePassageUpdate(const Passage& passage, const MapUpdateOptions& options,
                                                   const MapReaderInterface& map);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_
