#include "core/sim/city_scenario.h"

#include <algorithm>
#include <cmath>
#include <random>
#include <unordered_map>

#include "absl/strings/str_cat.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

constexpr uint64_t kVehicleStream = 0x7E41C1Eull;
constexpr uint64_t kPassageStream = 0xC17Dull;
constexpr uint64_t kOutageStream = 0x07A6Eull;
constexpr uint64_t kCalibrationStream = 0xCA11B8ull;

bool HasYawBias(NoiseConfig noise) { return noise == NoiseConfig::kYawBias || noise == NoiseConfig::kGnssAr1YawBias; }
bool HasGnssAr1(NoiseConfig noise) { return noise == NoiseConfig::kGnssAr1 || noise == NoiseConfig::kGnssAr1YawBias; }

uint64_t PassageSeed(uint64_t seed, int index) {
  return SplitMix64(SplitMix64(seed ^ kPassageStream) ^ static_cast<uint64_t>(index));
}

// A vehicle's own calibration, drawn from CalibrationSpread on its own stream (the other draws of
// the vehicle stay what they are without it).
Calibration VariedCalibration(uint64_t seed, int vehicle_index) {
  std::mt19937_64 rng(SplitMix64(SplitMix64(seed ^ kCalibrationStream) ^ static_cast<uint64_t>(vehicle_index)));
  const auto uniform = [&rng](double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng); };
  const CalibrationSpread s;
  Calibration c;
  c.image_width_px = std::round(uniform(s.image_width_min_px, s.image_width_max_px));
  c.fx_px = 0.5 * c.image_width_px / std::tan(0.5 * uniform(s.fov_min_rad, s.fov_max_rad));
  c.cx_px = c.image_width_px * (0.5 + uniform(-s.principal_point_offset_max, s.principal_point_offset_max));
  c.camera_position_m = {uniform(s.camera_x_min_m, s.camera_x_max_m), uniform(-s.camera_y_max_m, s.camera_y_max_m)};
  c.camera_yaw_rad = uniform(-s.camera_yaw_max_rad, s.camera_yaw_max_rad);
  c.gnss_lever_arm_m = {uniform(s.antenna_x_min_m, s.antenna_x_max_m), uniform(-s.antenna_y_max_m, s.antenna_y_max_m)};
  c.wheelbase_m = uniform(s.wheelbase_min_m, s.wheelbase_max_m);
  return c;
}

}  // namespace

absl::StatusOr<CityScenario> CityScenario::Create(const CityScenarioOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  return CityScenario(options);
}

CityVehicle CityScenario::Vehicle(int vehicle_index) const {
  const CityScenarioOptions& o = options_;
  std::mt19937_64 rng(SplitMix64(SplitMix64(o.seed ^ kVehicleStream) ^ static_cast<uint64_t>(vehicle_index)));
  std::uniform_real_distribution<double> rate_factor(1.0 - o.rate_variation, 1.0 + o.rate_variation);
  std::normal_distribution<double> normal(0.0, 1.0);
  CityVehicle v;
  v.index = vehicle_index;
  v.vehicle_id = absl::StrCat("city-v", vehicle_index);
  v.odometry_rate_hz = o.odometry_rate_hz * rate_factor(rng);
  v.gnss_rate_hz = o.gnss_rate_hz * rate_factor(rng);
  v.camera_rate_hz = o.camera_rate_hz * rate_factor(rng);
  v.calibration = o.vary_calibration ? VariedCalibration(o.seed, vehicle_index) : o.calibration;
  v.true_camera = v.calibration;
  v.true_camera.camera_yaw_rad += o.vehicle_yaw_bias_sigma_rad * normal(rng);
  if (HasYawBias(o.noise)) v.true_camera.camera_yaw_rad += o.camera_yaw_bias_rad;
  // Drawn last and only when asked for, so that the other draws stay what they were.
  if (o.vehicle_speed_scale_sigma > 0.0) v.speed_scale = 1.0 + o.vehicle_speed_scale_sigma * normal(rng);
  return v;
}

CityDrive CityScenario::TrueDrive(int index) const {
  const CityVehicle vehicle = Vehicle(index % options_.vehicles);
  std::mt19937_64 rng(PassageSeed(options_.seed, index));
  CityScenarioOptions driven = options_;  // driven with the vehicle's own wheelbase
  driven.calibration = vehicle.calibration;
  const double cruise_mps = std::uniform_real_distribution<double>(options_.speed_min_mps, options_.speed_max_mps)(rng);
  const int streets_x = static_cast<int>(layout_.street_x_m().size()) -
                        (index < options_.late_from_passage ? options_.late_blocks_x : 0);
  return DriveRandomRoute(layout_, driven, 1.0 / vehicle.odometry_rate_hz, cruise_mps, &rng, streets_x);
}

Passage CityScenario::MakePassage(int index) const { return MakePassageWithTruth(index).first; }

