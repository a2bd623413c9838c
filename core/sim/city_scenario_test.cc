#include "core/sim/city_scenario.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "core/model/motion_model.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

CityScenario Make(const CityScenarioOptions& options) {
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(options);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  return *std::move(scenario);
}

CityScenarioOptions Small() {
  CityScenarioOptions options;
  options.blocks_x = 4;
  options.blocks_y = 3;
  options.route_length_m = 600.0;
  options.vehicles = 3;
  return options;
}

double NearestDistance(const std::vector<double>& streets, double v) {
  double best = INFINITY;
  for (double s : streets) best = std::min(best, std::abs(v - s));
  return best;
}

bool InsideAnyBuilding(const CityLayout& layout, const Eigen::Vector2d& p) {
  for (const Rect2& b : layout.buildings()) {
    if ((p.array() > b.min_m.array()).all() && (p.array() < b.max_m.array()).all()) return true;
  }
  return false;
}

bool SamePassage(const Passage& a, const Passage& b) {
  if (a.vehicle_id != b.vehicle_id || a.passage_id != b.passage_id || a.odometry.size() != b.odometry.size() ||
      a.gnss.size() != b.gnss.size() || a.detections.size() != b.detections.size()) {
    return false;
  }
  for (size_t i = 0; i < a.odometry.size(); ++i) {
    if (a.odometry[i].speed_mps != b.odometry[i].speed_mps || a.odometry[i].steering_rad != b.odometry[i].steering_rad) {
      return false;
    }
  }
  for (size_t i = 0; i < a.gnss.size(); ++i) {
    if (a.gnss[i].lat_deg != b.gnss[i].lat_deg || a.gnss[i].lon_deg != b.gnss[i].lon_deg) return false;
  }
  for (size_t i = 0; i < a.detections.size(); ++i) {
    if (a.detections[i].landmark_id != b.detections[i].landmark_id || a.detections[i].u_px != b.detections[i].u_px) {
      return false;
    }
  }
  return true;
}

TEST(CityScenario, SameOptionsGiveTheSameLayoutAndPassages) {
  const CityScenario a = Make(Small()), b = Make(Small());
  ASSERT_EQ(a.landmark_count(), b.landmark_count());
  for (size_t k = 0; k < a.landmark_count(); ++k) {
    EXPECT_EQ(a.landmarks()[k].id, static_cast<LandmarkId>(k + 1));
    EXPECT_EQ(a.landmarks()[k].position_m, b.landmarks()[k].position_m);
  }
  EXPECT_TRUE(SamePassage(a.MakePassage(4), b.MakePassage(4)));
  EXPECT_FALSE(SamePassage(a.MakePassage(4), a.MakePassage(5)));
  EXPECT_EQ(a.MakePassage(4).vehicle_id, "city-v1");

  CityScenarioOptions other_seed = Small();
  other_seed.seed = 2;
  const CityScenario c = Make(other_seed);
  EXPECT_EQ(c.landmarks().back().position_m, a.landmarks().back().position_m);  // the layout stays
  EXPECT_FALSE(SamePassage(a.MakePassage(4), c.MakePassage(4)));

  CityScenarioOptions other_layout = Small();
  other_layout.layout_seed = 2;
  EXPECT_NE(Make(other_layout).landmarks().front().position_m, a.landmarks().front().position_m);
}

