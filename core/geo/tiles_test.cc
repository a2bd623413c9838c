#include "core/geo/tiles.h"

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(Tiles, KnownTilesAtLowZoom) {
  EXPECT_TRUE((TileContaining({10.0, 10.0}, 1) == TileId{1, 1, 0}));
  EXPECT_TRUE((TileContaining({-10.0, -10.0}, 1) == TileId{1, 0, 1}));
  // Standard slippy-map example: z16 tile of a point in Paris.
  const TileId t = TileContaining({48.8584, 2.2945}, 16);
  EXPECT_EQ(t.x, 33185);
  EXPECT_EQ(t.y, 22545);
}

TEST(Tiles, BoundsContainThePointTheTileCameFrom) {
  for (const LatLon p : {LatLon{48.7128, 2.17}, LatLon{-33.86, 151.21}, LatLon{0.0001, -0.0001}}) {
    const BoundingBox b = TileBounds(TileContaining(p));
    EXPECT_LE(b.min_lat_deg, p.lat_deg);
    EXPECT_GE(b.max_lat_deg, p.lat_deg);
    EXPECT_LE(b.min_lon_deg, p.lon_deg);
    EXPECT_GE(b.max_lon_deg, p.lon_deg);
    EXPECT_LT(b.max_lon_deg - b.min_lon_deg, 0.006);  // z16: 360 / 65536 degrees
  }
}

TEST(Tiles, ValidityAndPolarClamping) {
  EXPECT_TRUE(IsValidTile({16, 0, 65535}));
  EXPECT_FALSE(IsValidTile({16, 65536, 0}));
  EXPECT_FALSE(IsValidTile({16, -1, 0}));
  EXPECT_FALSE(IsValidTile({31, 0, 0}));
  EXPECT_EQ(TileContaining({89.9, 0.0}, 16).y, 0);
  EXPECT_EQ(TileContaining({-89.9, 0.0}, 16).y, 65535);
  EXPECT_EQ(TileContaining({0.0, 180.0}, 16).x, 65535);
}

}  // namespace
}  // namespace crowdmap
