#ifndef CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_
#define CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_

// The steps that the sequential update (map_updater.cc) and the joint solve (joint_solve.cc)
// share: grouping a subgraph's detections, the initial guess, the solve, the linearisation.

#include <array>
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

// FailedPrecondition when `unfit` of a passage's `total` detections is more than
// options.max_unfit_detection_fraction allows (and at least MapUpdateOptions::kMinUnfitDetections).
absl::Status CheckDetectionsFit(int unfit, int total, const MapUpdateOptions& options);

// After a usable solve: the linearisation at the solution (the landmarks' marginal covariance,
// and the factor's without `factor_leaves_out`: GraphLinearization::Compute), its time added to
// `summary`.
absl::StatusOr<GraphLinearization> Linearize(ceres::Problem* problem, const std::vector<double*>& landmark_blocks,
                                             const MapUpdateOptions& options, PassageUpdateSummary* summary,
                                             const std::vector<ceres::ResidualBlockId>& factor_leaves_out = {});

// The second-order bias correction (if enabled) of the solution `linearization` was computed at,
// its time added to `summary`.
absl::Status CorrectBias(GraphLinearization* linearization, ceres::Problem* problem, const MapUpdateOptions& options,
                         PassageUpdateSummary* summary);

// The consistency test of a solve: chi2 / dof when chi2 exceeds dof by more than `test_sigmas`
// standard deviations (sqrt(2 dof)), the factor the measurement covariances are then inflated by;
// 1 otherwise (and when test_sigmas is 0). The normal approximation of the chi-square: for a
// sensor with a few degrees of freedom it fires more often than 4 sigmas say (about 1% at one).
// The chi-square's own quantile was tried (2026-11-29): identical maps as declared, but a camera
// twice as noisy as declared was found in fewer subgraphs and its maps were 2% worse (joint NEES
// 1.03 -> 1.08 over seeds 1-4), so the approximation stays.
double VarianceFactor(double chi2, double dof, double test_sigmas);

// The weights of a passage's measurements, one per sensor: 1 / the sensor's variance factor,
// which is 1 until a consistency test finds the sensor's noise larger than the passage declares.
// The losses are what the residual blocks are added with (the problem must not own them).
class MeasurementWeights {
 public:
  enum Sensor { kOdometry = 0, kGnss = 1, kCamera = 2 };
  static constexpr int kSensors = kPassageSensors;

  MeasurementWeights();
  ceres::LossFunctionWrapper* loss(Sensor sensor) { return &losses_[sensor]; }
  double factor(Sensor sensor) const { return factors_[sensor]; }
  const std::array<double, kSensors>& factors() const { return factors_; }
  // The sensor whose loss `loss` is; -1 for any other (a prior).
  int SensorOf(const ceres::LossFunction* loss) const;
  // Every sensor's variance factor times `factor` (the whole passage's test).
  void InflateAll(double factor);
  void Inflate(Sensor sensor, double factor);

 private:
  ceres::LossFunctionWrapper losses_[kSensors];
  std::array<double, kSensors> factors_ = {1.0, 1.0, 1.0};
};

// Each sensor's residuals at the solution: their chi-square (with the sensor's current weight)
// and their redundancy (GraphLinearization::Redundancies).
struct SensorResiduals {
  double chi2[MeasurementWeights::kSensors] = {0.0, 0.0, 0.0};
  double redundancy[MeasurementWeights::kSensors] = {0.0, 0.0, 0.0};
};
// Over `blocks` (the residual blocks of one passage), those weighted by `weights`.
SensorResiduals SensorResidualsOf(ceres::Problem* problem, const std::vector<ceres::ResidualBlockId>& blocks,
                                  const std::unordered_map<ceres::ResidualBlockId, double>& redundancies,
                                  const MeasurementWeights& weights);

// Variance component estimation (Foerstner): a sensor whose chi-square at the solution exceeds
// its redundancy by more than `test_sigmas` standard deviations has its variance factor raised by
// their ratio. The whole passage's test (VarianceFactor over all residuals) misses one sensor
// noisier than declared when the others hold most of the degrees of freedom; this finds it.
// Returns whether any weight changed (the graph is then to be solved again).
bool RaiseSensorVarianceFactors(const SensorResiduals& residuals, double test_sigmas, MeasurementWeights* weights);
// Rounds of that test (each a solve) per graph.
constexpr int kSensorTestRounds = 2;

// One passage's residual blocks in a graph and their weights.
struct WeightedBlocks {
  const std::vector<ceres::ResidualBlockId>* blocks;
  MeasurementWeights* weights;
};

// Linearize after a usable solve, then each passage's sensors tested (RaiseSensorVarianceFactors):
// while one is raised (at most kSensorTestRounds times) the graph is solved again (with
// `solver_options`; `solver_summary` is the last solve's) and linearised at the new solution.
// The largest factor each sensor's test applied goes to summary->sensor_test_factors.
absl::StatusOr<GraphLinearization> LinearizeTestingSensors(
    ceres::Problem* problem, const std::vector<double*>& landmark_blocks, const std::vector<WeightedBlocks>& passages,
    const ceres::Solver::Options& solver_options, const MapUpdateOptions& options,
    ceres::Solver::Summary* solver_summary, PassageUpdateSummary* summary,
    const std::vector<ceres::ResidualBlockId>& factor_leaves_out = {});

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_SUBGRAPH_STEPS_H_
