#ifndef CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_
#define CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_

// The Cramer-Rao bound of a map: the smallest covariance any unbiased estimator can reach from
// the passages' measurements, the inverse of their Fisher information about the landmarks.
// Passages share no poses, so the map's Fisher information is the sum of each passage's, taken at
// the truth with its poses eliminated (the information form's factors, at the true values).

#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/estimation/graph_builder.h"
#include "core/model/passage.h"

namespace crowdmap {

// One passage's Fisher information about the landmarks it detects, in the graph frame of
// `options.frame_origin` (East/North, metres), from the estimator's own graph (`options`: the
// same nodes, detections and noise model) evaluated at the true poses and landmark positions.
// Coloured GNSS noise declared by the passage (NoiseModel::gnss_correlation_time_s) is whitened
// with the Cholesky factor of the fixes' full correlation matrix, not with the estimator's
// factors, so that the bound checks them.
struct PassageFisherInformation {
  std::vector<LandmarkId> landmarks;
  // With the camera yaw estimated: the passage's vehicle, whose camera yaw offset (one state per
  // vehicle, shared by its passages) follows the landmarks in `information`.
  std::optional<std::string> camera_yaw_vehicle;
  Eigen::MatrixXd information;  // 2 rows per landmark, in `landmarks` order, then the yaw's row
};

// `true_pose(t)` is the vehicle's true pose at t (s since the passage start) and
// `true_landmark(id)` a landmark's true position, both in the frame at options.frame_origin
// (which must be set). Detections of landmarks without a true position are left out.
// `true_camera_yaw_offset_rad`: set when the estimator estimates the vehicle's camera yaw offset
// (MapUpdateOptions::estimate_camera_yaw), the true offset of its camera from the declared
// calibration; the offset is then a state of the bound, not eliminated with the poses.
absl::StatusOr<PassageFisherInformation> PassageLandmarkInformation(
    const Passage& passage, const GraphOptions& options, const std::function<Pose2(double)>& true_pose,
    const std::function<std::optional<Eigen::Vector2d>(LandmarkId)>& true_landmark,
    std::optional<double> true_camera_yaw_offset_rad = std::nullopt);

// Sums passages' Fisher information and gives the bound.
class CramerRaoBound {
 public:
  // `camera_yaw_prior_sigma_rad`: the estimator's prior on a vehicle's camera yaw offset, added
  // once per vehicle whose passages carry the yaw state (a Bayesian bound: the prior is
  // information the estimator has). 0: no prior.
  // `landmark_prior_sigma_m`: a diffuse prior added once per landmark (0: none). It keeps the bound
  // finite where the passages see a landmark along one ray only (the estimator holds such a
  // landmark back), and changes the others' by about (their sigma / this)^2, relatively.
  explicit CramerRaoBound(double camera_yaw_prior_sigma_rad = 0.0, double landmark_prior_sigma_m = 0.0)
      : camera_yaw_prior_sigma_rad_(camera_yaw_prior_sigma_rad), landmark_prior_sigma_m_(landmark_prior_sigma_m) {}

  void Add(const PassageFisherInformation& passage);
  // The bound on each landmark seen so far: its 2x2 block of the inverse of the summed
  // information. FailedPrecondition when the information is singular (a landmark the passages do
  // not determine).
  absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> Covariances() const;
  // The bound's joint covariance of `ids` (2 rows and columns each, in that order): with it, a
  // map's stacked errors e give e^T C^-1 e, chi-square with 2 n degrees of freedom for an efficient
  // unbiased estimator. InvalidArgument for a landmark no passage saw; FailedPrecondition as
  // Covariances().
  absl::StatusOr<Eigen::MatrixXd> JointCovariance(const std::vector<LandmarkId>& ids) const;

 private:
  // The inverse of the summed information (every landmark and yaw state).
  absl::StatusOr<Eigen::MatrixXd> Inverse() const;
  // Offset of each landmark (2 rows) and of each vehicle's camera yaw (1 row) in information_.
  int Grow(int rows);  // a new variable's offset
  std::map<LandmarkId, int> landmark_offset_;
  std::map<std::string, int> vehicle_offset_;
  Eigen::MatrixXd information_;  // its leading dim_ x dim_ block; the rest is spare capacity
  int dim_ = 0;
  double camera_yaw_prior_sigma_rad_;
  double landmark_prior_sigma_m_;
};

// Expected distance |e| of a zero-mean 2-D Gaussian error with covariance `cov`: the bound's
// counterpart of a landmark's distance error.
double ExpectedDistance(const Eigen::Matrix2d& cov);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_CRAMER_RAO_H_
