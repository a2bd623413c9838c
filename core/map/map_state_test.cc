#include "core/map/map_state.h"

#include <algorithm>
#include <vector>

#include <gtest/gtest.h>

#include "core/map/map_testing.h"

namespace crowdmap {
namespace {

std::vector<LandmarkId> SortedLinked(const MapReaderInterface& map, LandmarkId id) {
  std::vector<LandmarkId> n;
  map.AppendLinked(id, &n);
  std::sort(n.begin(), n.end());
  return n;
}

TEST(MapState, FindsWhatWasPutAndReplacesOnPut) {
  MapState map;
  EXPECT_EQ(map.FindLandmark(1), nullptr);
  map.PutLandmark(MakeLandmark(1, 2));
  map.PutLandmark(MakeLandmark(5, 1));
  ASSERT_NE(map.FindLandmark(1), nullptr);
  EXPECT_EQ(map.FindLandmark(5)->cov_en_m2, Eigen::Matrix2d::Identity() * 5);
  EXPECT_EQ(map.version(), 2) << "the highest landmark version";
  Landmark moved = MakeLandmark(1, 3);
  moved.position.lat_deg += 1e-5;
  map.PutLandmark(moved);
  EXPECT_EQ(map.landmark_count(), 2u);
  EXPECT_NEAR(map.FindLandmark(1)->Offset().y(), 1.11, 0.01) << "1e-5 degree of latitude north of the anchor";
  EXPECT_EQ(map.LandmarkIds(), (std::vector<LandmarkId>{1, 5}));
}

TEST(MapState, SumsTheFactorsIntoSparseInformationBlocks) {
  MapState map;
  map.PutFactor(MakeFactor(1, {1, 2}));
  map.PutFactor(MakeFactor(2, {2, 3}, "q"));
  EXPECT_EQ(map.factor_count(), 2u);
  EXPECT_EQ(map.last_factor_id(), 2);
  // Landmark 2 is second in factor 1 and first in factor 2.
  const InformationBlock diag2 = map.Information(2, 2);
  EXPECT_EQ(diag2.factors, 2);
  EXPECT_DOUBLE_EQ(diag2.value(0, 0), 3.0 + 1.0);
  EXPECT_DOUBLE_EQ(diag2.value(1, 1), 4.0 + 2.0);
  EXPECT_EQ(map.Information(1, 3).factors, 0) << "never in one factor";
  EXPECT_EQ(map.Information(3, 2).value, map.Information(2, 3).value.transpose());
  EXPECT_DOUBLE_EQ(map.InformationVector(2).x(), 3.0 + 1.0);
  EXPECT_EQ(SortedLinked(map, 2), (std::vector<LandmarkId>{1, 3}));
  EXPECT_EQ(SortedLinked(map, 1), (std::vector<LandmarkId>{2}));
  std::vector<int64_t> ids;
  map.AppendPassageFactorIds("v", "q", &ids);
  EXPECT_EQ(ids, (std::vector<int64_t>{2}));

  map.RemoveFactor(1);
  EXPECT_EQ(map.Information(2, 2).factors, 1);
  EXPECT_NEAR(map.Information(2, 2).value(0, 0), 1.0, 1e-15);
  EXPECT_TRUE(SortedLinked(map, 1).empty()) << "the link went with the factor";
  EXPECT_EQ(map.InformationVector(1), Eigen::Vector2d::Zero());
  EXPECT_EQ(map.last_factor_id(), 2) << "ids are not reused";
}

TEST(MapState, ApplyWritesTheDeltaAndAdvancesTheVersion) {
  MapState map;
  map.PutLandmark(MakeLandmark(1, 4));
  map.PutLandmark(MakeLandmark(2, 4));
  map.PutFactor(MakeFactor(7, {1, 2}));
  MapDelta delta;
  delta.base_version = 4;
  delta.version = 6;
  delta.landmarks[3] = MakeLandmark(3, 6);
  delta.added_factors[8] = MakeFactor(8, {2, 3});
  delta.removed_factors.push_back(7);
  delta.removed_landmarks.push_back(1);
  map.Apply(delta);
  EXPECT_EQ(map.version(), 6);
  EXPECT_EQ(map.FindLandmark(1), nullptr);
  EXPECT_EQ(map.FindLandmark(2)->version, 4) << "not in the delta: unchanged";
  EXPECT_EQ(map.FindFactor(7), nullptr);
  ASSERT_NE(map.FindFactor(8), nullptr);
  EXPECT_EQ(SortedLinked(map, 2), (std::vector<LandmarkId>{3}));

  MapDelta empty;
  empty.base_version = 6;
  empty.version = 7;
  EXPECT_TRUE(empty.empty());
  map.Apply(empty);
  EXPECT_EQ(map.version(), 7) << "a version step without changes still advances the map";
}

TEST(MapState, FoldingDropsTheRecordAndKeepsTheInformation) {
  MapState map;
  map.PutFactor(MakeFactor(1, {1, 2}));
  map.PutFactor(MakeFactor(2, {2, 3}, "q"));
  const InformationBlock before = map.Information(1, 2);
  const Eigen::Vector2d vector_before = map.InformationVector(2);
  MapDelta delta;
  delta.folded_factors = {1};
  map.Apply(delta);
  EXPECT_EQ(map.FindFactor(1), nullptr);
  EXPECT_EQ(map.factor_count(), 1u);
  std::vector<int64_t> of_p;
  map.AppendPassageFactorIds("v", "p", &of_p);
  EXPECT_TRUE(of_p.empty());
  EXPECT_EQ(map.Information(1, 2).value, before.value);
  EXPECT_EQ(map.Information(1, 2).factors, before.factors);
  EXPECT_EQ(map.InformationVector(2), vector_before);
  EXPECT_EQ(SortedLinked(map, 2), (std::vector<LandmarkId>{1, 3}));
  // Loading a stored base gives the same sums.
  MapState loaded;
  loaded.PutFactor(MakeFactor(2, {2, 3}, "q"));
  const MapFactor folded = MakeFactor(1, {1, 2});
  loaded.PutBaseBlock(1, 1, folded.information.block<2, 2>(0, 0));
  loaded.PutBaseBlock(1, 2, folded.information.block<2, 2>(0, 2));
  loaded.PutBaseBlock(2, 2, folded.information.block<2, 2>(2, 2));
  loaded.PutBaseVector(1, folded.information_vector.segment<2>(0));
  loaded.PutBaseVector(2, folded.information_vector.segment<2>(2));
  for (LandmarkId a : {1, 2, 3}) {
    EXPECT_EQ(loaded.InformationVector(a), map.InformationVector(a)) << a;
    for (LandmarkId b : {1, 2, 3}) EXPECT_EQ(loaded.Information(a, b).value, map.Information(a, b).value) << a << b;
  }
}

class MapOverlayTest : public testing::Test {
 protected:
  MapOverlayTest() {
    for (LandmarkId id : {1, 2, 4}) base_.PutLandmark(MakeLandmark(id, 3));
    base_.PutFactor(MakeFactor(1, {1, 2}));
    base_.PutFactor(MakeFactor(2, {2, 4}, "q"));
  }
  MapState base_;
};

TEST_F(MapOverlayTest, ReadsThroughToTheBaseBeforeAnyWrite) {
  MapOverlay overlay(base_);
  EXPECT_EQ(overlay.version(), 3);
  EXPECT_EQ(overlay.last_factor_id(), 2);
  EXPECT_EQ(overlay.Information(2, 2).value, base_.Information(2, 2).value);
  EXPECT_EQ(SortedLinked(overlay, 2), (std::vector<LandmarkId>{1, 4}));
  EXPECT_TRUE(overlay.delta().empty());
}

TEST_F(MapOverlayTest, ListsTheVehiclesOfTheBaseAndItsOwnInOrderItsRecordsReplacingTheBases) {
  auto vehicle = [](const std::string& id, double offset) {
    VehicleCalibration v;
    v.vehicle_id = id;
    v.camera_yaw_offset_rad = offset;
    return v;
  };
  for (const char* id : {"b", "d", "f"}) base_.PutVehicle(vehicle(id, 1.0));
  MapOverlay overlay(base_);
  for (const char* id : {"a", "d", "e", "g"}) overlay.PutVehicle(vehicle(id, 2.0));
  std::vector<std::pair<std::string, double>> listed;
  overlay.ForEachVehicle([&](const VehicleCalibration& v) { listed.emplace_back(v.vehicle_id, v.camera_yaw_offset_rad); });
  EXPECT_EQ(listed, (std::vector<std::pair<std::string, double>>{
                        {"a", 2.0}, {"b", 1.0}, {"d", 2.0}, {"e", 2.0}, {"f", 1.0}, {"g", 2.0}}));
  int in_base = 0;
  base_.ForEachVehicle([&](const VehicleCalibration& v) { in_base += v.camera_yaw_offset_rad == 1.0; });
  EXPECT_EQ(in_base, 3);
}

TEST_F(MapOverlayTest, AddsAndRemovesFactorsOverTheBaseAndLeavesItUntouched) {
  MapOverlay overlay(base_);
  EXPECT_EQ(overlay.AddFactor(MakeFactor(0, {4, 5})), 3) << "the next id";
  overlay.RemoveFactor(1);
  EXPECT_EQ(overlay.FindFactor(1), nullptr);
  EXPECT_EQ(SortedLinked(overlay, 2), (std::vector<LandmarkId>{4}));
  EXPECT_EQ(SortedLinked(overlay, 4), (std::vector<LandmarkId>{2, 5}));
  EXPECT_NEAR(overlay.Information(2, 2).value(0, 0), 1.0, 1e-15) << "factor 2 only";
  std::vector<int64_t> of_p;
  overlay.AppendPassageFactorIds("v", "p", &of_p);
  EXPECT_EQ(of_p, (std::vector<int64_t>{3})) << "factor 1 removed, factor 3 added";
  std::vector<int64_t> of_4;
  overlay.AppendFactorIds(4, &of_4);
  std::sort(of_4.begin(), of_4.end());
  EXPECT_EQ(of_4, (std::vector<int64_t>{2, 3}));
  EXPECT_EQ(SortedLinked(base_, 2), (std::vector<LandmarkId>{1, 4})) << "base untouched";

  // A base factor folded here is hidden like a removed one, but its information stays.
  MapOverlay folding(base_);
  folding.FoldFactor(2);
  EXPECT_EQ(folding.FindFactor(2), nullptr);
  EXPECT_EQ(folding.Information(2, 4).value, base_.Information(2, 4).value);
  EXPECT_EQ(folding.delta().folded_factors, (std::vector<int64_t>{2}));

  // An added factor removed again leaves nothing behind.
  overlay.RemoveFactor(3);
  EXPECT_TRUE(overlay.delta().added_factors.empty());
  EXPECT_EQ(SortedLinked(overlay, 4), (std::vector<LandmarkId>{2}));
}

TEST_F(MapOverlayTest, TakeDeltaHoldsExactlyTheWritesUntilApplied) {
  MapOverlay overlay(base_);
  overlay.AddFactor(MakeFactor(0, {4, 5}));
  overlay.RemoveFactor(1);
  overlay.RemoveLandmark(1);
  EXPECT_EQ(overlay.FindLandmark(1), nullptr);
  overlay.PutLandmark(MakeLandmark(5, 4));
  EXPECT_EQ(overlay.BumpVersion(), 4);
  MapDelta delta = overlay.TakeDelta();
  EXPECT_EQ(delta.base_version, 3);
  EXPECT_EQ(delta.version, 4);
  base_.Apply(delta);
  EXPECT_EQ(base_.FindLandmark(1), nullptr);
  EXPECT_NE(base_.FindLandmark(5), nullptr);
  EXPECT_EQ(base_.factor_count(), 2u);
  EXPECT_EQ(SortedLinked(base_, 4), (std::vector<LandmarkId>{2, 5}));
  EXPECT_EQ(base_.version(), 4);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

MapDelta OneLandmarkOneFactor() {
  MapDelta delta;
  Landmark l;
  l.id = 7;
  l.anchor = l.position = LatLon{45.0, 4.0};
  l.cov_en_m2 << 2.0, 0.5, 0.5, 1.0;
  delta.landmarks[7] = l;
  MapFactor f;
  f.id = 3;
  f.landmarks = {7};
  f.information = Eigen::Matrix2d::Identity();
  f.information_vector = Eigen::Vector2d(1.0, 2.0);
  delta.added_factors[3] = f;
  return delta;
}

TEST(CheckDeltaInvariants, AcceptsAFiniteConsistentChange) { EXPECT_TRUE(CheckDeltaInvariants(OneLandmarkOneFactor()).ok()); }

TEST(CheckDeltaInvariants, RefusesEachViolationNamingWhatBrokeIt) {
  const auto refused = [](const MapDelta& delta, const std::string& what) {
    const absl::Status s = CheckDeltaInvariants(delta);
    EXPECT_EQ(s.code(), absl::StatusCode::kInternal) << what;
    EXPECT_NE(s.message().find(what), std::string::npos) << s.message();
  };
  MapDelta d = OneLandmarkOneFactor();
  d.landmarks[7].position.lat_deg = std::nan("");
  refused(d, "landmark 7: position");
  d = OneLandmarkOneFactor();
  d.landmarks[7].position.lat_deg = 91.0;
  refused(d, "landmark 7: position");
  d = OneLandmarkOneFactor();
  d.landmarks[7].cov_en_m2 << 1.0, 2.0, 2.0, 1.0;  // indefinite
  refused(d, "landmark 7: covariance");
  d = OneLandmarkOneFactor();
  d.landmarks[7].cov_en_m2(0, 1) = 0.7;  // not symmetric
  refused(d, "landmark 7: covariance");
  d = OneLandmarkOneFactor();
  d.added_factors[3].information(1, 1) = -1.0;
  refused(d, "factor 3: information not positive semi-definite");
  d = OneLandmarkOneFactor();
  d.added_factors[3].information_vector(0) = std::numeric_limits<double>::infinity();
  refused(d, "factor 3: information not finite");
  d = OneLandmarkOneFactor();
  d.added_factors[3].information = Eigen::Matrix3d::Identity();
  refused(d, "factor 3: information of the wrong size");
}

}  // namespace
}  // namespace crowdmap
