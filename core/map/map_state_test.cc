#include "core/map/map_state.h"

#include <algorithm>

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

TEST(MapState, CrossCovarianceIsStoredOnceAndReadTransposed) {
  MapState map;
  map.PutLandmark(MakeLandmark(1, 1));
  map.PutLandmark(MakeLandmark(2, 1));
  Eigen::Matrix2d c;
  c << 1.0, 2.0, 3.0, 4.0;
  map.PutCrossCovariance(1, 2, c);
  Eigen::Matrix2d ab, ba;
  ASSERT_TRUE(map.CrossCovariance(1, 2, &ab));
  ASSERT_TRUE(map.CrossCovariance(2, 1, &ba));
  EXPECT_EQ(ab, c);
  EXPECT_EQ(ba, c.transpose());
  EXPECT_EQ(map.cross_block_count(), 1u);
  EXPECT_FALSE(map.CrossCovariance(1, 3, &ab));
  std::vector<LandmarkId> n;
  map.AppendNeighbors(1, &n);
  EXPECT_EQ(n, std::vector<LandmarkId>{2});
  EXPECT_EQ(map.version(), 1);
}

TEST(MapOverlay, ReadsThroughToTheBaseAndKeepsItsWritesUntilApplied) {
  MapState base;
  base.PutLandmark(MakeLandmark(1, 3));
  base.PutLandmark(MakeLandmark(2, 3));
  base.PutCrossCovariance(1, 2, Eigen::Matrix2d::Constant(0.5));
  MapOverlay overlay(base);
  EXPECT_EQ(overlay.version(), 3);
  EXPECT_EQ(overlay.FindLandmark(1)->version, 3);

  EXPECT_EQ(overlay.BumpVersion(), 4);
  overlay.PutLandmark(MakeLandmark(3, 4));
  Landmark moved = MakeLandmark(1, 4);
  moved.cov_en_m2 *= 0.5;
  overlay.PutLandmark(moved);
  overlay.PutCrossCovariance(3, 1, Eigen::Matrix2d::Constant(0.25));
  overlay.PutCrossCovariance(2, 1, Eigen::Matrix2d::Constant(0.125));  // replaces a base block

  EXPECT_EQ(overlay.FindLandmark(1)->version, 4);
  EXPECT_EQ(base.FindLandmark(1)->version, 3) << "the base is untouched until Apply";
  EXPECT_EQ(base.FindLandmark(3), nullptr);
  std::vector<LandmarkId> n;
  overlay.AppendNeighbors(1, &n);
  std::sort(n.begin(), n.end());
  EXPECT_EQ(n, (std::vector<LandmarkId>{2, 3})) << "each neighbour once";
  Eigen::Matrix2d c;
  ASSERT_TRUE(overlay.CrossCovariance(1, 2, &c));
  EXPECT_EQ(c, Eigen::Matrix2d::Constant(0.125));

  const MapDelta delta = overlay.TakeDelta();
  EXPECT_EQ(delta.base_version, 3);
  EXPECT_EQ(delta.version, 4);
  EXPECT_EQ(delta.landmarks.size(), 2u);
  EXPECT_EQ(delta.cross.size(), 2u);
  base.Apply(delta);
  EXPECT_EQ(base.version(), 4);
  EXPECT_EQ(base.landmark_count(), 3u);
  EXPECT_EQ(base.cross_block_count(), 2u);
  ASSERT_TRUE(base.CrossCovariance(1, 3, &c));
  EXPECT_EQ(c, Eigen::Matrix2d::Constant(0.25));
}

}  // namespace
}  // namespace crowdmap