std::pair<Passage, CityDrive> CityScenario::MakePassageWithTruth(int index) const {
  const CityScenarioOptions& o = options_;
  const CityVehicle vehicle = Vehicle(index % o.vehicles);
  CityDrive drive = TrueDrive(index);
  NoiseSource noise(SplitMix64(PassageSeed(o.seed, index)));

  Passage p;
  p.vehicle_id = vehicle.vehicle_id;
  p.passage_id = absl::StrCat("city-p", index, "-s", o.seed, "-l", o.layout_seed, "-g", o.blocks_x, "x", o.blocks_y,
                              "x", o.block_m, "-r", o.route_length_m, "-", NoiseConfigName(o.noise));
  p.start_time_unix_ms = 1767225600000LL + static_cast<int64_t>(index) * 300000;
  p.calibration = vehicle.calibration;
  p.noise = o.noise_model;
  const NoiseModel drawn = DrawnNoise(o.noise_model, o.undeclared_noise);
  p.odometry = SimulateOdometry(drive.inputs, drive.duration_s, drawn, &noise);
  for (OdometrySample& sample : p.odometry) sample.speed_mps *= vehicle.speed_scale;

  GnssSimulation gnss;
  gnss.rate_hz = vehicle.gnss_rate_hz;
  gnss.sigma_m = o.gnss_sigma_m;
  gnss.undeclared_scale = o.undeclared_noise.gnss;
  gnss.ar1 = HasGnssAr1(o.noise);
  gnss.ar1_alpha = o.gnss_ar1_alpha;
  p.noise.gnss_correlation_time_s = gnss.CorrelationTimeS();  // the passage declares its GNSS process
  p.gnss = SimulateGnss([&drive](double t) { return drive.PoseAt(t); }, drive.duration_s, frame(),
                        vehicle.calibration, gnss, &noise);
  // An outage removes fixes after they are drawn: the receiver's error evolves through it, and
  // the other measurements of the passage are those it has without an outage.
  if (o.gnss_outage_probability > 0.0) {
    std::mt19937_64 rng(SplitMix64(PassageSeed(o.seed, index) ^ kOutageStream));
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    const double length_s = std::uniform_real_distribution<double>(o.gnss_outage_min_s, o.gnss_outage_max_s)(rng);
    constexpr double kKeptAtEndsS = 10.0;
    const double room_s = drive.duration_s - 2.0 * kKeptAtEndsS - length_s;
    if (unit(rng) < o.gnss_outage_probability && room_s > 0.0) {
      const double from_s = kKeptAtEndsS + room_s * unit(rng);
      p.gnss.erase(std::remove_if(p.gnss.begin(), p.gnss.end(),
                                  [&](const GnssFix& f) { return f.t_s >= from_s && f.t_s < from_s + length_s; }),
                   p.gnss.end());
    }
  }

  // A camera standing still sees the same image, and its detector makes the same error on it: each
  // landmark's pixel error is drawn again only once the vehicle has moved since its last draw
  // (while moving, one draw per frame and landmark, as before stops existed).
  struct PixelError {
    Pose2 drawn_at;
    double error_px = 0.0;
  };
  std::unordered_map<LandmarkId, PixelError> pixel_errors;
  const int frames = static_cast<int>(std::floor(drive.duration_s * vehicle.camera_rate_hz + 1e-9)) + 1;
  for (int k = 0; k < frames; ++k) {
    const double t = k / vehicle.camera_rate_hz;
    const Pose2 pose = drive.PoseAt(t);
    for (const VisibleLandmark& seen : VisibleLandmarks(pose, vehicle.true_camera)) {
      auto [it, fresh] = pixel_errors.try_emplace(seen.id);
      if (fresh || (it->second.drawn_at - pose).norm() > 1e-9) {
        it->second = {pose, drawn.pixel_sigma_px * noise.Normal()};
      }
      const double u = seen.u_px + it->second.error_px;
      if (u >= 0.0 && u <= vehicle.true_camera.image_width_px) p.detections.push_back({t, seen.id, u});
    }
  }
  return {std::move(p), std::move(drive)};
}

std::vector<VisibleLandmark> CityScenario::VisibleLandmarks(const Pose2& pose, const Calibration& camera) const {
  const double c = std::cos(pose.z()), s = std::sin(pose.z());
  const Eigen::Vector2d& offset = camera.camera_position_m;
  const Eigen::Vector2d camera_m =
      pose.head<2>() + Eigen::Vector2d(c * offset.x() - s * offset.y(), s * offset.x() + c * offset.y());
  std::vector<VisibleLandmark> seen;
  layout_.ForEachLandmarkNear(camera_m, options_.max_detection_range_m, [&](const TruthLandmark& lm) {
    double u = 0.0;
    if (!TruePixel(pose, lm.position_m, camera, options_.min_detection_range_m, options_.max_detection_range_m, &u)) {
      return;
    }
    if (options_.occlusion && !layout_.LineOfSightClear(camera_m, lm.position_m)) return;
    seen.push_back({lm.id, u});
  });
  std::sort(seen.begin(), seen.end(), [](const VisibleLandmark& a, const VisibleLandmark& b) { return a.id < b.id; });
  return seen;
}

}  // namespace crowdmap
