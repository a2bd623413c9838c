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

// The covariance layout a read asked for: BLOCKS for UNSPECIFIED. InvalidArgument naming `field`
// for a value outside the enum, or for a layout asked without the covariance (`include_cross`).
absl::StatusOr<pb::CovarianceFormat> CovarianceFormatFromProto(int format, bool include_cross, const char* field);
// The joint covariance of a page's landmarks (LandmarkPage::covariance) on the wire: one block per
// pair, the smaller id first, or the packed upper triangle.
void CovarianceToBlocks(const LandmarkPage& page, google::protobuf::RepeatedPtrField<pb::CrossCovariance>* wire);
void CovarianceToPacked(const Eigen::MatrixXd& covariance, pb::PackedCovariance* wire);
// The matrix of a PackedCovariance of `landmarks` landmarks; InvalidArgument naming `field` when
// its size does not match.
absl::StatusOr<Eigen::MatrixXd> CovarianceFromPacked(const pb::PackedCovariance& wire, int landmarks,
                                                     const char* field);
// The same matrix from a landmark's own 2x2 covariances and the blocks between them (as a server
// without the packed layout sends them); InvalidArgument naming `field` for a block of a landmark
// not in `landmarks`. Pairs without a block are uncorrelated.
absl::StatusOr<Eigen::MatrixXd> CovarianceFromBlocks(const google::protobuf::RepeatedPtrField<pb::Landmark>& landmarks,
                                                     const google::protobuf::RepeatedPtrField<pb::CrossCovariance>& blocks,
                                                     const char* field);
// The joint covariance a GetTileResponse or QueryRegionResponse carries (asked with
// include_cross_covariance): packed, or from the blocks of a server without the packed layout.
template <typename Response>
absl::StatusOr<Eigen::MatrixXd> CovarianceFromProto(const Response& response) {
  return response.has_packed_covariance()
             ? CovarianceFromPacked(response.packed_covariance(), response.landmarks_size(), "packed_covariance")
             : CovarianceFromBlocks(response.landmarks(), response.cross_covariances(), "cross_covariances");
}
pb::CovarianceBound CovarianceBoundToProto(CovarianceBound bound);
// A page of landmarks into a GetTileResponse or QueryRegionResponse, with its covariance (if read)
// in `format` and how it relates to the exact one.
template <typename Response>
void LandmarkPageToProto(const LandmarkPage& page, pb::CovarianceFormat format, Response* response) {
  response->mutable_landmarks()->Reserve(static_cast<int>(page.landmarks.size()));
  for (const Landmark& l : page.landmarks) LandmarkToProto(l, response->add_landmarks());
  if (page.covariance.size() == 0) return;
  response->set_covariance_bound(CovarianceBoundToProto(page.covariance_bound));
  if (format == pb::COVARIANCE_FORMAT_PACKED) {
    CovarianceToPacked(page.covariance, response->mutable_packed_covariance());
  } else {
    CovarianceToBlocks(page, response->mutable_cross_covariances());
  }
}

void StoredPassageToProto(const StoredPassage& record, pb::PassageStatus* wire);
pb::PassageState PassageStateToProto(PassageState state);
// nullopt for UNSPECIFIED; InvalidArgument for values outside the enum.
absl::StatusOr<std::optional<PassageState>> PassageStateFromProto(pb::PassageState state);

// Poses in WGS84 with heading and covariance at the pose, the landmarks used, the rejections.
void PassageLocalizationToProto(const PassageLocalization& localization, pb::LocalizePassageResponse* wire);

absl::StatusOr<BoundingBox> BoundingBoxFromProto(const pb::BoundingBox& wire, const char* field);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_WIRE_CONVERT_H_
