#ifndef CROWDMAP_CORE_LOCALIZATION_STREAMING_LOCALIZER_H_
#define CROWDMAP_CORE_LOCALIZATION_STREAMING_LOCALIZER_H_

#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/geo/local_frame.h"
#include "core/localization/passage_localizer.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

struct StreamingLocalizerOptions {
  // The filter starts once GNSS fixes span this long (s) and number at least `start_min_fixes`:
  // the heading is unknown at the first fix. The odometry + GNSS of that span are solved as a pose
  // graph (as a passage's initial poses are) and its last pose and covariance start the filter.
  // Detections before the start are not used.
  double start_span_s = 10.0;
  int start_min_fixes = 5;
  // A detection whose whitened innovation (pixel residual over the square root of its innovation
  // variance, at the predicted state) exceeds this is rejected; as PassageLocalizerOptions.
  double detection_gate_sigmas = 4.0;
  // Iterated update: re-linearisations per measurement batch (1 = extended Kalman filter).
  int max_iterations = 4;
  // Stop iterating when the pose moves less than this (m, and rad) between iterations.
  double iteration_tolerance = 1e-4;
  // The camera's yaw offset from the calibration given is a state of the filter with this prior
  // standard deviation (rad; as PassageLocalizerOptions::camera_yaw_sigma_rad: the vehicle's
  // calibration record's, or 1 degree without one). 0: the calibration is taken as exact.
  double camera_yaw_sigma_rad = 0.0;

  absl::Status Validate() const;
};

// The result of one input.
struct StreamingUpdate {
  bool tracking = false;      // false while the filter waits for its start (pose unset)
  LocalizedPose pose;         // at the input's time: the filter's estimate (predicted for odometry)
  // The update's correction of the predicted pose (posterior - prediction; zero for odometry) and
  // its largest component over that component's predicted sigma (East, North, heading).
  Eigen::Vector3d correction = Eigen::Vector3d::Zero();
  double correction_sigmas = 0.0;
  // The camera's estimated yaw offset and its standard deviation (both 0 when not estimated).
  double camera_yaw_offset_rad = 0.0;
  double camera_yaw_sigma_rad = 0.0;
  int detections_used = 0;    // of this input
  int detections_unmapped = 0;  // of landmarks the filter does not hold (not used)
  std::vector<RejectedDetection> rejected;

  std::string Brief() const;
};

// Localises a vehicle against the map as its measurements arrive (the on-vehicle counterpart of
// LocalizePassage). An iterated extended Kalman filter whose state is the current pose and the map
// landmarks it holds: the landmarks enter with the map's joint covariance as a correlated prior (the
// cross blocks given with them), so the pose covariance accounts for the map's uncertainty and a
// landmark seen again is not counted as new information. The motion between updates is the
// odometry preintegrated as the passage graph's odometry factor; GNSS and detections are the
// graph's GnssFactor and CameraFactor. Each update costs O(n^2) in the n landmarks held
// (removing landmarks far behind the vehicle keeps n small: RemoveMapLandmarks marginalises them
// out exactly). Inputs must come in time order. Not thread-safe.
class StreamingLocalizer {
 public:
  static absl::StatusOr<std::unique_ptr<StreamingLocalizer>> Create(const Calibration& calibration,
                                                                   const NoiseModel& noise,
                                                                   const StreamingLocalizerOptions& options = {});

  // Adds map landmarks with their joint covariance (map.cov_en_m2; landmarks already held are
  // skipped). They are taken as independent of the landmarks held before, whose information must
  // not have included them: add a group of correlated landmarks (a tile) in one call.
  absl::Status AddMapLandmarks(const LocalizationMap& map);
  // Marginalises landmarks out of the filter (unknown ids are ignored).
  void RemoveMapLandmarks(const std::vector<LandmarkId>& ids);

  // One encoder reading: returns the pose predicted to its time (the state is not changed).
  absl::StatusOr<StreamingUpdate> AddOdometry(const OdometrySample& sample);
  absl::StatusOr<StreamingUpdate> AddGnss(const GnssFix& fix);
  // The detections of one camera frame (all at one time).
  absl::StatusOr<StreamingUpdate> AddDetections(const std::vector<Detection>& frame);

  bool tracking() const { return tracking_; }
  int landmarks_held() const { return static_cast<int>(slot_ids_.size()); }
  bool HoldsLandmark(LandmarkId id) const { return slot_.count(id) > 0; }
  // The frame of the local coordinates (at the first GNSS fix); nullopt before it.
  const std::optional<LocalFrame>& frame() const { return frame_; }

 private:
  StreamingLocalizer(const Calibration& calibration, const NoiseModel& noise, const StreamingLocalizerOptions& options);

  // One residual of an update: its cost function and the state offset of each parameter block.
  struct Measurement;

  absl::Status CheckTime(double t_s) const;
  absl::Status Start();
  // Moves the state to t_s with the odometry since the state's time.
  void Predict(double t_s);
  // The predicted pose and its covariance at t_s, the state unchanged.
  void PredictPose(double t_s, Pose2* pose, Eigen::Matrix3d* cov) const;
  // An iterated update with `measurements` (whitened residuals), not yet applied.
  struct Step;
  // False when a residual cannot be evaluated at the state.
  bool ComputeUpdate(const std::vector<Measurement>& measurements, Step* step) const;
  void Apply(const Step& step);
  bool Update(const std::vector<Measurement>& measurements);
  // Detection gate after the update: the studentized residual of each detection (its residual at
  // the posterior over that residual's sigma); the worst above the gate is rejected and the update
  // recomputed without it. Catches a detection that only the other detections of the frame show
  // not to fit (one landmark alone cannot tell a map error from a heading error).
  bool UpdateGated(double t_s, std::vector<Measurement>* measurements, std::vector<const Detection*>* detections,
                   std::vector<RejectedDetection>* rejected);
  StreamingUpdate Output(double t_s, const Pose2& pose, const Eigen::Matrix3d& cov) const;
  StreamingUpdate Current() const;

  Calibration calibration_;
  NoiseModel noise_;
  StreamingLocalizerOptions options_;

  std::optional<LocalFrame> frame_;
  bool tracking_ = false;
  double state_t_s_ = 0.0;
  double last_input_t_s_ = -1e300;
  // The state row of the camera's yaw offset (-1: not estimated) and of the first landmark.
  int yaw_row() const { return options_.camera_yaw_sigma_rad > 0.0 ? 3 : -1; }
  int landmark_row(int slot) const { return (options_.camera_yaw_sigma_rad > 0.0 ? 4 : 3) + 2 * slot; }

  // State: pose (x, y, heading), the camera's yaw offset if estimated, then 2 rows per landmark
  // held; P its covariance.
  Eigen::VectorXd x_;
  Eigen::MatrixXd P_;
  std::unordered_map<LandmarkId, int> slot_;  // id -> landmark index (state rows 3 + 2 index)
  std::vector<LandmarkId> slot_ids_;
  // Landmarks given before the frame exists (converted at the start).
  std::vector<LocalizationMap> pending_;
  // Odometry from the last sample at or before the state's time on.
  std::vector<OdometrySample> odometry_;
  // Before the start: the GNSS fixes and odometry to start from.
  std::vector<GnssFix> start_gnss_;
  std::vector<OdometrySample> start_odometry_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_STREAMING_LOCALIZER_H_
