#include "core/sim/scenario.h"

#include <algorithm>
#include <cmath>
#include <random>

#include "absl/strings/str_cat.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

// Route curvature profile: (duration s, curvature 1/m) pieces, blended smoothly. A road-like
// loop segment: long straights, gentle bends, two tighter turns; about 165 s at about 12 m/s.
struct CurvePiece {
  double duration_s;
  double curvature_per_m;
};
constexpr CurvePiece kRoute[] = {
    {14.0, 0.0},        {9.0, 1.0 / 180.0}, {16.0, 0.0},          {11.0, -1.0 / 120.0}, {12.0, 0.0},
    {7.0, 1.0 / 60.0},  {18.0, 0.0},        {10.0, -1.0 / 250.0}, {14.0, 0.0},          {8.0, 1.0 / 70.0},
    {15.0, 0.0},        {9.0, -1.0 / 90.0}, {22.0, 0.0},
};
constexpr double kTransitionS = 3.0;  // curvature ramps (clothoid-like) between pieces
constexpr double kMeanSpeedMps = 12.0;

double RouteProfileS() {
  double total = 0.0;
  for (const CurvePiece& piece : kRoute) total += piece.duration_s;
  return total;
}

double CurvatureAt(double t, bool repeat) {
  // Piecewise-constant profile smoothed with a raised-cosine ramp centred on each boundary. The
  // profile starts and ends straight, so repeating it adds no jump.
  if (repeat) t = std::fmod(t, RouteProfileS());
  double start = 0.0, value = kRoute[0].curvature_per_m;
  for (size_t i = 1; i < std::size(kRoute); ++i) {
    start += kRoute[i - 1].duration_s;
    const double w = std::clamp((t - start + 0.5 * kTransitionS) / kTransitionS, 0.0, 1.0);
    value += (kRoute[i].curvature_per_m - kRoute[i - 1].curvature_per_m) * 0.5 * (1.0 - std::cos(M_PI * w));
  }
  return value;
}

double SpeedAt(double t) { return kMeanSpeedMps + 1.5 * std::sin(2.0 * M_PI * t / 70.0) + 0.5 * std::sin(2.0 * M_PI * t / 23.0); }

// The thesis's four real traffic signs stand at fixed places; the others are random but depend
// only on their index, so a scenario with more landmarks extends one with fewer.
struct LandmarkPlacement {
  double arc_fraction;
  double lateral_m;  // left of the road (negative: right)
};
constexpr LandmarkPlacement kFixedLandmarks[] = {{0.12, 4.5}, {0.37, -5.0}, {0.61, 3.5}, {0.86, -4.0}};

LandmarkPlacement RandomPlacement(int index) {
  std::mt19937_64 rng(SplitMix64(0xC0FFEEull + static_cast<uint64_t>(index)));
  std::uniform_real_distribution<double> along(0.03, 0.97), offset(3.0, 8.0), side(0.0, 1.0);
  const double arc = along(rng);
  const double lateral = offset(rng) * (side(rng) < 0.5 ? 1.0 : -1.0);
  return {arc, lateral};
}

}  // namespace

absl::StatusOr<NoiseConfig> ParseNoiseConfig(std::string_view name) {
  if (name == "white") return NoiseConfig::kWhite;
  if (name == "gnss-ar1") return NoiseConfig::kGnssAr1;
  if (name == "yaw-bias") return NoiseConfig::kYawBias;
  if (name == "ar1+yaw") return NoiseConfig::kGnssAr1YawBias;
  return absl::InvalidArgumentError(
      absl::StrCat("noise: unknown '", std::string(name), "' (expected white, gnss-ar1, yaw-bias or ar1+yaw)"));
}

const char* NoiseConfigName(NoiseConfig config) {
  switch (config) {
    case NoiseConfig::kWhite:
      return "white";
    case NoiseConfig::kGnssAr1:
      return "gnss-ar1";
    case NoiseConfig::kYawBias:
      return "yaw-bias";
    case NoiseConfig::kGnssAr1YawBias:
      return "ar1+yaw";
  }
  return "?";
}

