#ifndef CROWDMAP_CORE_SIM_SCENARIO_H_
#define CROWDMAP_CORE_SIM_SCENARIO_H_

#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "core/geo/local_frame.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {

// Noise injected into the simulated measurements (thesis section 5.2.3).
enum class NoiseConfig {
  kWhite,         // "white": independent Gaussian noise everywhere
  kGnssAr1,       // "gnss-ar1": GNSS error e_k = alpha e_(k-1) + beta w_k per axis
  kYawBias,       // "yaw-bias": constant camera yaw calibration error
  kGnssAr1YawBias // "ar1+yaw": both
};

absl::StatusOr<NoiseConfig> ParseNoiseConfig(std::string_view name);
const char* NoiseConfigName(NoiseConfig config);

// The thesis's reference scenario (DESIGN section 8). Defaults are the thesis values.
struct ScenarioOptions {
  int landmarks = 25;
  NoiseConfig noise = NoiseConfig::kWhite;
  uint64_t seed = 1;               // passage noise; passage i draws from (seed, i) only
  LatLon origin{48.7128, 2.1700};  // WGS84 position of the route start
  double duration_s = 165.0;
  // Beyond its 165 s the route's curvature profile starts again (a longer road-like route, e.g.
  // the thesis's 4 km localisation loop); false: the route goes straight on after it.
  bool repeat_route = false;
  double odometry_rate_hz = 25.0;
  double gnss_rate_hz = 1.0;
  double camera_rate_hz = 2.0;
  double gnss_sigma_m = 10.0;
  double gnss_ar1_alpha = 0.988;   // beta = sqrt(1 - alpha^2) keeps the marginal sigma
  double camera_yaw_bias_rad = 0.009;
  double min_detection_range_m = 5.0;
  double max_detection_range_m = 50.0;
  Calibration calibration;         // true calibration (and what the vehicle reports)
  NoiseModel noise_model;          // sigmas declared in the uploaded passage (and drawn, times undeclared_noise)
  UndeclaredNoiseScales undeclared_noise;
  // Partial drives: each passage keeps one piece of the route (its measurements within it), of a
  // length uniform in [piece_min_m, piece_max_m] (at most the route) starting uniformly along the
  // rest, drawn from (seed, index). Both 0 = the whole route.
  double piece_min_m = 0.0;
  double piece_max_m = 0.0;
  // A fleet: passage i is driven by vehicle i % vehicles (vehicle_id "sim-v<i % vehicles>"), whose
  // camera yaw is off by its own error, drawn once per vehicle from N(0, sigma^2) with (seed,
  // vehicle) (VehicleYawBiasRad), besides the noise configuration's common bias. 0 = every passage
  // its own vehicle (vehicle_id "sim-<i % 1000>"), without such an error.
  int vehicles = 0;
  double vehicle_yaw_bias_sigma_rad = 0.0;
  // Traffic both ways: odd passages drive the route backwards, from its end to its start (the same
  // road, the other lane's direction). false: every passage drives it the same way (the thesis).
  // Not with partial drives.
  bool alternate_directions = false;

  absl::Status Validate() const;
};

struct TruthLandmark {
  LandmarkId id = 0;
  Eigen::Vector2d position_m;  // in the scenario frame (East/North at options.origin)
  LatLon position;
};

// A road-like route driven by every simulated vehicle, landmarks along it, and deterministic
// noisy passages. The route is generated with the bicycle model itself (so it is exactly
// consistent with the estimator's motion model) and is the same for every seed; landmarks depend
// only on their count, and the first landmarks of a larger scenario are those of a smaller one.
class Scenario {
 public:
  static absl::StatusOr<Scenario> Create(const ScenarioOptions& options);

  const ScenarioOptions& options() const { return options_; }
  const LocalFrame& frame() const { return frame_; }
  const std::vector<TruthLandmark>& landmarks() const { return landmarks_; }
  // True rear-axle poses at the odometry rate, and the true inputs that produced them.
  const std::vector<Pose2>& true_poses() const { return true_poses_; }
  const std::vector<OdometrySample>& true_inputs() const { return true_inputs_; }
  // Route length (m).
  double route_length_m() const { return route_length_m_; }

  // The passage of vehicle `index` (0-based), as the vehicle would upload it: vehicle_id
  // "sim-<index % 1000>", passage_id "p<index>-s<seed>-n<landmarks>-<noise>". The id names the
  // scenario, so the same passage uploaded twice is a duplicate but a passage of another seed,
  // landmark count or noise configuration is not.
  Passage MakePassage(int index) const;

  // The vehicle of passage `index` (0 when options.vehicles is 0) and its own camera yaw error
  // (rad; 0 without a fleet).
  int VehicleOf(int index) const { return options_.vehicles > 0 ? index % options_.vehicles : 0; }
  double VehicleYawBiasRad(int vehicle) const;
  // How far passage `index`'s true camera yaw is off the calibration it declares (rad): the noise
  // configuration's common bias plus its vehicle's own error.
  double CameraYawErrorRad(int index) const;

  // True pose at time t (seconds since start), by the same bicycle steps as the route.
  Pose2 TruePoseAt(double t_s) const;
  // The same for passage `index`: the route backwards for odd passages with
  // options.alternate_directions.
  Pose2 TruePoseAt(int index, double t_s) const;
  bool Backwards(int index) const { return options_.alternate_directions && index % 2 == 1; }
  // The time span [first, second] (seconds since start) passage `index` keeps: its piece of the
  // route (options.piece_min_m), or the whole passage.
  std::pair<double, double> PieceOf(int index) const;

 private:
  explicit Scenario(const ScenarioOptions& options);

  ScenarioOptions options_;
  LocalFrame frame_;
  std::vector<TruthLandmark> landmarks_;
  std::vector<Pose2> true_poses_;
  std::vector<OdometrySample> true_inputs_;
  // The route driven backwards (options.alternate_directions): from the last true pose turned
  // about, the inputs in reverse order with the steering negated.
  std::vector<Pose2> backward_poses_;
  std::vector<OdometrySample> backward_inputs_;
  std::vector<double> arc_m_;  // distance driven at each true pose
  double route_length_m_ = 0.0;
};

// The thesis's localisation loop (section 5.4): the route's profile repeated over 340 s (about
// 4 km), with `landmarks` along it (500: one every 8 m).
ScenarioOptions LocalizationRouteOptions(int landmarks = 500);

// `passage` with only its measurements from `first_s` to `last_s` (seconds since its start), e.g.
// its first minutes.
Passage PassageBetween(Passage passage, double first_s, double last_s);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_SCENARIO_H_