TEST(CityScenario, LandmarksAreSpacedWithinBoundsBesideTheRoadAndOutsideBuildings) {
  const CityScenarioOptions options = Small();
  const CityScenario city = Make(options);
  const CityLayout& layout = city.layout();
  const double half = layout.road_half_width_m();
  ASSERT_GT(city.landmark_count(), 100u);
  int spacings_checked = 0;
  for (size_t k = 0; k < city.landmark_count(); ++k) {
    const Eigen::Vector2d p = city.landmarks()[k].position_m;
    const double dx = NearestDistance(layout.street_x_m(), p.x()), dy = NearestDistance(layout.street_y_m(), p.y());
    // Off every carriageway by at least the smaller of the kerb offset and the corner clearance...
    EXPECT_GE(std::min(dx, dy), half + std::min(options.landmark_kerb_offset_min_m, options.corner_clearance_m) - 1e-9);
    // ...and beside one street at the kerb offset.
    const double beside = std::min(dx, dy);
    EXPECT_GE(beside, half + options.landmark_kerb_offset_min_m - 1e-9) << "landmark " << k + 1;
    EXPECT_LE(beside, half + options.landmark_kerb_offset_max_m + 1e-9) << "landmark " << k + 1;
    EXPECT_FALSE(InsideAnyBuilding(layout, p)) << "landmark " << k + 1;
    if (k == 0) continue;
    // Consecutive ids on the same side of the same stretch of street: spacing within bounds.
    const Eigen::Vector2d q = city.landmarks()[k - 1].position_m;
    const bool east_west = dy < dx;
    const double across_p = east_west ? p.y() : p.x(), across_q = east_west ? q.y() : q.x();
    const double along_p = east_west ? p.x() : p.y(), along_q = east_west ? q.x() : q.y();
    const std::vector<double>& cross = east_west ? layout.street_x_m() : layout.street_y_m();
    const auto block = [&](double v) { return std::upper_bound(cross.begin(), cross.end(), v) - cross.begin(); };
    if (std::abs(across_p - across_q) < 2.0 * (options.landmark_kerb_offset_max_m - options.landmark_kerb_offset_min_m) &&
        (east_west ? NearestDistance(layout.street_y_m(), q.y()) < NearestDistance(layout.street_x_m(), q.x())
                   : NearestDistance(layout.street_x_m(), q.x()) < NearestDistance(layout.street_y_m(), q.y())) &&
        block(along_p) == block(along_q) && along_p > along_q) {
      EXPECT_GE(along_p - along_q, options.spacing_min_m - 1e-9);
      EXPECT_LE(along_p - along_q, options.spacing_max_m + 1e-9);
      ++spacings_checked;
    }
  }
  EXPECT_GT(spacings_checked, static_cast<int>(city.landmark_count()) / 2);
}

TEST(CityScenario, PassagesAreValidAndSeeLandmarks) {
  const CityScenario city = Make(Small());
  for (int i = 0; i < 6; ++i) {
    const Passage p = city.MakePassage(i);
    EXPECT_TRUE(ValidatePassage(p).ok()) << ValidatePassage(p);
    EXPECT_GT(p.detections.size(), 50u) << "passage " << i;
  }
}

TEST(CityScenario, RouteHasTheRequestedLengthAndStaysOnTheStreets) {
  CityScenarioOptions options = Small();
  const CityScenario city = Make(options);
  const CityLayout& layout = city.layout();
  int turns = 0;
  for (int i = 0; i < 8; ++i) {
    const CityDrive drive = city.TrueDrive(i);
    turns += drive.turns;
    EXPECT_GE(drive.length_m, options.route_length_m);
    EXPECT_LE(drive.length_m, options.route_length_m + options.speed_max_mps * drive.dt_s + 1e-9);
    double chord_m = 0.0;
    for (size_t j = 0; j < drive.poses.size(); ++j) {
      const Eigen::Vector2d p = drive.poses[j].head<2>();
      if (j > 0) chord_m += (p - drive.poses[j - 1].head<2>()).norm();
      const double dx = NearestDistance(layout.street_x_m(), p.x()), dy = NearestDistance(layout.street_y_m(), p.y());
      ASSERT_LE(std::min(dx, dy), layout.road_half_width_m()) << "passage " << i << " leaves the road at t=" << j * drive.dt_s;
      const OdometrySample& in = drive.inputs[j];
      EXPECT_LE(std::abs(in.steering_rad), options.max_steering_rad + 1e-12);
      // Smooth curvature: the lane's arcs are followed without steering jumps.
      if (j > 0) {
        EXPECT_LT(std::abs(in.steering_rad - drive.inputs[j - 1].steering_rad) / drive.dt_s, 0.5);
      }
      EXPECT_GE(in.speed_mps, std::min(options.turn_speed_mps, options.speed_min_mps) - 1e-9);
      EXPECT_LE(in.speed_mps, options.speed_max_mps + 1e-9);
    }
    EXPECT_NEAR(chord_m, drive.length_m, 1e-3 * drive.length_m);
  }
  EXPECT_GT(turns, 4);  // eight 600 m drives on 150 m blocks do turn
}

