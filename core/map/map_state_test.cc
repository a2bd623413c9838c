#include "core/map/map_state.h"

#include <algorithm>
#include <set>
#include <vector>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

Landmark MakeLandmark(LandmarkId id, int64_t version) {
  Landmark l;
  l.id = id;
  l.position = {48.0 + 0.001 * id, 2.0};
  l.cov_en_m2 = Eigen::Matrix2d::Identity() * id;
  l.version = version;
  return l;
}

Eigen::Matrix2d Block(double a, double b, double c, double d) {
  Eigen::Matrix2d m;
  m << a, b, c, d;
  return m;
}

std::vector<LandmarkId> SortedNeighbors(const MapReaderInterface& map, LandmarkId id) {
  std::vector<LandmarkId> n;
  map.AppendNeighbors(id, &n);
  std::sort(n.begin(), n.end());
  return n;
}

TEST(MapState, FindsWhatWasPutAndReplacesOnPut) {
  MapState map;
  EXPECT_EQ(map.FindLandmark(1), nullptr);
  map.PutLandmark(MakeLandmark(1, 2));
  map.PutLandmark(MakeLandmark(5, 1));
  ASSERT_NE(map.FindLandmark(1), nullptr);
  EXPECT_EQ(map.FindLandmark(1)->id, 1);
  EXPECT_EQ(map.FindLandmark(5)->cov_en_m2, Eigen::Matrix2d::Identity() * 5);
  EXPECT_EQ(map.FindLandmark(2), nullptr);
  EXPECT_EQ(map.version(), 2) << "the highest landmark version";

  Landmark moved = MakeLandmark(1, 3);
  moved.position.lat_deg = 47.0;
  map.PutLandmark(moved);
  EXPECT_EQ(map.landmark_count(), 2u);
  EXPECT_EQ(map.FindLandmark(1)->position.lat_deg, 47.0);
  EXPECT_EQ(map.version(), 3);
  EXPECT_EQ(map.LandmarkIds(), (std::vector<LandmarkId>{1, 5}));
}

TEST(MapState, CrossCovarianceReadsTransposedFromTheOtherSide) {
  MapState map;
  for (LandmarkId id : {1, 2, 3}) map.PutLandmark(MakeLandmark(id, 1));
  const Eigen::Matrix2d c = Block(1.0, 2.0, 3.0, 4.0);
  map.PutCrossCovariance(1, 2, c);
  Eigen::Matrix2d ab, ba;
  ASSERT_TRUE(map.CrossCovariance(1, 2, &ab));
  ASSERT_TRUE(map.CrossCovariance(2, 1, &ba));
  EXPECT_EQ(ab, c);
  EXPECT_EQ(ba, c.transpose());
  EXPECT_EQ(map.cross_block_count(), 1u);

  // Writing the same pair from the other side replaces the block; it is still one block.
  const Eigen::Matrix2d d = Block(5.0, 6.0, 7.0, 8.0);
  map.PutCrossCovariance(2, 1, d);
  ASSERT_TRUE(map.CrossCovariance(1, 2, &ab));
  EXPECT_EQ(ab, d.transpose());
  EXPECT_EQ(map.cross_block_count(), 1u);

  Eigen::Matrix2d untouched = Eigen::Matrix2d::Constant(-9.0);
  EXPECT_FALSE(map.CrossCovariance(1, 3, &untouched));
  EXPECT_FALSE(map.CrossCovariance(1, 42, &untouched));
  EXPECT_EQ(untouched, Eigen::Matrix2d::Constant(-9.0)) << "no block: output untouched";
}

TEST(MapState, ReportsNeighboursFromBothEndsOfEachBlock) {
  MapState map;
  for (LandmarkId id : {1, 2, 3, 4}) map.PutLandmark(MakeLandmark(id, 1));
  map.PutCrossCovariance(1, 2, Eigen::Matrix2d::Identity());
  map.PutCrossCovariance(3, 1, Eigen::Matrix2d::Identity());
  map.PutCrossCovariance(1, 3, Eigen::Matrix2d::Identity());  // same pair again
  EXPECT_EQ(SortedNeighbors(map, 1), (std::vector<LandmarkId>{2, 3}));
  EXPECT_EQ(SortedNeighbors(map, 2), (std::vector<LandmarkId>{1}));
  EXPECT_EQ(SortedNeighbors(map, 3), (std::vector<LandmarkId>{1}));
  EXPECT_TRUE(SortedNeighbors(map, 4).empty());
  EXPECT_TRUE(SortedNeighbors(map, 99).empty());
  EXPECT_EQ(map.cross_block_count(), 2u);
}

