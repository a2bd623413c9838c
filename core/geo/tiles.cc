#include "core/geo/tiles.h"

#include <algorithm>
#include <cmath>

namespace crowdmap {
namespace {

double TileXToLon(double x, int z) { return x / std::ldexp(1.0, z) * 360.0 - 180.0; }

double TileYToLat(double y, int z) {
  const double n = M_PI - 2.0 * M_PI * y / std::ldexp(1.0, z);
  return 180.0 / M_PI * std::atan(std::sinh(n));
}

}  // namespace

TileId TileContaining(const LatLon& p, int z) {
  const double n = std::ldexp(1.0, z);
  const double lat = std::clamp(p.lat_deg, -kMaxMercatorLatDeg, kMaxMercatorLatDeg) * M_PI / 180.0;
  const double fx = (p.lon_deg + 180.0) / 360.0 * n;
  const double fy = (1.0 - std::asinh(std::tan(lat)) / M_PI) / 2.0 * n;
  const int max_index = static_cast<int>(n) - 1;
  return {z, std::clamp(static_cast<int>(std::floor(fx)), 0, max_index),
          std::clamp(static_cast<int>(std::floor(fy)), 0, max_index)};
}

BoundingBox TileBounds(const TileId& t) {
  BoundingBox b;
  b.min_lon_deg = TileXToLon(t.x, t.z);
  b.max_lon_deg = TileXToLon(t.x + 1, t.z);
  b.max_lat_deg = TileYToLat(t.y, t.z);
  b.min_lat_deg = TileYToLat(t.y + 1, t.z);
  return b;
}

bool IsValidTile(const TileId& t) {
  if (t.z < 0 || t.z > 30) return false;
  const long n = 1L << t.z;
  return t.x >= 0 && t.x < n && t.y >= 0 && t.y < n;
}

}  // namespace crowdmap