// The small city, its vehicles stopping 10 to 20 s before every intersection.
CityScenarioOptions StoppingEverywhere() {
  CityScenarioOptions options = Small();
  options.stop_probability = 1.0;
  options.stop_min_s = 10.0;
  options.stop_max_s = 20.0;
  return options;
}

TEST(CityScenario, VehiclesStopBeforeIntersectionsAndDriveTheSameRoute) {
  const CityScenario plain = Make(Small());
  const CityScenarioOptions options = StoppingEverywhere();
  const CityScenario stopping = Make(options);
  int stops = 0;
  for (int i = 0; i < 6; ++i) {
    const CityDrive a = plain.TrueDrive(i), b = stopping.TrueDrive(i);
    EXPECT_EQ(a.stops, 0);
    EXPECT_EQ(a.lane_m, b.lane_m) << "the same route, " << i;
    EXPECT_GE(b.length_m, options.route_length_m);
    stops += b.stops;
    // Every stop is a run of zero speed of 10 to 20 s, reached by braking at about 2 m/s^2, the
    // last step from a crawl.
    int still = 0, runs = 0;
    for (size_t j = 0; j < b.inputs.size(); ++j) {
      const double v = b.inputs[j].speed_mps;
      if (j > 0 && v > 0.0) {
        EXPECT_GE(v - b.inputs[j - 1].speed_mps, -2.1 * b.dt_s) << i << " at " << b.inputs[j].t_s;
      } else if (j > 0) {
        EXPECT_LE(b.inputs[j - 1].speed_mps, 0.5) << i << " at " << b.inputs[j].t_s;
      }
      if (v == 0.0) {
        ++still;
      } else if (still > 0) {
        EXPECT_GE(still * b.dt_s, 10.0 - 1e-6);
        EXPECT_LE(still * b.dt_s, 20.0 + 2.0 * b.dt_s);
        ++runs;
        still = 0;
      }
    }
    EXPECT_EQ(runs, b.stops) << i;
    EXPECT_NEAR(b.duration_s - a.duration_s, 15.0 * b.stops, 5.0 * b.stops + 10.0) << i;
  }
  EXPECT_GT(stops, 6) << "600 m drives on 150 m blocks cross intersections";
}

// A camera standing still sees the same image: its detector's error on a landmark is the same in
// every frame of a stop, and drawn anew once the vehicle moves.
TEST(CityScenario, AStoppedCameraMakesTheSameDetectionErrorInEveryFrame) {
  const CityScenario stopping = Make(StoppingEverywhere());
  int repeated = 0, moving_pairs = 0, moving_equal = 0;
  for (int i = 0; i < 6; ++i) {
    const auto [passage, drive] = stopping.MakePassageWithTruth(i);
    std::map<LandmarkId, const Detection*> previous;
    for (const Detection& d : passage.detections) {
      const Detection* before = previous[d.landmark_id];
      previous[d.landmark_id] = &d;
      if (before == nullptr) continue;
      const bool still = (drive.PoseAt(before->t_s) - drive.PoseAt(d.t_s)).norm() < 1e-9;
      if (still) {
        EXPECT_EQ(d.u_px, before->u_px) << i << " landmark " << d.landmark_id << " at " << d.t_s;
        ++repeated;
      } else {
        ++moving_pairs;
        moving_equal += d.u_px == before->u_px;
      }
    }
  }
  EXPECT_GT(repeated, 100) << "landmarks in view during the stops";
  EXPECT_GT(moving_pairs, 1000);
  EXPECT_EQ(moving_equal, 0);
}

