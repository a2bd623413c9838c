// MapService handlers that read the vehicles' estimated camera calibrations.
#include "absl/strings/str_cat.h"
#include "server/map_service.h"
#include "server/request_log.h"

namespace crowdmap {

grpc::Status MapService::GetVehicle(grpc::ServerContext* ctx, const pb::GetVehicleRequest* request,
                                    pb::Vehicle* response) {
  RequestLog log("GetVehicle", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadPassages, &log);
  if (!who.ok()) return log.Done(who.status());
  if (request->vehicle_id().empty()) return log.Done(absl::InvalidArgumentError("vehicle_id: required"));
  log.Add(absl::StrCat("vehicle=", request->vehicle_id()));
  // What a vehicle's camera does is its own business: a vehicle reads only its own.
  if (!who->MayReadAllPassages()) {
    if (absl::Status s = who->MayActFor(request->vehicle_id()); !s.ok()) return log.Done(s);
  }
  absl::StatusOr<VehicleCalibration> vehicle = context_->store->GetVehicle(request->vehicle_id());
  if (!vehicle.ok()) return log.Done(vehicle.status());
  VehicleToProto(*vehicle, response);
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::ListVehicles(grpc::ServerContext* ctx, const pb::ListVehiclesRequest* request,
                                      pb::ListVehiclesResponse* response) {
  RequestLog log("ListVehicles", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadPassages, &log);
  if (!who.ok()) return log.Done(who.status());
  if (!who->MayReadAllPassages()) {
    return log.Done(absl::PermissionDeniedError(absl::StrCat(
        "role vehicle: lists no other vehicles; GetVehicle with vehicle_id '", who->name, "' reads its own")));
  }
  absl::StatusOr<std::vector<VehicleCalibration>> vehicles = context_->store->ListVehicles();
  if (!vehicles.ok()) return log.Done(vehicles.status());
  for (const VehicleCalibration& v : *vehicles) VehicleToProto(v, response->add_vehicles());
  log.Add(absl::StrCat("vehicles=", vehicles->size()));
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
