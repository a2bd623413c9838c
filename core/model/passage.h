#ifndef CROWDMAP_CORE_MODEL_PASSAGE_H_
#define CROWDMAP_CORE_MODEL_PASSAGE_H_

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"

namespace crowdmap {

using LandmarkId = int64_t;

// Sensor placement and intrinsics of one vehicle. Vehicle frame: x forward, y left, origin at the
// rear axle centre (the point the bicycle model moves).
struct Calibration {
  double wheelbase_m = 2.7;
  Eigen::Vector2d gnss_lever_arm_m{0.5, 0.0};
  Eigen::Vector2d camera_position_m{1.5, 0.0};
  double camera_yaw_rad = 0.0;
  double fx_px = 1000.0;
  double cx_px = 960.0;
  double image_width_px = 1920.0;
};

// Coloured GNSS error of a standard (single-frequency, code-only) receiver, for clients that know
// nothing better about theirs: a first-order Gauss-Markov process with this correlation time
// (alpha = 0.988 per fix at 1 Hz, the thesis's simulation) and stationary sigma per axis. Not
// applied by default: a passage that declares no process is estimated with white GNSS noise.
constexpr double kStandardReceiverGnssCorrelationTimeS = 82.8;
constexpr double kStandardReceiverGnssProcessSigmaM = 10.0;
// A fix's sigma per axis lies within what receivers report (RTK's millimetres to a fix kilometres
// off): its covariance's variances lie within the squares.
constexpr double kMinGnssSigmaM = 1e-3;
constexpr double kMaxGnssSigmaM = 1e4;

// Measurement noise the estimator assumes. Defaults: thesis Table 5.1, white GNSS noise.
struct NoiseModel {
  double speed_sigma_mps = 0.56;
  double steering_sigma_rad = 0.044;
  double pixel_sigma_px = 5.0;
  // GNSS error as a first-order Gauss-Markov (AR(1)) process per axis: between fixes dt apart,
  // e_k = alpha e_(k-1) + w_k with alpha = exp(-dt / tau) and w_k white with covariance
  // (1 - alpha^2) C_k, C_k the process's stationary covariance at fix k. tau in seconds;
  // 0 = white (independent fixes, as the estimator has always assumed).
  double gnss_correlation_time_s = 0.0;
  // Stationary standard deviation (m, per axis) of the GNSS error; 0 = each fix's own declared
  // covariance (cov_en_m2) is the error's. Set it when the receiver's reported covariance is not
  // the error's (receivers often report the white part only).
  double gnss_process_sigma_m = 0.0;
};

// One wheel/steering encoder reading, held until the next sample.
struct OdometrySample {
  double t_s = 0.0;  // seconds since the passage start
  double speed_mps = 0.0;
  double steering_rad = 0.0;
};

// One GNSS fix with its East/North covariance (m^2) at the fix.
struct GnssFix {
  double t_s = 0.0;
  double lat_deg = 0.0;
  double lon_deg = 0.0;
  Eigen::Matrix2d cov_en_m2 = Eigen::Matrix2d::Identity() * 100.0;
};

// One landmark detection: the horizontal pixel coordinate of a landmark with a known id.
struct Detection {
  double t_s = 0.0;
  LandmarkId landmark_id = 0;
  double u_px = 0.0;
};

// Everything a vehicle measured on one drive.
struct Passage {
  std::string vehicle_id;
  std::string passage_id;  // client-chosen; (vehicle_id, passage_id) is the idempotency key
  int64_t start_time_unix_ms = 0;
  Calibration calibration;
  NoiseModel noise;
  std::vector<OdometrySample> odometry;
  std::vector<GnssFix> gnss;
  std::vector<Detection> detections;
};

// SHA-256 (32 raw bytes) of what the passage measured: its start time, calibration, noise model
// and every sample, fix and detection, bit for bit, but not its vehicle_id or passage_id. Two
// uploads with the same digest are the same drive: the service takes it once, whatever ids it
// comes under, since a drive counted twice makes the map twice as sure of its errors.
std::string PassageContentDigest(const Passage& passage);

// Identifiers (vehicle_id, passage_id): 1 to kMaxIdLength printable ASCII characters without
// spaces (they appear in logs and file names). InvalidArgument naming `field` otherwise, without
// echoing the identifier.
constexpr size_t kMaxIdLength = 128;
absl::Status ValidateId(const char* field, const std::string& id);

// Checks a passage before it is accepted. The message names the offending field with its index,
// e.g. "gnss[12].lat_deg: latitude 91.2 outside [-90, 90]". Returns InvalidArgument on failure.
absl::Status ValidatePassage(const Passage& passage);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MODEL_PASSAGE_H_
