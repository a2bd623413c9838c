#ifndef CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_
#define CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_

// The steps that the sequential update (map_updater.cc) and the joint solve (joint_solve.cc)
// share: grouping a subgraph's detections, the initial guess, the solve, the linearisation.

#include <chrono>
#include <set>
#include <unordered_set>
#include <utility>
#include <vector>

#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/estimation/graph_builder.h"
#include "core/estimation/graph_linearization.h"
#include "core/estimation/map_updater.h"
#include "core/estimation/subdivision.h"
#include "core/map/map_state.h"

namespace crowdmap {

// Calls options.yield_point, if set.
void Yield(const MapUpdateOptions& options);

double MillisecondsSince(std::chrono::steady_clock::time_point start);

// The detections of one subgraph grouped by landmark, with the landmarks' initial positions.
struct SubgraphLandmarks {
  std::vector<LandmarkId> ids;
  std::vector<bool> known;  // in the map
  std::vector<Eigen::Vector2d> initial;
  std::vector<std::vector<const CameraObservation*>> detections;
};

// The detections of nodes range.first..range.last grouped by landmark; map landmarks start at
// their map position.
SubgraphLandmarks GroupDetections(const PassageGraph& graph, const NodeRange& range, const MapReaderInterface& map);

// A detection: its node and landmark.
using DetectionKey = std::pair<int, LandmarkId>;

// Removes the landmarks in `landmarks_aside` with their detections, and the detections in
// `detections_aside`; returns the detections removed.
int SetAside(const std::unordered_set<LandmarkId>& landmarks_aside, const std::set<DetectionKey>& detections_aside,
             SubgraphLandmarks* landmarks);

ceres::Solver::Options SolverOptions(int max_iterations);
// The options of a subgraph's solve from its refined initial guess: SolverOptions with Levenberg-
// Marquardt started close to Gauss-Newton.
ceres::Solver::Options SubgraphSolveOptions(int max_iterations);

// ceres::Solve with options.yield_point called after each iteration and at the end.
void Solve(const MapUpdateOptions& options, ceres::Solver::Options solver_options, ceres::Problem* problem,
           ceres::Solver::Summary* summary);

// Refines the subgraph's initial poses against odometry, GNSS and the map landmarks held fixed.
void InitializePoses(const PassageGraph& graph, const NodeRange& range, const Passage& passage,
                     const MapUpdateOptions& update_options, SubgraphLandmarks* landmarks, std::vector<Pose2>* poses);

// Initial positions of the new landmarks and the usable detections (see subgraph_steps.cc);
// returns the detections dropped.
int InitializeLandmarks(const std::vector<Pose2>& poses, const NodeRange& range, const Calibration& calib,
                        double edge_margin_px, double min_parallax_rad, int min_new_detections,
                        SubgraphLandmarks* landmarks);

// How well a passage's rays determine a landmark's position, with the poses held where they are:
// the largest standard deviation (m) of the position from its detections alone, and its largest
// distance from the cameras. A landmark whose rays barely cross is free along them: a solve can
// place it far off, and its linearised covariance does not describe that.
struct RayGeometry {
  double sigma_m = 0.0;
  double max_range_m = 0.0;
};
RayGeometry NewLandmarkGeometry(const std::vector<Pose2>& poses, int first_node,
                                const std::vector<const CameraObservation*>& detections,
                                const Eigen::Vector2d& position, const Calibration& calib, double pixel_sigma_px);

// Whether a new landmark may enter the map with this geometry (the options' creation rule).
bool WellDeterminedNewLandmark(const RayGeometry& geometry, const MapUpdateOptions& options);

// After a usable solve: the landmarks' marginal covariance (and the factor's, without
// `factor_leaves_out`: GraphLinearization::Compute) and (if enabled) the second-order bias
// correction of the solution, with their times added to `summary`.
absl::StatusOr<GraphLinearization> LinearizeSolution(ceres::Problem* problem, const std::vector<double*>& landmark_blocks,
                                                     const MapUpdateOptions& options, PassageUpdateSummary* summary,
                                                     const std::vector<ceres::ResidualBlockId>& factor_leaves_out = {});

// The consistency test of a solve: chi2 / dof when chi2 exceeds dof by more than `test_sigmas`
// standard deviations (sqrt(2 dof)), the factor the measurement covariances are then inflated by;
// 1 otherwise (and when test_sigmas is 0).
double VarianceFactor(double chi2, double dof, double test_sigmas);

// Scales the measurements weighted by `weight` for a variance factor (their covariances times it).
void Inflate(double variance_factor, ceres::LossFunctionWrapper* weight);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_