TEST(CityScenario, AGnssOutageRemovesTheFixesOfOneIntervalInsideThePassage) {
  CityScenarioOptions options = Small();
  const CityScenario plain = Make(options);
  options.gnss_outage_probability = 1.0;
  options.gnss_outage_min_s = 15.0;
  options.gnss_outage_max_s = 25.0;
  const CityScenario outage = Make(options);
  for (int i = 0; i < 6; ++i) {
    const Passage a = plain.MakePassage(i), b = outage.MakePassage(i);
    ASSERT_TRUE(ValidatePassage(b).ok()) << ValidatePassage(b);
    EXPECT_EQ(a.odometry.size(), b.odometry.size());
    EXPECT_EQ(a.detections.size(), b.detections.size());
    double longest_gap_s = 0.0;
    for (size_t j = 1; j < b.gnss.size(); ++j) longest_gap_s = std::max(longest_gap_s, b.gnss[j].t_s - b.gnss[j - 1].t_s);
    EXPECT_GE(longest_gap_s, 15.0) << i;
    EXPECT_LE(longest_gap_s, 25.0 + 1.0 + 1e-9) << i;
    EXPECT_LE(b.gnss.front().t_s, 1e-9);
    EXPECT_NEAR(b.gnss.back().t_s, a.gnss.back().t_s, 1e-9);
    EXPECT_NEAR(a.gnss.size() - b.gnss.size(), longest_gap_s - 1.0, 1.0 + 1e-9) << i;
  }
}

TEST(CityScenario, EachVehiclesEncodersReportTheSpeedTimesItsOwnScale) {
  CityScenarioOptions options = Small();
  options.noise_model.speed_sigma_mps = 0.0;
  const CityScenario exact = Make(options);
  options.vehicle_speed_scale_sigma = 0.02;
  const CityScenario scaled = Make(options);
  std::vector<double> scales;
  for (int i = 0; i < options.vehicles; ++i) {
    const Passage a = exact.MakePassage(i), b = scaled.MakePassage(i);
    ASSERT_EQ(a.odometry.size(), b.odometry.size());
    const double scale = scaled.Vehicle(i).speed_scale;
    EXPECT_EQ(exact.Vehicle(i).speed_scale, 1.0);
    for (size_t j = 0; j < a.odometry.size(); ++j) {
      EXPECT_NEAR(b.odometry[j].speed_mps, scale * a.odometry[j].speed_mps, 1e-12);
      EXPECT_EQ(b.odometry[j].steering_rad, a.odometry[j].steering_rad);
    }
    EXPECT_EQ(a.gnss.size(), b.gnss.size()) << "the truth and the other sensors stay";
    scales.push_back(scale);
  }
  EXPECT_NE(scales[0], scales[1]);
  for (double scale : scales) EXPECT_NEAR(scale, 1.0, 0.1);
}

