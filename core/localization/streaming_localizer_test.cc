#include "core/localization/streaming_localizer.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include <gtest/gtest.h>

#include "absl/strings/str_format.h"
#include "core/localization/localization_testing.h"

namespace crowdmap {
namespace {

using testing_localization::Feed;
using testing_localization::MakeMap;
using testing_localization::NoiseFree;
using testing_localization::PassageInput;
using testing_localization::PassageInputs;
using testing_localization::PoseError;

Scenario MakeScenario(int landmarks, uint64_t seed = 1) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.seed = seed;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  return *std::move(scenario);
}

// Every update of a passage replayed through a fresh localizer holding `map`.
struct Replay {
  std::vector<StreamingUpdate> updates;  // GNSS and detection updates while tracking
  int rejected = 0;
  std::vector<RejectedDetection> rejections;
};

Replay ReplayPassage(const Passage& passage, const LocalizationMap& map, const StreamingLocalizerOptions& options = {}) {
  Replay replay;
  absl::StatusOr<std::unique_ptr<StreamingLocalizer>> localizer =
      StreamingLocalizer::Create(passage.calibration, passage.noise, options);
  EXPECT_TRUE(localizer.ok()) << localizer.status();
  EXPECT_TRUE((*localizer)->AddMapLandmarks(map).ok());
  for (const PassageInput& input : PassageInputs(passage)) {
    absl::StatusOr<StreamingUpdate> update = Feed(passage, input, localizer->get());
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok()) break;
    for (const RejectedDetection& r : update->rejected) replay.rejections.push_back(r);
    if (update->tracking && input.kind != PassageInput::Kind::kOdometry) replay.updates.push_back(*update);
  }
  replay.rejected = static_cast<int>(replay.rejections.size());
  return replay;
}

TEST(StreamingLocalizer, RecoversNoiseFreePassageExactly) {
  const Scenario scenario = MakeScenario(25);
  int unprojected = 0;
  const Passage passage = NoiseFree(scenario, scenario.MakePassage(0), &unprojected);
  EXPECT_EQ(unprojected, 0);
  const LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 1, /*exact=*/true);
  const Replay replay = ReplayPassage(passage, map);
  EXPECT_EQ(replay.rejected, 0);
  ASSERT_GT(replay.updates.size(), 250u);
  double worst_m = 0.0, worst_rad = 0.0;
  int used = 0;
  for (const StreamingUpdate& u : replay.updates) {
    const Eigen::Vector3d e = PoseError(scenario, u.pose);
    worst_m = std::max(worst_m, e.head<2>().norm());
    worst_rad = std::max(worst_rad, std::abs(e.z()));
    used += u.detections_used;
  }
  EXPECT_GT(used, 150);
  // As for PassageLocalizer: the filter's frame (at the first fix) and the scenario's are tangent
  // planes 0.5 m apart, a few micrometres over the route.
  EXPECT_LT(worst_m, 1e-5);
  EXPECT_LT(worst_rad, 1e-6);
}

// Pose NEES over independent passages and maps (white noise, a consistent correlated map), the
// continuity of the trajectory, and the error beside the whole-passage localizer's.
TEST(StreamingLocalizer, PoseCovarianceIsConsistentOverManyPassages) {
  const Scenario scenario = MakeScenario(25);
  constexpr int kRuns = 40;
  double nees_sum = 0.0, error_sum = 0.0, batch_error_sum = 0.0, worst_jump = 0.0;
  int count = 0, batch_count = 0, jumps_over_3 = 0, rejected = 0;
  for (int run = 0; run < kRuns; ++run) {
    const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 100 + run, /*exact=*/false);
    const Passage passage = scenario.MakePassage(run);
    const Replay replay = ReplayPassage(passage, map);
    rejected += replay.rejected;
    for (const StreamingUpdate& u : replay.updates) {
      const Eigen::Vector3d e = PoseError(scenario, u.pose);
      nees_sum += e.dot(u.pose.cov.ldlt().solve(e));
      error_sum += e.head<2>().norm();
      ++count;
      worst_jump = std::max(worst_jump, u.correction_sigmas);
      jumps_over_3 += u.correction_sigmas > 3.0;
    }
    absl::StatusOr<PassageLocalization> batch = LocalizePassage(passage, map);
    ASSERT_TRUE(batch.ok()) << batch.status();
    for (const LocalizedPose& p : batch->poses) {
      if (p.t_s < replay.updates.front().pose.t_s - 1e-9) continue;  // the same times as the filter's
      batch_error_sum += PoseError(scenario, p).head<2>().norm();
      ++batch_count;
    }
  }
  const double nees_per_dof = nees_sum / (3.0 * count);
  const std::string figures = absl::StrFormat(
      "updates=%d pose_nees_per_dof=%.3f mean_error_m=%.3f passage_localizer_mean_error_m=%.3f "
      "worst_jump_sigmas=%.2f jumps_over_3_sigma=%d rejected=%d",
      count, nees_per_dof, error_sum / count, batch_error_sum / batch_count, worst_jump, jumps_over_3, rejected);
  std::cout << figures << "\n";
  RecordProperty("figures", figures);
  EXPECT_GT(nees_per_dof, 0.8) << figures;
  EXPECT_LT(nees_per_dof, 1.25) << figures;
  // Continuity: an update's correction of the predicted pose, per component, over its predicted
  // sigma. A consistent filter's correction has covariance P- - P+ <= P-, so at most 0.27% of
  // the components exceed 3 predicted sigmas (the rate when an update removes all uncertainty).
  EXPECT_LT(jumps_over_3, 0.0027 * count) << figures;
  EXPECT_LT(worst_jump, 5.0) << figures;
}