absl::Status ScenarioOptions::Validate() const {
  if (landmarks < 1) return absl::InvalidArgumentError(absl::StrCat("landmarks: must be >= 1, got ", landmarks));
  if (!(duration_s > 1.0)) return absl::InvalidArgumentError("duration_s: must be > 1");
  if (!(odometry_rate_hz > 0) || !(gnss_rate_hz > 0) || !(camera_rate_hz > 0)) {
    return absl::InvalidArgumentError("sensor rates must be > 0");
  }
  if (!(gnss_sigma_m > 0)) return absl::InvalidArgumentError("gnss_sigma_m: must be > 0");
  if (!(gnss_ar1_alpha >= 0.0 && gnss_ar1_alpha < 1.0)) {
    return absl::InvalidArgumentError("gnss_ar1_alpha: must lie in [0, 1)");
  }
  if (!(piece_min_m == 0.0 && piece_max_m == 0.0) && !(piece_min_m > 0.0 && piece_max_m >= piece_min_m)) {
    return absl::InvalidArgumentError(absl::StrCat("piece_min_m, piece_max_m: must be both 0 (whole passages) or 0 < min <= max, got ",
                                                   piece_min_m, ", ", piece_max_m));
  }
  if (vehicles < 0 || !(vehicle_yaw_bias_sigma_rad >= 0.0 && vehicle_yaw_bias_sigma_rad < 0.5)) {
    return absl::InvalidArgumentError(absl::StrCat("vehicles, vehicle_yaw_bias_sigma_rad: must be >= 0 and in [0, 0.5), got ",
                                                   vehicles, ", ", vehicle_yaw_bias_sigma_rad));
  }
  if (absl::Status s = undeclared_noise.Validate(); !s.ok()) return s;
  if (alternate_directions && piece_max_m > 0.0) {
    return absl::InvalidArgumentError("alternate_directions: not with partial drives (piece_min_m, piece_max_m)");
  }
  if (vehicle_yaw_bias_sigma_rad > 0.0 && vehicles == 0) {
    return absl::InvalidArgumentError("vehicle_yaw_bias_sigma_rad: needs a fleet (vehicles > 0)");
  }
  if (std::abs(origin.lat_deg) > 85.0 || std::abs(origin.lon_deg) > 180.0) {
    return absl::InvalidArgumentError("origin: latitude must lie in [-85, 85] and longitude in [-180, 180]");
  }
  return absl::OkStatus();
}

Scenario::Scenario(const ScenarioOptions& options) : options_(options), frame_(options.origin) {}

absl::StatusOr<Scenario> Scenario::Create(const ScenarioOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  Scenario sc(options);
  const double dt = 1.0 / options.odometry_rate_hz;
  const double wheelbase = options.calibration.wheelbase_m;
  const int steps = static_cast<int>(std::ceil(options.duration_s * options.odometry_rate_hz)) + 1;
  // The route starts heading north-east; inputs are sampled at the odometry rate and held.
  Pose2 pose(0.0, 0.0, M_PI / 4);
  std::vector<double> arc(steps, 0.0);
  for (int j = 0; j < steps; ++j) {
    const double t = j * dt;
    const double v = SpeedAt(t);
    const double steering = std::asin(std::clamp(CurvatureAt(t, options.repeat_route) * wheelbase, -0.9, 0.9));
    sc.true_poses_.push_back(pose);
    sc.true_inputs_.push_back({t, v, steering});
    if (j > 0) arc[j] = arc[j - 1] + sc.true_inputs_[j - 1].speed_mps * dt;
    pose = BicycleStep(pose, v, steering, dt, wheelbase);
  }
  sc.route_length_m_ = arc.back();
  sc.arc_m_ = arc;
  if (options.alternate_directions) {
    // Input j took pose j to pose j + 1; backwards, the segment is driven from its end at the same
    // speed with the opposite curvature.
    Pose2 back = sc.true_poses_.back();
    back.z() += M_PI;
    for (int k = 0; k < steps; ++k) {
      const OdometrySample& forward = sc.true_inputs_[std::max(0, steps - 2 - k)];
      sc.backward_poses_.push_back(back);
      sc.backward_inputs_.push_back({k * dt, forward.speed_mps, -forward.steering_rad});
      back = BicycleStep(back, forward.speed_mps, -forward.steering_rad, dt, wheelbase);
    }
  }

  for (int k = 0; k < options.landmarks; ++k) {
    const LandmarkPlacement place = k < static_cast<int>(std::size(kFixedLandmarks)) ? kFixedLandmarks[k]
                                                                                     : RandomPlacement(k);
    const double s = place.arc_fraction * sc.route_length_m_;
    const int j = static_cast<int>(std::lower_bound(arc.begin(), arc.end(), s) - arc.begin());
    const Pose2& p = sc.true_poses_[std::min(j, steps - 1)];
    TruthLandmark lm;
    lm.id = k + 1;
    lm.position_m = p.head<2>() + place.lateral_m * Eigen::Vector2d(-std::sin(p.z()), std::cos(p.z()));
    lm.position = sc.frame_.ToGeo(lm.position_m);
    sc.landmarks_.push_back(lm);
  }
  return sc;
}

Pose2 Scenario::TruePoseAt(double t) const {
  return PoseAlongInputs(true_poses_, true_inputs_, 1.0 / options_.odometry_rate_hz, options_.calibration.wheelbase_m,
                         t);
}

Pose2 Scenario::TruePoseAt(int index, double t) const {
  if (!Backwards(index)) return TruePoseAt(t);
  return PoseAlongInputs(backward_poses_, backward_inputs_, 1.0 / options_.odometry_rate_hz,
                         options_.calibration.wheelbase_m, t);
}

double Scenario::VehicleYawBiasRad(int vehicle) const {
  if (options_.vehicles == 0 || options_.vehicle_yaw_bias_sigma_rad == 0.0) return 0.0;
  std::mt19937_64 rng(SplitMix64(SplitMix64(options_.seed ^ 0x56454849434c45ull) ^ static_cast<uint64_t>(vehicle)));
  return options_.vehicle_yaw_bias_sigma_rad * std::normal_distribution<double>(0.0, 1.0)(rng);
}

