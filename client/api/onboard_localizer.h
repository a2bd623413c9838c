#ifndef CROWDMAP_CLIENT_API_ONBOARD_LOCALIZER_H_
#define CROWDMAP_CLIENT_API_ONBOARD_LOCALIZER_H_

#include <map>
#include <memory>
#include <tuple>
#include <vector>

#include "absl/status/statusor.h"
#include "client/api/map_client.h"
#include "core/localization/streaming_localizer.h"
#include "core/localization/tile_window.h"

namespace crowdmap {

struct OnboardLocalizerOptions {
  // Tiles held around the vehicle: the (2 tile_radius + 1)^2 storage-zoom tiles (about 400 m each)
  // centred on its tile. Tiles that leave the window stay cached but leave the filter.
  int tile_radius = 1;
  StreamingLocalizerOptions filter;

  absl::Status Validate() const;
};

// The on-vehicle localizer: a StreamingLocalizer fed with the map tiles around the vehicle. Each
// tile is downloaded once (GetTile with the cross-covariances among its landmarks) and cached; a
// download happens, inside the update that needs it, when the vehicle's tile changes and a tile of
// the window is not cached yet. A tile that cannot be downloaded does not stop the localisation:
// the filter goes on with the tiles it holds (last_download_error() says why), and the tile is
// tried again when the window next moves. Landmarks of different tiles are taken as independent (GetTile
// carries only the blocks within a tile). Not thread-safe; `client` must outlive it.
class OnboardLocalizer {
 public:
  static absl::StatusOr<std::unique_ptr<OnboardLocalizer>> Create(MapClient* client, const Calibration& calibration,
                                                                  const NoiseModel& noise,
                                                                  const OnboardLocalizerOptions& options = {});

  absl::StatusOr<StreamingUpdate> AddOdometry(const OdometrySample& sample);
  absl::StatusOr<StreamingUpdate> AddGnss(const GnssFix& fix);
  // The detections of one camera frame (all at one time).
  absl::StatusOr<StreamingUpdate> AddDetections(const std::vector<Detection>& frame);

  int tiles_downloaded() const { return tiles_downloaded_; }
  int tiles_missing() const { return static_cast<int>(missing_.size()); }  // in the window, not downloaded
  const absl::Status& last_download_error() const { return last_download_error_; }
  int64_t map_version() const { return map_version_; }  // highest version among the tiles read
  const StreamingLocalizer& filter() const { return *filter_; }

 private:
  OnboardLocalizer(MapClient* client, std::unique_ptr<StreamingLocalizer> filter, const OnboardLocalizerOptions& options);

  // Moves the tile window to `position`: downloads what is missing, updates the filter's landmarks.
  absl::Status FollowVehicle(const LatLon& position);
  absl::Status Enter(const TileId& tile);
  absl::StatusOr<const LocalizationMap*> Tile(const TileId& tile);

  MapClient* client_;
  std::unique_ptr<StreamingLocalizer> filter_;
  OnboardLocalizerOptions options_;
  TileWindow window_;
  std::map<std::tuple<int, int, int>, LocalizationMap> cache_;
  std::vector<TileId> missing_;
  absl::Status last_download_error_;
  int tiles_downloaded_ = 0;
  int64_t map_version_ = 0;
};

// A GetTile response as the landmarks it holds with their joint covariance (East/North at each),
// packed or as blocks; InvalidArgument naming the field when the covariance does not fit the
// landmarks.
absl::StatusOr<LocalizationMap> LocalizationMapFromTile(const pb::GetTileResponse& tile);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_API_ONBOARD_LOCALIZER_H_
