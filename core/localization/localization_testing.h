#ifndef CROWDMAP_CORE_LOCALIZATION_LOCALIZATION_TESTING_H_
#define CROWDMAP_CORE_LOCALIZATION_LOCALIZATION_TESTING_H_

// Helpers shared by the localisation tests and benchmarks: noise-free passages, simulated maps with
// a known covariance, pose errors, and a passage replayed as a vehicle's inputs in time order.

#include <algorithm>
#include <cmath>
#include <functional>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "core/estimation/factors.h"
#include "core/localization/passage_localizer.h"
#include "core/model/camera_model.h"
#include "core/sim/scenario.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace testing_localization {

// The passage's measurements without noise: true encoder inputs, GNSS fixes at the true antenna,
// true pixels. The declared encoder noise is made small too: the preintegration lengthens each step
// by exp(var / 2) to be unbiased under heading noise, which is a bias when there is none.
// `unprojected`, when given, counts the detections whose landmark does not project into the image
// (none should: the caller checks).
inline Passage NoiseFree(const Scenario& scenario, Passage passage, int* unprojected = nullptr) {
  const ScenarioOptions& o = scenario.options();
  passage.noise.speed_sigma_mps = 1e-4;
  passage.noise.steering_sigma_rad = 1e-6;
  passage.odometry.clear();
  for (const OdometrySample& s : scenario.true_inputs()) {
    if (s.t_s <= o.duration_s + 1e-9) passage.odometry.push_back(s);
  }
  for (GnssFix& fix : passage.gnss) {
    const Pose2 pose = scenario.TruePoseAt(fix.t_s);
    const Eigen::Vector2d antenna = pose.head<2>() + Eigen::Rotation2Dd(pose.z()) * o.calibration.gnss_lever_arm_m;
    const LatLon p = scenario.frame().ToGeo(antenna);
    fix.lat_deg = p.lat_deg;
    fix.lon_deg = p.lon_deg;
  }
  for (Detection& d : passage.detections) {
    const Pose2 pose = scenario.TruePoseAt(d.t_s);
    const bool projected =
        ProjectLandmark(pose.data(), scenario.landmarks()[d.landmark_id - 1].position_m.data(), o.calibration, &d.u_px);
    if (!projected && unprojected != nullptr) ++*unprojected;
  }
  return passage;
}

// A map of the scenario's landmarks with covariance cov = common^2 (1 1^T (x) I) + own^2 I (every
// landmark shares one offset), its estimate drawn from that covariance (seeded), or the truth.
inline LocalizationMap MakeMap(const Scenario& scenario, double common_sigma_m, double own_sigma_m, uint64_t seed,
                               bool exact) {
  NoiseSource noise(SplitMix64(seed));
  const Eigen::Vector2d common(noise.Normal() * common_sigma_m, noise.Normal() * common_sigma_m);
  LocalizationMap map;
  const int n = static_cast<int>(scenario.landmarks().size());
  map.cov_en_m2 = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  for (int k = 0; k < n; ++k) {
    const TruthLandmark& lm = scenario.landmarks()[k];
    const Eigen::Vector2d own(noise.Normal() * own_sigma_m, noise.Normal() * own_sigma_m);
    map.ids.push_back(lm.id);
    map.positions.push_back(
        scenario.frame().ToGeo(exact ? lm.position_m : Eigen::Vector2d(lm.position_m + common + own)));
    for (int l = 0; l < n; ++l) {
      map.cov_en_m2.block<2, 2>(2 * k, 2 * l) = common_sigma_m * common_sigma_m * Eigen::Matrix2d::Identity();
    }
    map.cov_en_m2.block<2, 2>(2 * k, 2 * k) += own_sigma_m * own_sigma_m * Eigen::Matrix2d::Identity();
  }
  map.version = 7;
  return map;
}

// Error (East, North, heading) of a localised pose against the truth, in the scenario's frame.
inline Eigen::Vector3d PoseError(const Scenario& scenario, const LocalizedPose& p) {
  const Pose2 truth = scenario.TruePoseAt(p.t_s);
  Eigen::Vector3d e;
  e.head<2>() = scenario.frame().ToLocal(p.position) - truth.head<2>();
  e.z() = NormalizeAngle(p.pose_m.z() - truth.z());
  return e;
}

// One input of a passage as a vehicle delivers it.
struct PassageInput {
  enum class Kind { kOdometry, kGnss, kDetections } kind;
  double t_s = 0.0;
  size_t index = 0;                 // into passage.odometry / passage.gnss
  std::vector<Detection> frame;     // kDetections: one camera frame
};

// The passage's inputs in time order (at one time: odometry, then GNSS, then the camera frame).
inline std::vector<PassageInput> PassageInputs(const Passage& passage) {
  std::vector<PassageInput> inputs;
  for (size_t i = 0; i < passage.odometry.size(); ++i) {
    inputs.push_back({PassageInput::Kind::kOdometry, passage.odometry[i].t_s, i, {}});
  }
  for (size_t i = 0; i < passage.gnss.size(); ++i) {
    inputs.push_back({PassageInput::Kind::kGnss, passage.gnss[i].t_s, i, {}});
  }
  std::vector<Detection> detections = passage.detections;
  std::stable_sort(detections.begin(), detections.end(),
                   [](const Detection& a, const Detection& b) { return a.t_s < b.t_s; });
  for (const Detection& d : detections) {
    if (!inputs.empty() && inputs.back().kind == PassageInput::Kind::kDetections &&
        std::abs(inputs.back().t_s - d.t_s) < 1e-9) {
      inputs.back().frame.push_back(d);
    } else {
      inputs.push_back({PassageInput::Kind::kDetections, d.t_s, 0, {d}});
    }
  }
  std::stable_sort(inputs.begin(), inputs.end(),
                   [](const PassageInput& a, const PassageInput& b) { return a.t_s < b.t_s; });
  return inputs;
}

// Feeds one input to a localizer (StreamingLocalizer or a class with its Add* methods).
template <typename Localizer>
auto Feed(const Passage& passage, const PassageInput& input, Localizer* localizer) {
  switch (input.kind) {
    case PassageInput::Kind::kOdometry: return localizer->AddOdometry(passage.odometry[input.index]);
    case PassageInput::Kind::kGnss: return localizer->AddGnss(passage.gnss[input.index]);
    case PassageInput::Kind::kDetections: break;
  }
  return localizer->AddDetections(input.frame);
}

}  // namespace testing_localization
}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_LOCALIZATION_TESTING_H_
