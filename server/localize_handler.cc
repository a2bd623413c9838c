// MapService::LocalizePassage: a passage localised against the map, read-only.
#include <algorithm>
#include <cmath>
#include <memory>
#include <optional>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/estimation/vehicle_calibration.h"
#include "core/localization/passage_localizer.h"
#include "server/map_service.h"
#include "server/quotas.h"
#include "server/request_log.h"

namespace crowdmap {
namespace {

// The page's landmarks with their joint covariance (read with it, at the page's map version).
LocalizationMap LocalizationMapFromPage(const LandmarkPage& page) {
  LocalizationMap map;
  map.version = page.map_version;
  for (const Landmark& l : page.landmarks) {
    map.ids.push_back(l.id);
    map.positions.push_back(l.position);
  }
  map.cov_en_m2 = page.landmarks.empty() ? Eigen::MatrixXd(0, 0) : page.covariance;
  return map;
}

}  // namespace

// Distinct landmarks one LocalizePassage may name (as many as a page of a region read with
// covariances).
constexpr size_t kMaxLocalizedLandmarks = 2000;

grpc::Status MapService::LocalizePassage(grpc::ServerContext* ctx, const pb::LocalizePassageRequest* request,
                                         pb::LocalizePassageResponse* response) {
  RequestLog log("LocalizePassage", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log);
  if (!who.ok()) return log.Done(who.status());
  absl::StatusOr<Passage> passage = PassageFromProto(request->passage());
  if (!passage.ok()) return log.Done(passage.status());
  log.Add(absl::StrCat("vehicle=", passage->vehicle_id, " passage=", passage->passage_id));
  // The vehicle's camera calibration is used and returned: a vehicle localises only its own
  // passages (as GetVehicle reads only its own record).
  if (!who->MayReadAllPassages()) {
    if (absl::Status s = who->MayActFor(passage->vehicle_id); !s.ok()) return log.Done(s);
  }
  // The map landmarks the passage detects, with their joint covariance (the store takes each once).
  std::vector<LandmarkId> detected;
  detected.reserve(passage->detections.size());
  for (const Detection& d : passage->detections) detected.push_back(d.landmark_id);
  std::sort(detected.begin(), detected.end());
  detected.erase(std::unique(detected.begin(), detected.end()), detected.end());
  if (detected.size() > kMaxLocalizedLandmarks) {
    return log.Done(absl::InvalidArgumentError(
        absl::StrCat("passage.detections: ", detected.size(), " distinct landmarks, at most ", kMaxLocalizedLandmarks,
                     " (their joint covariance is read whole): localise the drive in parts")));
  }
  // Their joint covariance is read as a read with covariances reads it (2,000 landmarks: 128 MB),
  // so the localisation takes a place among those, held until it is answered.
  absl::StatusOr<std::unique_ptr<ConcurrentCalls::Lease>> place = std::unique_ptr<ConcurrentCalls::Lease>();
  if (context_->covariance_reads != nullptr) place = context_->covariance_reads->Enter();
  if (!place.ok()) {
    AddRetryTrailers(place.status(), ctx);
    return log.Done(place.status());
  }
  absl::StatusOr<LandmarkPage> page = context_->store->GetLandmarks(detected, /*include_cross=*/true);
  if (!page.ok()) return log.Done(page.status());
  // The vehicle's camera yaw prior as the map update takes it (VehicleCameraYawPrior, over the
  // store's records): its record; for a vehicle never seen, the fleet's prior when the fleet is
  // large enough, else mean 0 with the map update's prior sigma.
  absl::StatusOr<VehicleCalibration> vehicle = context_->store->GetVehicle(passage->vehicle_id);
  if (absl::IsNotFound(vehicle.status())) {
    std::optional<VehicleCalibration> fleet_prior;
    if (context_->update.fleet_camera_yaw_prior_vehicles > 0) {
      absl::StatusOr<std::vector<VehicleCalibration>> fleet = context_->store->ListVehicles();
      if (!fleet.ok()) return log.Done(fleet.status());
      fleet_prior = FleetCameraYawPrior(*fleet, passage->vehicle_id, context_->update.fleet_camera_yaw_prior_vehicles,
                                        context_->update.camera_yaw_prior_sigma_rad);
    }
    vehicle = fleet_prior ? *std::move(fleet_prior)
                          : NewVehicleCalibration(passage->vehicle_id, context_->update.camera_yaw_prior_sigma_rad);
  }
  if (!vehicle.ok()) return log.Done(vehicle.status());
  const double camera_yaw_offset_rad = vehicle->camera_yaw_offset_rad;
  *passage = WithVehicleCameraYaw(*passage, *vehicle);
  // The offset is estimated again in the localisation, the prior's uncertainty its own.
  PassageLocalizerOptions options;
  options.camera_yaw_sigma_rad = std::sqrt(vehicle->camera_yaw_variance_rad2);
  options.correlated_gnss_min_lag1 = context_->update.correlated_gnss_min_lag1;
  absl::StatusOr<PassageLocalization> result =
      crowdmap::LocalizePassage(*passage, LocalizationMapFromPage(*page), options);
  if (!result.ok()) return log.Done(result.status());
  PassageLocalizationToProto(*result, response);
  response->set_camera_yaw_offset_rad(camera_yaw_offset_rad);
  if (result->camera_yaw_sigma_rad > 0.0) {
    response->set_camera_yaw_estimate_rad(camera_yaw_offset_rad + result->camera_yaw_offset_rad);
    response->set_camera_yaw_estimate_sigma_rad(result->camera_yaw_sigma_rad);
  }
  log.Add(result->Brief());
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
