// MapService::LocalizePassage: a passage localised against the map, read-only.
#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include "absl/strings/str_cat.h"
#include "core/estimation/vehicle_calibration.h"
#include "core/localization/passage_localizer.h"
#include "server/map_service.h"
#include "server/request_log.h"

namespace crowdmap {
namespace {

// Map landmarks are read in the passage's GNSS bounding box widened by this much: GNSS errors of
// tens of metres plus the camera's range.
constexpr double kLocalizationMarginM = 300.0;
constexpr double kMetresPerDegreeLat = 111320.0;

BoundingBox PassageBox(const Passage& passage) {
  BoundingBox box{90.0, 180.0, -90.0, -180.0};
  for (const GnssFix& f : passage.gnss) {
    box.min_lat_deg = std::min(box.min_lat_deg, f.lat_deg);
    box.max_lat_deg = std::max(box.max_lat_deg, f.lat_deg);
    box.min_lon_deg = std::min(box.min_lon_deg, f.lon_deg);
    box.max_lon_deg = std::max(box.max_lon_deg, f.lon_deg);
  }
  const double dlat = kLocalizationMarginM / kMetresPerDegreeLat;
  const double cos_lat = std::max(0.01, std::cos(std::max(std::abs(box.min_lat_deg), std::abs(box.max_lat_deg)) * M_PI / 180.0));
  const double dlon = dlat / cos_lat;
  box.min_lat_deg = std::max(-90.0, box.min_lat_deg - dlat);
  box.max_lat_deg = std::min(90.0, box.max_lat_deg + dlat);
  box.min_lon_deg = std::max(-180.0, box.min_lon_deg - dlon);
  box.max_lon_deg = std::min(180.0, box.max_lon_deg + dlon);
  return box;
}

// The page's landmarks that the passage detects, with their joint covariance from the page's
// marginals and cross blocks (all read at the page's map version).
LocalizationMap LocalizationMapFromPage(const Passage& passage, const LandmarkPage& page) {
  std::unordered_set<LandmarkId> detected;
  for (const Detection& d : passage.detections) detected.insert(d.landmark_id);
  LocalizationMap map;
  map.version = page.map_version;
  std::unordered_map<LandmarkId, int> index;
  for (const Landmark& l : page.landmarks) {
    if (!detected.count(l.id)) continue;
    index[l.id] = static_cast<int>(map.ids.size());
    map.ids.push_back(l.id);
    map.positions.push_back(l.position);
  }
  const int n = static_cast<int>(map.ids.size());
  map.cov_en_m2 = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  for (const Landmark& l : page.landmarks) {
    const auto it = index.find(l.id);
    if (it != index.end()) map.cov_en_m2.block<2, 2>(2 * it->second, 2 * it->second) = l.cov_en_m2;
  }
  for (const auto& [pair, block] : page.cross) {
    const auto a = index.find(pair.first), b = index.find(pair.second);
    if (a == index.end() || b == index.end()) continue;
    map.cov_en_m2.block<2, 2>(2 * a->second, 2 * b->second) = block;
    map.cov_en_m2.block<2, 2>(2 * b->second, 2 * a->second) = block.transpose();
  }
  return map;
}

}  // namespace

grpc::Status MapService::LocalizePassage(grpc::ServerContext* ctx, const pb::LocalizePassageRequest* request,
                                         pb::LocalizePassageResponse* response) {
  RequestLog log("LocalizePassage", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log); !who.ok()) return log.Done(who.status());
  absl::StatusOr<Passage> passage = PassageFromProto(request->passage());
  if (!passage.ok()) return log.Done(passage.status());
  log.Add(absl::StrCat("vehicle=", passage->vehicle_id, " passage=", passage->passage_id));
  absl::StatusOr<LandmarkPage> page =
      context_->store->QueryRegion(PassageBox(*passage), /*after_id=*/0, /*limit=*/0, /*include_cross=*/true);
  if (!page.ok()) return log.Done(page.status());
  // The vehicle's camera yaw as its uploads estimated it, when they did.
  double camera_yaw_offset_rad = 0.0;
  if (absl::StatusOr<VehicleCalibration> vehicle = context_->store->GetVehicle(passage->vehicle_id); vehicle.ok()) {
    camera_yaw_offset_rad = vehicle->camera_yaw_offset_rad;
    *passage = WithVehicleCameraYaw(*passage, *vehicle);
  } else if (!absl::IsNotFound(vehicle.status())) {
    return log.Done(vehicle.status());
  }
  absl::StatusOr<PassageLocalization> result = crowdmap::LocalizePassage(*passage, LocalizationMapFromPage(*passage, *page));
  if (!result.ok()) return log.Done(result.status());
  PassageLocalizationToProto(*result, response);
  response->set_camera_yaw_offset_rad(camera_yaw_offset_rad);
  log.Add(result->Brief());
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
