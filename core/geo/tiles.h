#ifndef CROWDMAP_CORE_GEO_TILES_H_
#define CROWDMAP_CORE_GEO_TILES_H_

#include "core/geo/local_frame.h"

namespace crowdmap {

// XYZ ("slippy map") Web-Mercator tile address.
struct TileId {
  int z = 0;
  int x = 0;
  int y = 0;
  bool operator==(const TileId& o) const { return z == o.z && x == o.x && y == o.y; }
};

// Storage zoom: a landmark lives in the z16 tile that contains it (about 400 m at mid latitudes).
constexpr int kStorageZoom = 16;
// Web-Mercator is defined up to this latitude.
constexpr double kMaxMercatorLatDeg = 85.05112877980659;

struct BoundingBox {
  double min_lat_deg = 0.0;
  double min_lon_deg = 0.0;
  double max_lat_deg = 0.0;
  double max_lon_deg = 0.0;
};

// The tile at zoom z containing p (latitude clamped to the Mercator range).
TileId TileContaining(const LatLon& p, int z = kStorageZoom);

// The tile's extent in WGS84 degrees.
BoundingBox TileBounds(const TileId& tile);

// True when z, x, y address an existing tile.
bool IsValidTile(const TileId& tile);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_GEO_TILES_H_