// A fleet of several car models: each vehicle declares its own calibration, within the spread,
// and its passages are simulated with it: driven with its wheelbase, fixed at its antenna, seen
// through its camera. Its other draws (the sensor rates) stay what they are without it.
TEST(CityScenario, EachVehicleDeclaresItsOwnCalibrationAndIsSimulatedWithIt) {
  CityScenarioOptions options = Small();
  options.rate_variation = 0.2;
  options.gnss_sigma_m = 1e-9;  // noise-free sensors: the passage must follow from the truth alone
  options.noise_model.speed_sigma_mps = 0.0;
  options.noise_model.steering_sigma_rad = 0.0;
  options.noise_model.pixel_sigma_px = 0.0;
  const CityScenario same = Make(options);
  options.vary_calibration = true;
  const CityScenario varied = Make(options);
  const CalibrationSpread spread;
  std::vector<Calibration> declared;
  for (int v = 0; v < options.vehicles; ++v) {
    const CityVehicle vehicle = varied.Vehicle(v);
    const Calibration& c = vehicle.calibration;
    EXPECT_EQ(vehicle.camera_rate_hz, same.Vehicle(v).camera_rate_hz) << v;
    EXPECT_EQ(vehicle.gnss_rate_hz, same.Vehicle(v).gnss_rate_hz) << v;
    EXPECT_EQ(same.Vehicle(v).calibration.fx_px, options.calibration.fx_px) << v;
    EXPECT_GE(c.image_width_px, spread.image_width_min_px) << v;
    EXPECT_LE(c.image_width_px, spread.image_width_max_px) << v;
    const double fov_rad = 2.0 * std::atan(0.5 * c.image_width_px / c.fx_px);
    EXPECT_GE(fov_rad, spread.fov_min_rad - 1e-9) << v;
    EXPECT_LE(fov_rad, spread.fov_max_rad + 1e-9) << v;
    EXPECT_LE(std::abs(c.cx_px / c.image_width_px - 0.5), spread.principal_point_offset_max) << v;
    EXPECT_LE(std::abs(c.camera_yaw_rad), spread.camera_yaw_max_rad) << v;
    EXPECT_GE(c.wheelbase_m, spread.wheelbase_min_m) << v;
    EXPECT_LE(c.wheelbase_m, spread.wheelbase_max_m) << v;
    EXPECT_EQ(vehicle.true_camera.camera_yaw_rad, c.camera_yaw_rad) << v << ": no yaw error asked for";
    declared.push_back(c);
  }
  EXPECT_NE(declared[0].fx_px, declared[1].fx_px);
  EXPECT_NE(declared[0].wheelbase_m, declared[1].wheelbase_m);

  for (int i = 0; i < 2 * options.vehicles; ++i) {
    const auto [passage, drive] = varied.MakePassageWithTruth(i);
    const Calibration& c = declared[i % options.vehicles];
    ASSERT_EQ(passage.calibration.fx_px, c.fx_px) << i;
    ASSERT_EQ(passage.calibration.gnss_lever_arm_m, c.gnss_lever_arm_m) << i;
    // Driven with its own wheelbase: dead reckoning with the declared one retraces the truth.
    Pose2 pose = drive.poses.front();
    double worst_m = 0.0;
    for (size_t j = 0; j + 1 < passage.odometry.size(); ++j) {
      const OdometrySample& o = passage.odometry[j];
      pose = BicycleStep(pose, o.speed_mps, o.steering_rad, passage.odometry[j + 1].t_s - o.t_s, c.wheelbase_m);
      worst_m = std::max(worst_m, (pose.head<2>() - drive.poses[j + 1].head<2>()).norm());
    }
    EXPECT_LT(worst_m, 1e-6) << i;
    // Fixed at its antenna.
    for (const GnssFix& fix : passage.gnss) {
      const Pose2 truth = drive.PoseAt(fix.t_s);
      const Eigen::Vector2d antenna = truth.head<2>() + Eigen::Rotation2Dd(truth.z()) * c.gnss_lever_arm_m;
      ASSERT_LT((varied.frame().ToLocal(LatLon{fix.lat_deg, fix.lon_deg}) - antenna).norm(), 1e-3) << i;
    }
    // Seen through its camera: each detection is the true pixel of that camera.
    ASSERT_FALSE(passage.detections.empty()) << i;
    for (const Detection& d : passage.detections) {
      double u = 0.0;
      ASSERT_TRUE(TruePixel(drive.PoseAt(d.t_s), varied.landmarks()[d.landmark_id - 1].position_m, c,
                            options.min_detection_range_m, options.max_detection_range_m, &u))
          << i;
      ASSERT_NEAR(d.u_px, u, 1e-9) << i;
    }
  }
}

TEST(CityScenario, ALateDistrictIsDrivenOnlyFromItsFirstPassageOn) {
  CityScenarioOptions options = Small();
  options.blocks_x = 4;
  options.late_blocks_x = 2;
  options.late_from_passage = 20;
  const CityScenario city = Make(options);
  // The street west of the late district; its lane lies at most a road half width east of it.
  const double boundary_m = city.layout().street_x_m()[options.blocks_x - options.late_blocks_x];
  double east_before = -1e9, east_after = -1e9;
  for (int i = 0; i < 40; ++i) {
    double& east = i < options.late_from_passage ? east_before : east_after;
    for (const Pose2& pose : city.TrueDrive(i).poses) east = std::max(east, pose.x());
  }
  EXPECT_LE(east_before, boundary_m + city.layout().road_half_width_m());
  EXPECT_GT(east_after, boundary_m + 100.0) << "later passages reach the district";
}