TEST(MapState, ApplyWritesTheDeltaAndAdvancesTheVersion) {
  MapState map;
  map.PutLandmark(MakeLandmark(1, 4));
  map.PutLandmark(MakeLandmark(2, 4));
  map.PutCrossCovariance(1, 2, Block(0.1, 0.2, 0.3, 0.4));
  MapDelta delta;
  delta.base_version = 4;
  delta.version = 6;
  Landmark changed = MakeLandmark(2, 6);
  changed.cov_en_m2 *= 0.5;
  delta.landmarks[2] = changed;
  delta.landmarks[3] = MakeLandmark(3, 6);
  delta.cross[{1, 3}] = Block(1.0, 2.0, 3.0, 4.0);
  delta.cross[{1, 2}] = Block(0.5, 0.6, 0.7, 0.8);
  map.Apply(delta);

  EXPECT_EQ(map.version(), 6);
  EXPECT_EQ(map.landmark_count(), 3u);
  EXPECT_EQ(map.FindLandmark(1)->version, 4) << "not in the delta: unchanged";
  EXPECT_EQ(map.FindLandmark(2)->cov_en_m2, Eigen::Matrix2d::Identity());
  EXPECT_EQ(map.FindLandmark(3)->version, 6);
  EXPECT_EQ(map.cross_block_count(), 2u);
  Eigen::Matrix2d c;
  ASSERT_TRUE(map.CrossCovariance(3, 1, &c));
  EXPECT_EQ(c, Block(1.0, 2.0, 3.0, 4.0).transpose());
  ASSERT_TRUE(map.CrossCovariance(1, 2, &c));
  EXPECT_EQ(c, Block(0.5, 0.6, 0.7, 0.8));
  EXPECT_EQ(SortedNeighbors(map, 1), (std::vector<LandmarkId>{2, 3}));

  MapDelta empty;
  empty.base_version = 6;
  empty.version = 7;
  EXPECT_TRUE(empty.empty());
  map.Apply(empty);
  EXPECT_EQ(map.version(), 7) << "a version step without changes still advances the map";
}

class MapOverlayTest : public testing::Test {
 protected:
  MapOverlayTest() {
    base_.PutLandmark(MakeLandmark(1, 3));
    base_.PutLandmark(MakeLandmark(2, 3));
    base_.PutLandmark(MakeLandmark(4, 2));
    base_.PutCrossCovariance(1, 2, Eigen::Matrix2d::Constant(0.5));
    base_.PutCrossCovariance(2, 4, Eigen::Matrix2d::Constant(0.75));
  }
  MapState base_;
};

TEST_F(MapOverlayTest, ReadsThroughToTheBaseBeforeAnyWrite) {
  MapOverlay overlay(base_);
  EXPECT_EQ(overlay.version(), 3);
  EXPECT_EQ(overlay.FindLandmark(1), base_.FindLandmark(1));
  EXPECT_EQ(overlay.FindLandmark(9), nullptr);
  Eigen::Matrix2d c;
  ASSERT_TRUE(overlay.CrossCovariance(4, 2, &c));
  EXPECT_EQ(c, Eigen::Matrix2d::Constant(0.75));
  EXPECT_EQ(SortedNeighbors(overlay, 2), (std::vector<LandmarkId>{1, 4}));
  EXPECT_TRUE(overlay.delta().empty());
}

TEST_F(MapOverlayTest, SeesItsOwnWritesAndLeavesTheBaseUntouched) {
  MapOverlay overlay(base_);
  EXPECT_EQ(overlay.BumpVersion(), 4);
  Landmark moved = MakeLandmark(1, 4);
  moved.cov_en_m2 *= 0.5;
  overlay.PutLandmark(moved);
  overlay.PutLandmark(MakeLandmark(3, 4));
  const Eigen::Matrix2d c31 = Block(0.1, 0.2, 0.3, 0.4);
  overlay.PutCrossCovariance(3, 1, c31);
  overlay.PutCrossCovariance(2, 1, Block(1.0, 2.0, 3.0, 4.0));  // replaces a base block

  EXPECT_EQ(overlay.version(), 4);
  EXPECT_EQ(overlay.FindLandmark(1)->version, 4);
  EXPECT_EQ(overlay.FindLandmark(1)->cov_en_m2, Eigen::Matrix2d::Identity() * 0.5);
  EXPECT_EQ(overlay.FindLandmark(3)->version, 4);
  EXPECT_EQ(overlay.FindLandmark(2), base_.FindLandmark(2));
  Eigen::Matrix2d c;
  ASSERT_TRUE(overlay.CrossCovariance(3, 1, &c));
  EXPECT_EQ(c, c31);
  ASSERT_TRUE(overlay.CrossCovariance(1, 3, &c));
  EXPECT_EQ(c, c31.transpose());
  ASSERT_TRUE(overlay.CrossCovariance(1, 2, &c));
  EXPECT_EQ(c, Block(1.0, 2.0, 3.0, 4.0).transpose());
  ASSERT_TRUE(overlay.CrossCovariance(2, 1, &c));
  EXPECT_EQ(c, Block(1.0, 2.0, 3.0, 4.0));

  EXPECT_EQ(base_.version(), 3);
  EXPECT_EQ(base_.FindLandmark(1)->version, 3);
  EXPECT_EQ(base_.FindLandmark(1)->cov_en_m2, Eigen::Matrix2d::Identity());
  EXPECT_EQ(base_.FindLandmark(3), nullptr);
  EXPECT_EQ(base_.cross_block_count(), 2u);
  ASSERT_TRUE(base_.CrossCovariance(1, 2, &c));
  EXPECT_EQ(c, Eigen::Matrix2d::Constant(0.5));
  EXPECT_FALSE(base_.CrossCovariance(1, 3, &c));
  EXPECT_EQ(SortedNeighbors(base_, 1), (std::vector<LandmarkId>{2}));
}

