#include "core/sim/sensor_simulation.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/model/camera_model.h"

namespace crowdmap {

uint64_t SplitMix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

absl::Status UndeclaredNoiseScales::Validate() const {
  for (const auto& [field, value] : {std::pair<const char*, double>{"speed", speed},
                                     {"steering", steering},
                                     {"pixel", pixel},
                                     {"gnss", gnss}}) {
    if (!(std::isfinite(value) && value > 0.0)) {
      return absl::InvalidArgumentError(
          absl::StrCat("undeclared_noise.", field, ": must be a finite factor > 0, got ", value));
    }
  }
  return absl::OkStatus();
}

NoiseModel DrawnNoise(const NoiseModel& declared, const UndeclaredNoiseScales& scales) {
  NoiseModel drawn = declared;
  drawn.speed_sigma_mps *= scales.speed;
  drawn.steering_sigma_rad *= scales.steering;
  drawn.pixel_sigma_px *= scales.pixel;
  return drawn;
}

Pose2 PoseAlongInputs(const std::vector<Pose2>& poses, const std::vector<OdometrySample>& inputs, double dt_s,
                      double wheelbase_m, double t_s) {
  const int j = std::clamp(static_cast<int>(std::floor(t_s / dt_s + 1e-9)), 0, static_cast<int>(poses.size()) - 1);
  const double rest = t_s - inputs[j].t_s;
  if (rest <= 0.0) return poses[j];
  return BicycleStep(poses[j], inputs[j].speed_mps, inputs[j].steering_rad, rest, wheelbase_m);
}

std::vector<OdometrySample> SimulateOdometry(const std::vector<OdometrySample>& truth, double duration_s,
                                             const NoiseModel& noise, NoiseSource* source) {
  std::vector<OdometrySample> out;
  out.reserve(truth.size());
  for (const OdometrySample& t : truth) {
    if (t.t_s > duration_s + 1e-9) break;
    const double speed = t.speed_mps + noise.speed_sigma_mps * source->Normal();
    out.push_back({t.t_s, speed, t.steering_rad + noise.steering_sigma_rad * source->Normal()});
  }
  return out;
}

double GnssSimulation::CorrelationTimeS() const {
  if (!ar1 || ar1_alpha <= 0.0) return 0.0;
  return -1.0 / (rate_hz * std::log(ar1_alpha));
}

std::vector<GnssFix> SimulateGnss(const TruePoseFn& pose_at, double duration_s, const LocalFrame& frame,
                                  const Calibration& calibration, const GnssSimulation& gnss, NoiseSource* source) {
  const double sigma = gnss.sigma_m * gnss.undeclared_scale;  // drawn; sigma_m is declared
  const double beta = std::sqrt(1.0 - gnss.ar1_alpha * gnss.ar1_alpha);
  // Stationary start. North is drawn before East: the order in which the scenario's first
  // passages (measured in the README) were drawn.
  const double first_north = sigma * source->Normal();
  Eigen::Vector2d error(sigma * source->Normal(), first_north);
  const int fixes = static_cast<int>(std::floor(duration_s * gnss.rate_hz + 1e-9)) + 1;
  std::vector<GnssFix> out;
  out.reserve(fixes);
  for (int k = 0; k < fixes; ++k) {
    const double t = k / gnss.rate_hz;
    if (k > 0) {
      const double north = sigma * source->Normal();
      const Eigen::Vector2d w(sigma * source->Normal(), north);
      error = gnss.ar1 ? Eigen::Vector2d(gnss.ar1_alpha * error + beta * w) : w;
    }
    const Pose2 pose = pose_at(t);
    const double c = std::cos(pose.z()), s = std::sin(pose.z());
    const Eigen::Vector2d& arm = calibration.gnss_lever_arm_m;
    const Eigen::Vector2d antenna = pose.head<2>() + Eigen::Vector2d(c * arm.x() - s * arm.y(), s * arm.x() + c * arm.y());
    const LatLon fix = frame.ToGeo(antenna + error);
    GnssFix g;
    g.t_s = t;
    g.lat_deg = fix.lat_deg;
    g.lon_deg = fix.lon_deg;
    g.cov_en_m2 = Eigen::Matrix2d::Identity() * gnss.sigma_m * gnss.sigma_m;
    out.push_back(g);
  }
  return out;
}

bool TruePixel(const Pose2& pose, const Eigen::Vector2d& landmark_m, const Calibration& camera, double min_range_m,
               double max_range_m, double* u_px) {
  const Eigen::Vector2d cam = LandmarkInCameraFrame(pose, landmark_m, camera);
  const double range = cam.norm();
  if (cam.x() <= 0.0 || range < min_range_m || range > max_range_m) return false;
  const double u = -camera.fx_px * cam.y() / cam.x() + camera.cx_px;
  if (u < 0.0 || u > camera.image_width_px) return false;
  *u_px = u;
  return true;
}

bool DetectedPixel(double u_true_px, const Calibration& camera, double pixel_sigma_px, NoiseSource* source,
                   double* u_px) {
  const double u = u_true_px + pixel_sigma_px * source->Normal();
  if (u < 0.0 || u > camera.image_width_px) return false;
  *u_px = u;
  return true;
}

}  // namespace crowdmap