TEST(CityScenario, NoiseFreeOdometryDeadReckoningReproducesTheTrueTrajectory) {
  CityScenarioOptions options = Small();
  options.noise_model.speed_sigma_mps = 0.0;
  options.noise_model.steering_sigma_rad = 0.0;
  const CityScenario city = Make(options);
  const auto [passage, drive] = city.MakePassageWithTruth(2);
  ASSERT_EQ(passage.odometry.size(), drive.poses.size());
  Pose2 pose = drive.poses.front();
  double worst_m = 0.0;
  for (size_t j = 0; j + 1 < passage.odometry.size(); ++j) {
    const OdometrySample& o = passage.odometry[j];
    pose = BicycleStep(pose, o.speed_mps, o.steering_rad, passage.odometry[j + 1].t_s - o.t_s,
                       passage.calibration.wheelbase_m);
    worst_m = std::max(worst_m, (pose.head<2>() - drive.poses[j + 1].head<2>()).norm());
  }
  EXPECT_LT(worst_m, 1e-6);
  EXPECT_GT((drive.poses.back().head<2>() - drive.poses.front().head<2>()).norm(), 10.0);
}

TEST(CityScenario, DetectionsNeverSeeThroughBuildings) {
  const CityScenario city = Make(Small());
  int checked = 0;
  for (int i = 0; i < 4; ++i) {
    const auto [passage, drive] = city.MakePassageWithTruth(i);
    for (const Detection& d : passage.detections) {
      const Pose2 pose = drive.PoseAt(d.t_s);
      const Eigen::Vector2d camera = pose.head<2>() + Eigen::Vector2d(std::cos(pose.z()), std::sin(pose.z())) *
                                                          passage.calibration.camera_position_m.x();
      const Eigen::Vector2d landmark = city.landmarks()[d.landmark_id - 1].position_m;
      for (const Rect2& b : city.layout().buildings()) ASSERT_FALSE(SegmentCrossesRect(camera, landmark, b));
      ++checked;
    }
  }
  EXPECT_GT(checked, 200);
}

TEST(CityScenario, BuildingHidesALandmarkInRangeAndInTheImage) {
  // Blocks of 60 m without jitter: building (1, 1) spans [73, 107] m on both axes. A vehicle on
  // the street below it looks north across the building at the landmarks of the street beyond.
  CityScenarioOptions options = Small();
  options.block_m = 60.0;
  options.street_jitter_m = 0.0;
  options.max_detection_range_m = 80.0;
  const Pose2 pose(90.0, 57.5, M_PI / 2);
  const CityScenario occluded = Make(options);
  LandmarkId hidden = 0;
  for (const TruthLandmark& lm : occluded.landmarks()) {
    if (lm.position_m.x() > 76.0 && lm.position_m.x() < 104.0 && lm.position_m.y() > 105.0 && lm.position_m.y() < 115.0) {
      hidden = lm.id;
    }
  }
  ASSERT_NE(hidden, 0) << "no landmark behind the building";
  auto sees = [&](const CityScenario& city) {
    for (const VisibleLandmark& v : city.VisibleLandmarks(pose, options.calibration)) {
      if (v.id == hidden) return true;
    }
    return false;
  };
  EXPECT_FALSE(sees(occluded));
  options.occlusion = false;
  EXPECT_TRUE(sees(Make(options)));
}

TEST(CityScenario, SegmentCrossesRectOnlyThroughTheInterior) {
  const Rect2 r{{0.0, 0.0}, {10.0, 5.0}};
  EXPECT_TRUE(SegmentCrossesRect({-1.0, 2.0}, {11.0, 2.0}, r));
  EXPECT_TRUE(SegmentCrossesRect({-1.0, -1.0}, {2.0, 2.0}, r));
  EXPECT_FALSE(SegmentCrossesRect({-1.0, -1.0}, {-1.0, 9.0}, r));
  EXPECT_FALSE(SegmentCrossesRect({-1.0, 5.0}, {11.0, 5.0}, r));  // along the border
  EXPECT_FALSE(SegmentCrossesRect({-2.0, 1.0}, {1.0, 7.0}, r));   // passes the corner outside
}

