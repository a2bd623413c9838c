// MapService handlers that read the vehicles' estimated camera calibrations.
#include "absl/strings/str_cat.h"
#include "core/model/passage.h"
#include "server/map_service.h"
#include "server/request_log.h"

namespace crowdmap {
namespace {

constexpr int kDefaultVehiclePage = 100;
constexpr int kMaxVehiclePage = 1000;

}  // namespace

grpc::Status MapService::GetVehicle(grpc::ServerContext* ctx, const pb::GetVehicleRequest* request,
                                    pb::Vehicle* response) {
  RequestLog log("GetVehicle", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadPassages, &log);
  if (!who.ok()) return log.Done(who.status());
  if (absl::Status s = ValidateId("vehicle_id", request->vehicle_id()); !s.ok()) return log.Done(s);
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
  if (request->page_size() < 0 || request->page_size() > kMaxVehiclePage) {
    return log.Done(absl::InvalidArgumentError(absl::StrCat("page_size: must lie in [0, ", kMaxVehiclePage, "]")));
  }
  constexpr char kQuery[] = "vehicles";
  absl::StatusOr<std::string> after = ParseKeyPageToken(request->page_token(), kQuery);
  if (!after.ok()) return log.Done(after.status());
  const int limit = request->page_size() == 0 ? kDefaultVehiclePage : request->page_size();
  // One more than asked: whether another page follows.
  absl::StatusOr<std::vector<VehicleCalibration>> vehicles = context_->store->ListVehicles(*after, limit + 1);
  if (!vehicles.ok()) return log.Done(vehicles.status());
  const bool more = static_cast<int>(vehicles->size()) > limit;
  if (more) vehicles->resize(limit);
  for (const VehicleCalibration& v : *vehicles) VehicleToProto(v, response->add_vehicles());
  if (more) response->set_next_page_token(MakeKeyPageToken(vehicles->back().vehicle_id, kQuery));
  log.Add(absl::StrCat("vehicles=", vehicles->size(), " more=", more ? "true" : "false"));
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