TEST_F(MapOverlayTest, ReportsNeighboursFromBaseAndDeltaOnce) {
  MapOverlay overlay(base_);
  overlay.BumpVersion();
  overlay.PutLandmark(MakeLandmark(3, 4));
  overlay.PutCrossCovariance(1, 2, Eigen::Matrix2d::Identity());  // pair already in the base
  overlay.PutCrossCovariance(2, 1, Eigen::Matrix2d::Identity());  // and once more, reversed
  overlay.PutCrossCovariance(3, 1, Eigen::Matrix2d::Identity());  // new pair
  overlay.PutCrossCovariance(1, 3, Eigen::Matrix2d::Identity());  // same new pair again
  overlay.PutCrossCovariance(3, 4, Eigen::Matrix2d::Identity());  // new pair
  EXPECT_EQ(SortedNeighbors(overlay, 1), (std::vector<LandmarkId>{2, 3}));
  EXPECT_EQ(SortedNeighbors(overlay, 2), (std::vector<LandmarkId>{1, 4}));
  EXPECT_EQ(SortedNeighbors(overlay, 3), (std::vector<LandmarkId>{1, 4}));
  EXPECT_EQ(SortedNeighbors(overlay, 4), (std::vector<LandmarkId>{2, 3}));
}

TEST_F(MapOverlayTest, TakeDeltaHoldsExactlyTheWritesUntilApplied) {
  MapOverlay overlay(base_);
  overlay.BumpVersion();
  Landmark moved = MakeLandmark(1, 4);
  moved.cov_en_m2 *= 0.5;
  overlay.PutLandmark(moved);
  overlay.PutLandmark(MakeLandmark(3, 4));
  overlay.PutCrossCovariance(3, 1, Block(0.1, 0.2, 0.3, 0.4));
  overlay.PutCrossCovariance(2, 1, Block(1.0, 2.0, 3.0, 4.0));

  const MapDelta delta = overlay.TakeDelta();
  EXPECT_EQ(delta.base_version, 3);
  EXPECT_EQ(delta.version, 4);
  std::set<LandmarkId> ids;
  for (const auto& [id, landmark] : delta.landmarks) {
    EXPECT_EQ(id, landmark.id);
    ids.insert(id);
  }
  EXPECT_EQ(ids, (std::set<LandmarkId>{1, 3}));
  ASSERT_EQ(delta.cross.size(), 2u);
  // Keys are ordered pairs; blocks are stored as Sigma_first,second.
  ASSERT_EQ(delta.cross.count({1, 3}), 1u);
  ASSERT_EQ(delta.cross.count({1, 2}), 1u);
  EXPECT_EQ(delta.cross.at({1, 3}), Block(0.1, 0.2, 0.3, 0.4).transpose());
  EXPECT_EQ(delta.cross.at({1, 2}), Block(1.0, 2.0, 3.0, 4.0).transpose());

  EXPECT_EQ(base_.version(), 3) << "untouched until Apply";
  EXPECT_EQ(base_.landmark_count(), 3u);
  base_.Apply(delta);
  EXPECT_EQ(base_.version(), 4);
  EXPECT_EQ(base_.landmark_count(), 4u);
  EXPECT_EQ(base_.cross_block_count(), 3u);
  EXPECT_EQ(base_.FindLandmark(1)->cov_en_m2, Eigen::Matrix2d::Identity() * 0.5);
  Eigen::Matrix2d c;
  ASSERT_TRUE(base_.CrossCovariance(3, 1, &c));
  EXPECT_EQ(c, Block(0.1, 0.2, 0.3, 0.4));
  ASSERT_TRUE(base_.CrossCovariance(2, 1, &c));
  EXPECT_EQ(c, Block(1.0, 2.0, 3.0, 4.0));
  EXPECT_EQ(SortedNeighbors(base_, 1), (std::vector<LandmarkId>{2, 3}));
}

}  // namespace
}  // namespace crowdmap
