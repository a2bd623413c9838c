#ifndef CROWDMAP_SERVER_WIRE_CONVERT_H_
#define CROWDMAP_SERVER_WIRE_CONVERT_H_

// The one place where wire messages (mapservice.v1) and core/storage types meet.

#include <cstddef>

#include "absl/status/statusor.h"
#include "core/localization/passage_localizer.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"
#include "mapservice/v1/map.pb.h"
#include "mapservice/v1/map_service.pb.h"
#include "mapservice/v1/passage.pb.h"
#include "server/storage/map_store.h"

namespace crowdmap {

namespace pb = ::mapservice::v1;

// Limits applied to uploads before anything is stored.
struct WireLimits {
  size_t max_passage_bytes = 64u << 20;

  absl::Status Validate() const;
};

// InvalidArgument naming "passage" when a serialized passage of `bytes` exceeds the limit.
absl::Status CheckPassageSize(size_t bytes, const WireLimits& limits);

// Converts and validates an uploaded passage: wire-level checks (required messages present),
// then the core's ValidatePassage, so field names read the same on both sides
// ("gnss[3].lat_deg: ..."). InvalidArgument on any malformed input.
absl::StatusOr<Passage> PassageFromProto(const pb::Passage& wire);
void PassageToProto(const Passage& passage, pb::Passage* wire);

void LandmarkToProto(const Landmark& landmark, pb::Landmark* wire);
Landmark LandmarkFromProto(const pb::Landmark& wire);
// The wire carries the yaw offset's standard deviation, the store its variance.
void VehicleToProto(const VehicleCalibration& vehicle, pb::Vehicle* wire);
VehicleCalibration VehicleFromProto(const pb::Vehicle& wire);
void CrossToProto(const LandmarkPair& pair, const Eigen::Matrix2d& block, pb::CrossCovariance* wire);

void StoredPassageToProto(const StoredPassage& record, pb::PassageStatus* wire);
pb::PassageState PassageStateToProto(PassageState state);
// nullopt for UNSPECIFIED; InvalidArgument for values outside the enum.
absl::StatusOr<std::optional<PassageState>> PassageStateFromProto(pb::PassageState state);

// Poses in WGS84 with heading and covariance at the pose, the landmarks used, the rejections.
void PassageLocalizationToProto(const PassageLocalization& localization, pb::LocalizePassageResponse* wire);

absl::StatusOr<BoundingBox> BoundingBoxFromProto(const pb::BoundingBox& wire, const char* field);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_WIRE_CONVERT_H_
