#include "core/localization/tile_window.h"

#include <algorithm>

namespace crowdmap {

TileWindow::Change TileWindow::MoveTo(const LatLon& position) {
  Change change;
  const TileId centre = TileContaining(position, kStorageZoom);
  if (placed_ && centre == centre_) return change;
  std::vector<TileId> tiles;
  for (int dy = -radius_; dy <= radius_; ++dy) {
    for (int dx = -radius_; dx <= radius_; ++dx) {
      const TileId t{kStorageZoom, centre.x + dx, centre.y + dy};
      if (IsValidTile(t)) tiles.push_back(t);
    }
  }
  auto contains = [](const std::vector<TileId>& v, const TileId& t) { return std::find(v.begin(), v.end(), t) != v.end(); };
  for (const TileId& t : tiles) {
    if (!contains(tiles_, t)) change.enter.push_back(t);
  }
  for (const TileId& t : tiles_) {
    if (!contains(tiles, t)) change.leave.push_back(t);
  }
  tiles_ = std::move(tiles);
  centre_ = centre;
  placed_ = true;
  return change;
}

}  // namespace crowdmap
