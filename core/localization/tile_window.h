#ifndef CROWDMAP_CORE_LOCALIZATION_TILE_WINDOW_H_
#define CROWDMAP_CORE_LOCALIZATION_TILE_WINDOW_H_

#include <vector>

#include "core/geo/tiles.h"

namespace crowdmap {

// The storage-zoom tiles a vehicle holds around its position: the (2 radius + 1)^2 square centred
// on the tile it is in. MoveTo says which tiles enter and which leave when the vehicle moves.
class TileWindow {
 public:
  explicit TileWindow(int radius) : radius_(radius) {}

  struct Change {
    std::vector<TileId> enter;
    std::vector<TileId> leave;
  };
  Change MoveTo(const LatLon& position);

  const std::vector<TileId>& tiles() const { return tiles_; }

 private:
  int radius_;
  bool placed_ = false;
  TileId centre_;
  std::vector<TileId> tiles_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOCALIZATION_TILE_WINDOW_H_
