#ifndef CROWDMAP_CORE_LOCALIZATION_PASSAGE_LOCALIZER_H_
#define CROWDMAP_CORE_LOCALIZATION_PASSAGE_LOCALIZER_H_

#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/geo/local_frame.h"
#include "core/map/map_state.h"
#include "core/map/map_window.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

// The map landmarks a passage is localised against: their estimate and joint covariance (2 rows
// and columns per landmark, East/North at each landmark, m^2). Zero cross blocks are independent.
struct LocalizationMap {
  std::vector<LandmarkId> ids;
  std::vector<LatLon> positions;
  Eigen::MatrixXd cov_en_m2;
  int64_t version = 0;  // map version read

  absl::Status Validate() const;
};

// The landmarks of `map` that the passage detects, with their joint covariance (MapWindow).
absl::StatusOr<LocalizationMap> ReadLocalizationMap(const MapReaderInterface& map, const Passage& passage,
                                                    const MapWindowOptions& window = {});

struct PassageLocalizerOptions {
  // First solve: Cauchy loss on the pixel residuals with this scale (pixel sigmas), so that
  // detections that do not fit the map cannot drag the trajectory before they are gated.
  double robust_loss_scale_sigmas = 3.0;
  // A detection whose whitened pixel residual exceeds this (sigmas) is rejected.
  double detection_gate_sigmas = 4.0;
  // A map landmark is rejected with all its detections when the chi-square of its detections and
  // its map position (marginal), with the poses held, exceeds the quantile of this false-alarm
  // probability (dof: its detections).
  double landmark_gate_probability = 1e-3;
  // Rounds of gating and re-solving (each removes what the previous solve shows not to fit).
  int max_gating_rounds = 3;
  int max_solver_iterations = 100;
  // The camera's yaw offset from the passage's calibration is estimated with this prior standard
  // deviation (rad; e.g. the vehicle's calibration record's, or the map's 1 degree for a vehicle
  // without one): one state shared by every detection, so that a camera turned a fraction of a
  // degree does not bend the trajectory with an uncertainty that does not show it. 0: the
  // calibration is taken as exact.
  double camera_yaw_sigma_rad = 0.0;
  // A passage declaring white GNSS noise whose fixes' residuals show a lag-1 correlation above this
  // is localised with the Gauss-Markov process they give (as the map's updates do:
  // MapUpdateOptions::correlated_gnss_min_lag1). 0: the declared noise as it is.
  double correlated_gnss_min_lag1 = 0.5;

  absl::Status Validate() const;
};

// One pose of the trajectory, at a graph node.
struct LocalizedPose {
  double t_s = 0.0;
  Pose2 pose_m;               // rear axle (x, y) in the passage frame (East/North at `frame`'s origin), heading
                              // (rad, from East, counter-clockwise)
  LatLon position;            // rear axle, WGS84
  Eigen::Matrix3d cov;        // (East m, North m, heading rad), passage frame
  // The same at the pose: heading from East (counter-clockwise) and covariance in the East/North
  // frame at the position (the passage frame's axes turn by up to 1e-3 rad over a few km).
  double heading_en_rad = 0.0;
  Eigen::Matrix3d cov_en;
};

// A pose of the local `frame` with its covariance there, as a LocalizedPose (WGS84, and heading and
// covariance in the East/North frame at the pose).
LocalizedPose MakeLocalizedPose(const LocalFrame& frame, double t_s, const Pose2& pose_m, const Eigen::Matrix3d& cov);

struct RejectedDetection {
  double t_s = 0.0;
  LandmarkId landmark_id = 0;
  double u_px = 0.0;
  double whitened_residual = 0.0;  // at the solve that rejected it
  bool whole_landmark = false;     // rejected by the landmark gate (else the detection gate)
};

struct PassageLocalization {
  LocalFrame frame{LatLon{}};
  std::vector<LocalizedPose> poses;         // one per graph node, in time order
  std::vector<LandmarkId> landmarks_used;   // map landmarks with at least one kept detection
  std::vector<RejectedDetection> rejected;
  int detections_used = 0;
  int detections_unmapped = 0;  // of landmarks not in the map (not used)
  // The estimated camera yaw offset from the passage's calibration and its standard deviation
  // (PassageLocalizerOptions::camera_yaw_sigma_rad; both 0 when not estimated).
  double camera_yaw_offset_rad = 0.0;
  double camera_yaw_sigma_rad = 0.0;
  // The correlation time of the GNSS process the passage was localised with where its fixes
  // showed correlated errors it declared white (PassageLocalizerOptions::correlated_gnss_min_lag1);
  // 0: as declared.
  double gnss_correlation_time_s = 0.0;
  double chi2 = 0.0;            // final solve: sum of squared whitened residuals
  int dof = 0;                  // residuals - parameters
  int64_t map_version = 0;
  double solve_ms = 0.0;

  std::string Brief() const;
};

// Localises a whole passage against the map (no cuts): poses, landmarks and the map prior are
// solved jointly (the map enters as one correlated Gaussian prior per independent group of
// landmarks, as the CC update's prior does; the landmark estimates are not returned to the map).
// Detections that do not fit are gated after a robust first solve and the passage re-solved
// without them. The pose covariances are the marginals of the final Gauss-Newton information.
absl::StatusOr<PassageLocalization> LocalizePassage(const Passage& passage, const LocalizationMap& map,
                                                    const PassageLocalizerOptions& options = {});

// Upper quantile of the chi-square distribution: x with P(chi2(dof) > x) = probability
// (exact for 1 and 2 dof, Wilson-Hilferty above: within 1% at the probabilities used here).
double ChiSquareUpperQuantile(double dof, double probability);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_PASSAGE_LOCALIZER_H_
