#include "client/api/onboard_localizer.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"
#include "server/wire_convert.h"

namespace crowdmap {

absl::Status OnboardLocalizerOptions::Validate() const {
  if (tile_radius < 0 || tile_radius > 5) return absl::InvalidArgumentError("tile_radius: must lie in [0, 5]");
  return filter.Validate();
}

absl::StatusOr<LocalizationMap> LocalizationMapFromTile(const pb::GetTileResponse& tile) {
  LocalizationMap map;
  map.version = tile.map_version();
  for (const pb::Landmark& wire : tile.landmarks()) {
    map.ids.push_back(wire.id());
    map.positions.push_back({wire.lat_deg(), wire.lon_deg()});
  }
  absl::StatusOr<Eigen::MatrixXd> cov = CovarianceFromProto(tile);
  if (!cov.ok()) return cov.status();
  map.cov_en_m2 = *std::move(cov);
  return map;
}

OnboardLocalizer::OnboardLocalizer(MapClient* client, std::unique_ptr<StreamingLocalizer> filter,
                                   const OnboardLocalizerOptions& options)
    : client_(client), filter_(std::move(filter)), options_(options), window_(options.tile_radius) {}

absl::StatusOr<std::unique_ptr<OnboardLocalizer>> OnboardLocalizer::Create(MapClient* client,
                                                                          const Calibration& calibration,
                                                                          const NoiseModel& noise,
                                                                          const OnboardLocalizerOptions& options) {
  if (client == nullptr) return absl::InvalidArgumentError("client: required");
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<std::unique_ptr<StreamingLocalizer>> filter =
      StreamingLocalizer::Create(calibration, noise, options.filter);
  if (!filter.ok()) return filter.status();
  return std::unique_ptr<OnboardLocalizer>(new OnboardLocalizer(client, std::move(*filter), options));
}

absl::StatusOr<const LocalizationMap*> OnboardLocalizer::Tile(const TileId& tile) {
  const auto key = std::make_tuple(tile.z, tile.x, tile.y);
  auto it = cache_.find(key);
  if (it != cache_.end()) return &it->second;
  absl::StatusOr<pb::GetTileResponse> response = client_->GetTile(tile.z, tile.x, tile.y, /*include_cross=*/true);
  if (!response.ok()) {
    return absl::Status(response.status().code(),
                        absl::StrCat("GetTile ", tile.z, "/", tile.x, "/", tile.y, ": ", response.status().message()));
  }
  absl::StatusOr<LocalizationMap> map = LocalizationMapFromTile(*response);
  if (!map.ok()) {
    return absl::DataLossError(
        absl::StrCat("GetTile ", tile.z, "/", tile.x, "/", tile.y, ": ", map.status().message()));
  }
  ++tiles_downloaded_;
  map_version_ = std::max(map_version_, response->map_version());
  return &cache_.emplace(key, *std::move(map)).first->second;
}

absl::Status OnboardLocalizer::Enter(const TileId& tile) {
  absl::StatusOr<const LocalizationMap*> map = Tile(tile);
  if (!map.ok()) {
    last_download_error_ = map.status();
    missing_.push_back(tile);
    return absl::OkStatus();
  }
  return filter_->AddMapLandmarks(**map);
}

absl::Status OnboardLocalizer::FollowVehicle(const LatLon& position) {
  const TileWindow::Change change = window_.MoveTo(position);
  if (change.enter.empty() && change.leave.empty()) return absl::OkStatus();
  for (const TileId& t : change.leave) {
    const auto it = cache_.find(std::make_tuple(t.z, t.x, t.y));
    if (it != cache_.end()) filter_->RemoveMapLandmarks(it->second.ids);
  }
  std::vector<TileId> retry;
  for (const TileId& t : missing_) {
    if (std::find(window_.tiles().begin(), window_.tiles().end(), t) != window_.tiles().end() &&
        std::find(change.enter.begin(), change.enter.end(), t) == change.enter.end()) {
      retry.push_back(t);
    }
  }
  missing_.clear();
  for (const TileId& t : retry) {
    if (absl::Status s = Enter(t); !s.ok()) return s;
  }
  for (const TileId& t : change.enter) {
    if (absl::Status s = Enter(t); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::StatusOr<StreamingUpdate> OnboardLocalizer::AddOdometry(const OdometrySample& sample) {
  return filter_->AddOdometry(sample);
}

absl::StatusOr<StreamingUpdate> OnboardLocalizer::AddGnss(const GnssFix& fix) {
  // Before the filter tracks, the fixes place the window.
  if (!filter_->tracking()) {
    if (absl::Status s = FollowVehicle({fix.lat_deg, fix.lon_deg}); !s.ok()) return s;
  }
  absl::StatusOr<StreamingUpdate> update = filter_->AddGnss(fix);
  if (update.ok() && update->tracking) {
    if (absl::Status s = FollowVehicle(update->pose.position); !s.ok()) return s;
  }
  return update;
}

absl::StatusOr<StreamingUpdate> OnboardLocalizer::AddDetections(const std::vector<Detection>& frame) {
  absl::StatusOr<StreamingUpdate> update = filter_->AddDetections(frame);
  if (update.ok() && update->tracking) {
    if (absl::Status s = FollowVehicle(update->pose.position); !s.ok()) return s;
  }
  return update;
}

}  // namespace crowdmap
