#include "core/geo/tiles.h"

#include <cmath>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// The slippy-map formula as written on the OpenStreetMap wiki (ln(tan + sec) form), kept apart
// from the library's asinh(tan) form so the two check each other.
TileId ReferenceTile(double lat_deg, double lon_deg, int z) {
  const double n = std::pow(2.0, z);
  const double lat = lat_deg * M_PI / 180.0;
  const double x = (lon_deg + 180.0) / 360.0 * n;
  const double y = (1.0 - std::log(std::tan(lat) + 1.0 / std::cos(lat)) / M_PI) / 2.0 * n;
  return {z, static_cast<int>(std::floor(x)), static_cast<int>(std::floor(y))};
}

bool Contains(const BoundingBox& b, const LatLon& p) {
  return b.min_lat_deg <= p.lat_deg && p.lat_deg <= b.max_lat_deg && b.min_lon_deg <= p.lon_deg &&
         p.lon_deg <= b.max_lon_deg;
}

TEST(TileContaining, GivesTheKnownTilesAtLowZoom) {
  EXPECT_EQ(TileContaining({0.0, 0.0}, 0), (TileId{0, 0, 0}));
  // (0, 0) lies on the corner of the four z1 tiles; floor puts it in the South-East one.
  EXPECT_EQ(TileContaining({0.0, 0.0}, 1), (TileId{1, 1, 1}));
  EXPECT_EQ(TileContaining({10.0, 10.0}, 1), (TileId{1, 1, 0}));
  EXPECT_EQ(TileContaining({10.0, -10.0}, 1), (TileId{1, 0, 0}));
  EXPECT_EQ(TileContaining({-10.0, -10.0}, 1), (TileId{1, 0, 1}));
  EXPECT_EQ(TileContaining({-10.0, 10.0}, 1), (TileId{1, 1, 1}));
}

TEST(TileContaining, GivesTheKnownTilesOfParisAndNewYork) {
  // Eiffel tower at z16: x = 182.2945 / 360 * 65536 = 33185.70,
  // y = (1 - ln(tan(48.8584 deg) + sec(48.8584 deg)) / pi) / 2 * 65536 = 22545.75.
  EXPECT_EQ(TileContaining({48.8584, 2.2945}, 16), (TileId{16, 33185, 22545}));
  // Statue of Liberty at z12: x = 105.9555 / 360 * 4096 = 1205.54, y = 1540.37.
  EXPECT_EQ(TileContaining({40.6892, -74.0445}, 12), (TileId{12, 1205, 1540}));
  // Default zoom is the storage zoom.
  EXPECT_EQ(TileContaining({48.8584, 2.2945}), (TileId{kStorageZoom, 33185, 22545}));
}

TEST(TileContaining, MatchesTheReferenceFormulaAwayFromTileEdges) {
  int compared = 0;
  for (double lat = -84.0; lat <= 84.0; lat += 7.3) {
    for (double lon = -179.0; lon <= 179.0; lon += 11.7) {
      for (int z : {3, 10, 16, 20}) {
        const TileId expected = ReferenceTile(lat, lon, z);
        EXPECT_EQ(TileContaining({lat, lon}, z), expected) << lat << " " << lon << " z" << z;
        ++compared;
      }
    }
  }
  EXPECT_GT(compared, 1000);
}

TEST(TileBounds, ContainThePointTheTileCameFrom) {
  for (const LatLon p : {LatLon{48.7128, 2.17}, LatLon{-33.86, 151.21}, LatLon{0.0001, -0.0001}, LatLon{84.9, 179.9},
                         LatLon{-84.9, -179.9}}) {
    for (int z : {0, 5, 16, 22}) {
      const TileId t = TileContaining(p, z);
      const BoundingBox b = TileBounds(t);
      EXPECT_TRUE(Contains(b, p)) << p.lat_deg << " " << p.lon_deg << " z" << z;
      EXPECT_NEAR(b.max_lon_deg - b.min_lon_deg, 360.0 / std::pow(2.0, z), 1e-9);
      EXPECT_LT(b.min_lat_deg, b.max_lat_deg);
    }
  }
}

TEST(TileBounds, GivesTheWholeMercatorWorldAtZoomZeroAndSharedEdgesBetweenNeighbours) {
  const BoundingBox world = TileBounds({0, 0, 0});
  EXPECT_NEAR(world.min_lon_deg, -180.0, 1e-12);
  EXPECT_NEAR(world.max_lon_deg, 180.0, 1e-12);
  EXPECT_NEAR(world.max_lat_deg, kMaxMercatorLatDeg, 1e-9);
  EXPECT_NEAR(world.min_lat_deg, -kMaxMercatorLatDeg, 1e-9);
  const BoundingBox north_west = TileBounds({1, 0, 0});
  EXPECT_NEAR(north_west.min_lat_deg, 0.0, 1e-12);
  EXPECT_NEAR(north_west.max_lon_deg, 0.0, 1e-12);
  const TileId t{16, 33185, 22545};
  EXPECT_DOUBLE_EQ(TileBounds(t).max_lon_deg, TileBounds({16, t.x + 1, t.y}).min_lon_deg);
  EXPECT_DOUBLE_EQ(TileBounds(t).min_lat_deg, TileBounds({16, t.x, t.y + 1}).max_lat_deg);
}

TEST(IsValidTile, AcceptsExactlyTheExistingAddresses) {
  EXPECT_TRUE(IsValidTile({0, 0, 0}));
  EXPECT_FALSE(IsValidTile({0, 1, 0}));
  EXPECT_FALSE(IsValidTile({0, 0, 1}));
  EXPECT_TRUE(IsValidTile({16, 0, 65535}));
  EXPECT_TRUE(IsValidTile({16, 65535, 65535}));
  EXPECT_FALSE(IsValidTile({16, 65536, 0}));
  EXPECT_FALSE(IsValidTile({16, 0, 65536}));
  EXPECT_FALSE(IsValidTile({16, -1, 0}));
  EXPECT_FALSE(IsValidTile({16, 0, -1}));
  EXPECT_FALSE(IsValidTile({-1, 0, 0}));
  EXPECT_TRUE(IsValidTile({30, (1 << 30) - 1, (1 << 30) - 1}));
  EXPECT_FALSE(IsValidTile({31, 0, 0}));
}

TEST(TileContaining, ClampsPolesAndTheAntimeridianIntoValidTiles) {
  const int last = (1 << 16) - 1;
  for (double lat : {kMaxMercatorLatDeg, 85.1, 89.9, 90.0}) {
    const TileId t = TileContaining({lat, 0.0}, 16);
    EXPECT_EQ(t.y, 0) << lat;
    EXPECT_TRUE(IsValidTile(t));
  }
  for (double lat : {-kMaxMercatorLatDeg, -85.1, -89.9, -90.0}) {
    const TileId t = TileContaining({lat, 0.0}, 16);
    EXPECT_EQ(t.y, last) << lat;
    EXPECT_TRUE(IsValidTile(t));
  }
  EXPECT_EQ(TileContaining({0.0, 180.0}, 16).x, last);
  EXPECT_EQ(TileContaining({0.0, -180.0}, 16).x, 0);
  EXPECT_TRUE(IsValidTile(TileContaining({90.0, 180.0}, 16)));
}

}  // namespace
}  // namespace crowdmap