// A camera turned by the yaw-bias scenario's 0.009 rad: with the offset a state of the filter (1
// degree prior) the pose covariance stays honest and the offset is found; taken as calibrated, the
// turned bearings pull the poses further than their covariance says.
TEST(StreamingLocalizer, EstimatesTheCameraYawOffset) {
  ScenarioOptions options;
  options.landmarks = 50;
  options.noise = NoiseConfig::kYawBias;
  const Scenario scenario = *Scenario::Create(options);
  StreamingLocalizerOptions estimated;
  estimated.camera_yaw_sigma_rad = 0.0174533;
  constexpr int kRuns = 24;
  double nees[2] = {0.0, 0.0}, yaw_nees = 0.0;
  int count[2] = {0, 0};
  for (int run = 0; run < kRuns; ++run) {
    const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 400 + run, /*exact=*/false);
    const Passage passage = scenario.MakePassage(run);
    for (int k = 0; k < 2; ++k) {
      const Replay replay = ReplayPassage(passage, map, k == 0 ? StreamingLocalizerOptions() : estimated);
      ASSERT_FALSE(replay.updates.empty());
      for (const StreamingUpdate& u : replay.updates) {
        const Eigen::Vector3d e = PoseError(scenario, u.pose);
        nees[k] += e.dot(u.pose.cov.ldlt().solve(e));
        ++count[k];
      }
      const StreamingUpdate& last = replay.updates.back();
      if (k == 0) {
        EXPECT_EQ(last.camera_yaw_sigma_rad, 0.0);
        continue;
      }
      ASSERT_GT(last.camera_yaw_sigma_rad, 0.0);
      EXPECT_LT(last.camera_yaw_sigma_rad, 0.5 * estimated.camera_yaw_sigma_rad) << "the passage informs it";
      const double error = last.camera_yaw_offset_rad - scenario.CameraYawErrorRad(run);
      yaw_nees += error * error / (last.camera_yaw_sigma_rad * last.camera_yaw_sigma_rad);
    }
  }
  const double fixed = nees[0] / (3.0 * count[0]), free = nees[1] / (3.0 * count[1]);
  const std::string figures = absl::StrFormat("pose_nees_per_dof calibration_fixed=%.3f yaw_estimated=%.3f yaw_nees=%.2f",
                                              fixed, free, yaw_nees / kRuns);
  std::cout << figures << "\n";
  RecordProperty("figures", figures);
  EXPECT_GT(free, 0.8) << figures;
  EXPECT_LT(free, 1.25) << figures;
  EXPECT_GT(fixed, free + 0.1) << figures;
  EXPECT_LT(yaw_nees / kRuns, 3.0) << figures;
}

TEST(StreamingLocalizer, RejectsMislabelledDetection) {
  const Scenario scenario = MakeScenario(150);
  const Passage clean = scenario.MakePassage(3);
  const LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 5, /*exact=*/false);
  Passage mislabelled = clean;
  // One detection of landmark 60 (after the start) reported as landmark 20, which stands elsewhere.
  Detection* wrong = nullptr;
  for (Detection& d : mislabelled.detections) {
    if (d.landmark_id == 60 && wrong == nullptr) wrong = &d;
  }
  ASSERT_NE(wrong, nullptr);
  ASSERT_GT(wrong->t_s, 20.0);
  wrong->landmark_id = 20;
  // The same passage without that detection at all.
  Passage dropped = mislabelled;
  dropped.detections.erase(dropped.detections.begin() + (wrong - mislabelled.detections.data()));
  const Replay a = ReplayPassage(dropped, map);
  const Replay b = ReplayPassage(mislabelled, map);
  bool found = false;
  for (const RejectedDetection& r : b.rejections) {
    found |= r.landmark_id == 20 && std::abs(r.t_s - wrong->t_s) < 1e-6 && r.u_px == wrong->u_px;
  }
  EXPECT_TRUE(found);
  EXPECT_EQ(b.rejected, a.rejected + 1);
  ASSERT_EQ(a.updates.size(), b.updates.size());
  double worst = 0.0;
  for (size_t k = 0; k < a.updates.size(); ++k) {
    worst = std::max(worst, (a.updates[k].pose.pose_m - b.updates[k].pose.pose_m).norm());
  }
  // Rejected, the detection changes nothing.
  EXPECT_LT(worst, 1e-12);
}