double Scenario::CameraYawErrorRad(int index) const {
  const bool common = options_.noise == NoiseConfig::kYawBias || options_.noise == NoiseConfig::kGnssAr1YawBias;
  return (common ? options_.camera_yaw_bias_rad : 0.0) + VehicleYawBiasRad(VehicleOf(index));
}

Passage Scenario::MakePassage(int index) const {
  const ScenarioOptions& o = options_;
  NoiseSource noise(SplitMix64(SplitMix64(o.seed) ^ static_cast<uint64_t>(index)));

  Passage p;
  p.vehicle_id = o.vehicles > 0 ? absl::StrCat("sim-v", VehicleOf(index)) : absl::StrCat("sim-", index % 1000);
  p.passage_id = absl::StrCat("p", index, "-s", o.seed, "-n", o.landmarks, "-", NoiseConfigName(o.noise));
  p.start_time_unix_ms = 1767225600000LL + static_cast<int64_t>(index) * 200000;
  p.calibration = o.calibration;
  p.noise = o.noise_model;
  const NoiseModel drawn = DrawnNoise(o.noise_model, o.undeclared_noise);
  p.odometry = SimulateOdometry(Backwards(index) ? backward_inputs_ : true_inputs_, o.duration_s, drawn, &noise);

  GnssSimulation gnss;
  gnss.rate_hz = o.gnss_rate_hz;
  gnss.sigma_m = o.gnss_sigma_m;
  gnss.undeclared_scale = o.undeclared_noise.gnss;
  gnss.ar1 = o.noise == NoiseConfig::kGnssAr1 || o.noise == NoiseConfig::kGnssAr1YawBias;
  gnss.ar1_alpha = o.gnss_ar1_alpha;
  p.noise.gnss_correlation_time_s = gnss.CorrelationTimeS();  // the passage declares its GNSS process
  p.gnss = SimulateGnss([this, index](double t) { return TruePoseAt(index, t); }, o.duration_s, frame_, o.calibration,
                        gnss, &noise);

  Calibration true_camera = o.calibration;
  true_camera.camera_yaw_rad += CameraYawErrorRad(index);
  const int frames = static_cast<int>(std::floor(o.duration_s * o.camera_rate_hz + 1e-9)) + 1;
  for (int k = 0; k < frames; ++k) {
    const double t = k / o.camera_rate_hz;
    const Pose2 pose = TruePoseAt(index, t);
    for (const TruthLandmark& lm : landmarks_) {
      double u_true = 0.0, u = 0.0;
      if (!TruePixel(pose, lm.position_m, true_camera, o.min_detection_range_m, o.max_detection_range_m, &u_true)) {
        continue;
      }
      if (DetectedPixel(u_true, true_camera, drawn.pixel_sigma_px, &noise, &u)) {
        p.detections.push_back({t, lm.id, u});
      }
    }
  }
  if (o.piece_max_m > 0.0) {  // drawn apart from the noise: a piece keeps the whole passage's values
    const auto [first, last] = PieceOf(index);
    p = PassageBetween(std::move(p), first, last);
    absl::StrAppend(&p.passage_id, "-piece", o.piece_min_m, "-", o.piece_max_m);
  }
  return p;
}

std::pair<double, double> Scenario::PieceOf(int index) const {
  const ScenarioOptions& o = options_;
  if (o.piece_max_m <= 0.0) return {0.0, o.duration_s};
  std::mt19937_64 rng(SplitMix64(SplitMix64(o.seed ^ 0x5049454345ull) ^ static_cast<uint64_t>(index)));
  const double length = std::min(route_length_m_, std::uniform_real_distribution<double>(o.piece_min_m, o.piece_max_m)(rng));
  const double start = std::uniform_real_distribution<double>(0.0, route_length_m_ - length)(rng);
  const double dt = 1.0 / o.odometry_rate_hz;
  const auto time_at = [&](double s) {
    return dt * static_cast<double>(std::lower_bound(arc_m_.begin(), arc_m_.end(), s) - arc_m_.begin());
  };
  return {time_at(start), std::min(o.duration_s, time_at(start + length))};
}

ScenarioOptions LocalizationRouteOptions(int landmarks) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.duration_s = 340.0;
  options.repeat_route = true;
  return options;
}

Passage PassageBetween(Passage passage, double first_s, double last_s) {
  const auto outside = [first_s, last_s](const auto& m) { return m.t_s < first_s || m.t_s > last_s; };
  passage.odometry.erase(std::remove_if(passage.odometry.begin(), passage.odometry.end(), outside),
                         passage.odometry.end());
  passage.gnss.erase(std::remove_if(passage.gnss.begin(), passage.gnss.end(), outside), passage.gnss.end());
  passage.detections.erase(std::remove_if(passage.detections.begin(), passage.detections.end(), outside),
                           passage.detections.end());
  return passage;
}

}  // namespace crowdmap
