#ifndef CROWDMAP_CORE_ESTIMATION_GRAPH_BUILDER_H_
#define CROWDMAP_CORE_ESTIMATION_GRAPH_BUILDER_H_

#include <optional>
#include <vector>

#include <ceres/ceres.h>

#include "absl/status/statusor.h"
#include "core/estimation/gnss_correlation.h"
#include "core/geo/local_frame.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

struct GraphOptions {
  // Detections used per landmark: the last K of the passage (0 = all); with a spacing, only those
  // of the first camera frame in each interval of `detection_spacing_s` once the vehicle is
  // `detection_spacing_m` along its path from the frame before (every landmark keeps the same
  // frames, whatever the camera's rate; none are added while the vehicle stands still).
  int detections_per_landmark = 5;
  // The K spread evenly over each landmark's track (its first and last frames among them) instead
  // of its last K.
  bool spread_detections = false;
  double detection_spacing_s = 0.0;
  double detection_spacing_m = 0.0;
  // Measurement times closer than this share one pose node.
  double node_merge_tolerance_s = 1e-3;
  int max_init_iterations = 50;
  // Refine the aligned dead-reckoning with a Ceres solve of the odometry + GNSS pose graph. The
  // map updater skips it: it refines each subgraph's poses itself, together with the map.
  bool refine_initial_poses = true;
  // Window of GNSS fixes (s) the dead-reckoning is aligned to around each node.
  double alignment_window_s = 30.0;
  // Origin of the graph's East/North frame; unset: the passage's first GNSS fix. Graphs of several
  // passages solved together share one.
  std::optional<LatLon> frame_origin;
  // Set: a passage that declares white GNSS noise is checked for correlated errors (the residuals
  // of its fixes against its odometry + GNSS trajectory, gnss_correlation.h) and, where they show,
  // estimated with the Gauss-Markov process they give (PassageGraph::correlated_gnss).
  std::optional<CorrelatedGnssOptions> detect_correlated_gnss;
};

struct GnssObservation {
  int node = 0;
  double t_s = 0.0;            // fix time (s since the passage start)
  Eigen::Vector2d position_m;  // antenna position in the graph frame
  Eigen::Matrix2d cov_m2;      // in the graph frame
};

struct CameraObservation {
  int node = 0;
  LandmarkId landmark_id = 0;
  double u_px = 0.0;
};

// A passage as a factor graph in a local East/North frame (GraphOptions::frame_origin).
struct PassageGraph {
  LocalFrame frame{LatLon{}};
  std::vector<double> node_times_s;            // union of GNSS and used-detection times
  std::vector<Pose2> initial_poses;            // odometry + GNSS pose graph, solved
  std::vector<RelativeMotion> motions;         // motions[k]: node k -> k+1
  std::vector<GnssObservation> gnss;           // sorted by node; cov_m2: the error's stationary covariance
  // The GNSS error's Gauss-Markov correlation time (s), 0 = white (NoiseModel).
  double gnss_correlation_time_s = 0.0;
  std::vector<CameraObservation> detections;   // used detections, sorted by node
  int detections_dropped = 0;                  // detections not kept (beyond the last K)
  // With GraphOptions::detect_correlated_gnss, for a passage that declares white GNSS noise: its
  // fixes' residuals, and the process it is estimated with when they show correlated errors
  // (gnss_correlation_time_s and each fix's cov_m2 are then the process's).
  std::optional<GnssResidualStats> gnss_residuals;
  std::optional<CorrelatedGnss> correlated_gnss;

  int node_count() const { return static_cast<int>(node_times_s.size()); }
};

// Adds the pose blocks of nodes first..last (inclusive; poses[k] is node first + k) and the
// odometry and GNSS factors among them to `problem`, weighted by `odometry_loss` and `gnss_loss`
// (each may be null: unweighted).
// With coloured GNSS noise the fixes enter as the process's innovations (GnssAr1Factor): the
// passage's first fix alone, every other with the one before it. An innovation whose earlier fix
// lies before `first` is left out, like the odometry across the cut: the subgraphs of a passage
// then hold disjoint sets of independent innovations, so their factors add up without counting
// any GNSS error twice. `independent_fixes` enters every fix alone with its stationary covariance,
// whatever the process: for initial guesses, which need each fix's pull on its own pose to stay
// robust (the innovations of a coloured process barely hold a piece of the trajectory in place,
// and bounded bearing residuals to the map then turn it into wrong minima), not for estimates.
// With `speed_scale` (a parameter block of 1), the odometry factors are ScaledOdometryFactor's on it.
void AddPoseGraphFactors(const PassageGraph& graph, int first, int last, const Eigen::Vector2d& gnss_lever_arm_m,
                         ceres::LossFunction* odometry_loss, ceres::LossFunction* gnss_loss,
                         std::vector<Pose2>* poses, ceres::Problem* problem,
                         bool independent_fixes = false, double* speed_scale = nullptr);

absl::StatusOr<PassageGraph> BuildPassageGraph(const Passage& passage, const GraphOptions& options);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_GRAPH_BUILDER_H_