TEST(StreamingLocalizer, RejectsDetectionsOfALandmarkTheMapPutsElsewhere) {
  const Scenario scenario = MakeScenario(150);
  LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 6, /*exact=*/false);
  const Passage passage = scenario.MakePassage(4);
  // Landmark 60's map entry is 6 m (twenty map sigmas) across the line of sight from where it
  // stands (along it, a shift barely moves the pixel).
  double first_seen_s = 0.0;
  for (const Detection& d : passage.detections) {
    if (d.landmark_id == 60 && first_seen_s == 0.0) first_seen_s = d.t_s;
  }
  const Eigen::Vector2d line_of_sight =
      (scenario.landmarks()[59].position_m - scenario.TruePoseAt(first_seen_s).head<2>()).normalized();
  map.positions[59] = scenario.frame().ToGeo(scenario.frame().ToLocal(map.positions[59]) +
                                             6.0 * Eigen::Vector2d(-line_of_sight.y(), line_of_sight.x()));
  const Replay replay = ReplayPassage(passage, map);
  int seen = 0, rejected = 0;
  for (const Detection& d : passage.detections) seen += d.landmark_id == 60;
  for (const RejectedDetection& r : replay.rejections) rejected += r.landmark_id == 60;
  ASSERT_GT(seen, 3);
  EXPECT_EQ(rejected, seen);
  EXPECT_LE(replay.rejected, seen + 3);
}

// Landmarks the passage never sees, held or marginalised out, change nothing: removing rows and
// columns of a Gaussian in covariance form is its exact marginal.
TEST(StreamingLocalizer, UnseenLandmarksAddedOrRemovedChangeNothing) {
  const Scenario scenario = MakeScenario(25);
  const Passage passage = scenario.MakePassage(2);
  const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 9, /*exact=*/false);
  LocalizationMap far;
  far.ids = {1001, 1002};
  far.positions = {scenario.frame().ToGeo({5000.0, 0.0}), scenario.frame().ToGeo({5000.0, 10.0})};
  far.cov_en_m2 = Eigen::MatrixXd::Identity(4, 4) + 0.5 * Eigen::MatrixXd::Ones(4, 4);
  auto run = [&](bool add_far, bool remove_far) {
    std::unique_ptr<StreamingLocalizer> localizer = *StreamingLocalizer::Create(passage.calibration, passage.noise);
    EXPECT_TRUE(localizer->AddMapLandmarks(map).ok());
    std::vector<StreamingUpdate> out;
    for (const PassageInput& input : PassageInputs(passage)) {
      absl::StatusOr<StreamingUpdate> u = Feed(passage, input, localizer.get());
      EXPECT_TRUE(u.ok()) << u.status();
      if (add_far && localizer->tracking() && !localizer->HoldsLandmark(1001) && input.t_s > 60.0) {
        EXPECT_TRUE(localizer->AddMapLandmarks(far).ok());
        EXPECT_EQ(localizer->landmarks_held(), 27);
      }
      if (remove_far && localizer->HoldsLandmark(1001) && input.t_s > 100.0) {
        localizer->RemoveMapLandmarks({1001, 1002, 77777});
        EXPECT_EQ(localizer->landmarks_held(), 25);
      }
      if (u->tracking) out.push_back(*u);
    }
    return out;
  };
  const std::vector<StreamingUpdate> plain = run(false, false), added = run(true, false), removed = run(true, true);
  ASSERT_EQ(plain.size(), added.size());
  ASSERT_EQ(plain.size(), removed.size());
  for (size_t k = 0; k < plain.size(); ++k) {
    EXPECT_LT((plain[k].pose.pose_m - added[k].pose.pose_m).norm(), 1e-9);
    EXPECT_LT((plain[k].pose.cov - removed[k].pose.cov).norm(), 1e-12);
  }
}

TEST(StreamingLocalizer, RefusesInputsOutOfTimeOrder) {
  const Scenario scenario = MakeScenario(25);
  const Passage passage = scenario.MakePassage(0);
  std::unique_ptr<StreamingLocalizer> localizer = *StreamingLocalizer::Create(passage.calibration, passage.noise);
  ASSERT_TRUE(localizer->AddMapLandmarks(MakeMap(scenario, 0.0, 0.3, 1, false)).ok());
  for (const PassageInput& input : PassageInputs(passage)) {
    if (input.t_s > 30.0) break;
    ASSERT_TRUE(Feed(passage, input, localizer.get()).ok());
  }
  ASSERT_TRUE(localizer->tracking());
  EXPECT_EQ(localizer->AddGnss(passage.gnss[5]).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(localizer->AddOdometry(passage.odometry[10]).status().code(), absl::StatusCode::kInvalidArgument);
  Detection a{31.0, 1, 900.0}, b{31.5, 2, 900.0};
  EXPECT_EQ(localizer->AddDetections({a, b}).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(StreamingLocalizerOptions, RejectsInvalidValues) {
  StreamingLocalizerOptions options;
  options.start_min_fixes = 1;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.detection_gate_sigmas = 0.0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.max_iterations = 0;
  EXPECT_FALSE(StreamingLocalizer::Create(Calibration{}, NoiseModel{}, options).ok());
  options = {};
  options.camera_yaw_sigma_rad = -0.01;
  EXPECT_FALSE(options.Validate().ok());
}

}  // namespace
}  // namespace crowdmap