TEST(CityScenario, RefusesInvalidOptionsNamingTheField) {
  const std::vector<std::pair<std::string, std::function<void(CityScenarioOptions*)>>> cases = {
      {"blocks_x", [](CityScenarioOptions* o) { o->blocks_x = 0; }},
      {"blocks_y", [](CityScenarioOptions* o) { o->blocks_y = -2; }},
      {"block_m", [](CityScenarioOptions* o) { o->block_m = 30.0; }},
      {"spacing_min_m", [](CityScenarioOptions* o) { o->spacing_min_m = 0.0; }},
      {"spacing_max_m", [](CityScenarioOptions* o) { o->spacing_max_m = 5.0; }},
      {"building_setback_m", [](CityScenarioOptions* o) { o->building_setback_m = 4.0; }},
      {"route_length_m", [](CityScenarioOptions* o) { o->route_length_m = -1.0; }},
      {"vehicles", [](CityScenarioOptions* o) { o->vehicles = 0; }},
      {"late_blocks_x", [](CityScenarioOptions* o) { o->late_blocks_x = o->blocks_x; }},
      {"late_from_passage", [](CityScenarioOptions* o) { o->late_from_passage = -1; }},
      {"camera_rate_hz", [](CityScenarioOptions* o) { o->camera_rate_hz = NAN; }},
      {"gnss_ar1_alpha", [](CityScenarioOptions* o) { o->gnss_ar1_alpha = 1.0; }},
      {"max_detection_range_m", [](CityScenarioOptions* o) { o->max_detection_range_m = 4.0; }},
      {"origin", [](CityScenarioOptions* o) { o->origin.lat_deg = 91.0; }},
      {"stop_probability", [](CityScenarioOptions* o) { o->stop_probability = 1.5; }},
      {"vehicle_speed_scale_sigma", [](CityScenarioOptions* o) { o->vehicle_speed_scale_sigma = 0.5; }},
      {"stop_max_s", [](CityScenarioOptions* o) { o->stop_max_s = 1.0; }},
      {"gnss_outage_probability", [](CityScenarioOptions* o) { o->gnss_outage_probability = -0.1; }},
      {"gnss_outage_min_s", [](CityScenarioOptions* o) { o->gnss_outage_min_s = NAN; }},
  };
  for (const auto& [field, mutate] : cases) {
    CityScenarioOptions options;
    mutate(&options);
    const absl::StatusOr<CityScenario> city = CityScenario::Create(options);
    ASSERT_FALSE(city.ok()) << field;
    EXPECT_EQ(city.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_EQ(city.status().message().substr(0, field.size() + 1), field + ":") << city.status();
  }
  EXPECT_TRUE(CityScenarioOptions().Validate().ok());
}

TEST(CityScenario, HundredThousandLandmarkLayoutIsBuiltQuicklyAndPassagesUseTheIndex) {
  CityScenarioOptions options;
  options.blocks_x = 70;
  options.blocks_y = 70;
  const auto start = std::chrono::steady_clock::now();
  const CityScenario city = Make(options);
  const double layout_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_GE(city.landmark_count(), 100000u);
  EXPECT_LT(layout_s, 3.0);
  const auto passage_start = std::chrono::steady_clock::now();
  const Passage p = city.MakePassage(0);
  const double passage_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - passage_start).count();
  EXPECT_TRUE(ValidatePassage(p).ok());
  EXPECT_LT(passage_s, 1.0);
  std::printf("layout: %zu landmarks in %.3f s; one 2 km passage (%zu detections) in %.3f s\n", city.landmark_count(),
              layout_s, p.detections.size(), passage_s);
}

}  // namespace
}  // namespace crowdmap
