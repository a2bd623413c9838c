#include "server/wire_convert.h"

#include <cmath>
#include <string>
#include <unordered_map>

#include "absl/strings/str_cat.h"
#include "core/geo/tiles.h"

namespace crowdmap {
namespace {

absl::Status Invalid(const std::string& field, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(field, ": ", what));
}

Eigen::Matrix2d MatrixFromProto(const pb::Matrix2& m) {
  Eigen::Matrix2d out;
  out << m.ee(), m.en(), m.ne(), m.nn();
  return out;
}

void MatrixToProto(const Eigen::Matrix2d& m, pb::Matrix2* out) {
  out->set_ee(m(0, 0));
  out->set_en(m(0, 1));
  out->set_ne(m(1, 0));
  out->set_nn(m(1, 1));
}

Calibration CalibrationFromProto(const pb::Calibration& c) {
  Calibration out;
  out.wheelbase_m = c.wheelbase_m();
  out.gnss_lever_arm_m = {c.gnss_lever_arm_m().x_m(), c.gnss_lever_arm_m().y_m()};
  out.camera_position_m = {c.camera_position_m().x_m(), c.camera_position_m().y_m()};
  out.camera_yaw_rad = c.camera_yaw_rad();
  out.fx_px = c.fx_px();
  out.cx_px = c.cx_px();
  out.image_width_px = c.image_width_px();
  return out;
}

}  // namespace

absl::Status WireLimits::Validate() const {
  if (max_passage_bytes == 0) return absl::InvalidArgumentError("max_passage_bytes must be > 0");
  return absl::OkStatus();
}

absl::Status CheckPassageSize(size_t bytes, const WireLimits& limits) {
  if (bytes > limits.max_passage_bytes) {
    return Invalid("passage", absl::StrCat("serialized size ", bytes, " bytes exceeds the limit of ",
                                           limits.max_passage_bytes, " bytes"));
  }
  return absl::OkStatus();
}

absl::StatusOr<Passage> PassageFromProto(const pb::Passage& wire) {
  if (!wire.has_calibration()) return Invalid("calibration", "missing; every passage carries its calibration");
  Passage p;
  p.vehicle_id = wire.vehicle_id();
  p.passage_id = wire.passage_id();
  p.start_time_unix_ms = wire.start_time_unix_ms();
  p.calibration = CalibrationFromProto(wire.calibration());
  // Absent noise fields keep the thesis defaults of NoiseModel.
  const pb::NoiseModel& n = wire.noise();
  if (n.has_speed_sigma_mps()) p.noise.speed_sigma_mps = n.speed_sigma_mps();
  if (n.has_steering_sigma_rad()) p.noise.steering_sigma_rad = n.steering_sigma_rad();
  if (n.has_pixel_sigma_px()) p.noise.pixel_sigma_px = n.pixel_sigma_px();
  if (n.has_gnss_correlation_time_s()) p.noise.gnss_correlation_time_s = n.gnss_correlation_time_s();
  if (n.has_gnss_process_sigma_m()) p.noise.gnss_process_sigma_m = n.gnss_process_sigma_m();

  p.odometry.reserve(wire.odometry_size());
  for (const pb::OdometrySample& o : wire.odometry()) p.odometry.push_back({o.t_s(), o.speed_mps(), o.steering_rad()});
  p.gnss.reserve(wire.gnss_size());
  for (int i = 0; i < wire.gnss_size(); ++i) {
    const pb::GnssFix& g = wire.gnss(i);
    GnssFix fix;
    fix.t_s = g.t_s();
    fix.lat_deg = g.lat_deg();
    fix.lon_deg = g.lon_deg();
    if (g.has_cov_en_m2()) {
      fix.cov_en_m2 = MatrixFromProto(g.cov_en_m2());
    } else if (g.has_sigma_m()) {
      if (!std::isfinite(g.sigma_m()) || g.sigma_m() < kMinGnssSigmaM || g.sigma_m() > kMaxGnssSigmaM) {
        return Invalid(absl::StrCat("gnss[", i, "].sigma_m"),
                       absl::StrCat("must lie in [", kMinGnssSigmaM, ", ", kMaxGnssSigmaM, "] m, got ", g.sigma_m()));
      }
      fix.cov_en_m2 = Eigen::Matrix2d::Identity() * g.sigma_m() * g.sigma_m();
    } else {
      return Invalid(absl::StrCat("gnss[", i, "].cov_en_m2"), "missing; give cov_en_m2 or sigma_m");
    }
    if (g.has_height_m() && !std::isfinite(g.height_m())) {
      return Invalid(absl::StrCat("gnss[", i, "].height_m"), "must be a finite number");
    }
    p.gnss.push_back(fix);
  }
  p.detections.reserve(wire.detections_size());
  for (const pb::Detection& d : wire.detections()) p.detections.push_back({d.t_s(), d.landmark_id(), d.u_px()});

  if (absl::Status s = ValidatePassage(p); !s.ok()) return s;
  return p;
}

void PassageToProto(const Passage& p, pb::Passage* wire) {
  wire->Clear();
  wire->set_vehicle_id(p.vehicle_id);
  wire->set_passage_id(p.passage_id);
  wire->set_start_time_unix_ms(p.start_time_unix_ms);
  pb::Calibration* c = wire->mutable_calibration();
  c->set_wheelbase_m(p.calibration.wheelbase_m);
  c->mutable_gnss_lever_arm_m()->set_x_m(p.calibration.gnss_lever_arm_m.x());
  c->mutable_gnss_lever_arm_m()->set_y_m(p.calibration.gnss_lever_arm_m.y());
  c->mutable_camera_position_m()->set_x_m(p.calibration.camera_position_m.x());
  c->mutable_camera_position_m()->set_y_m(p.calibration.camera_position_m.y());
  c->set_camera_yaw_rad(p.calibration.camera_yaw_rad);
  c->set_fx_px(p.calibration.fx_px);
  c->set_cx_px(p.calibration.cx_px);
  c->set_image_width_px(p.calibration.image_width_px);
  pb::NoiseModel* n = wire->mutable_noise();
  n->set_speed_sigma_mps(p.noise.speed_sigma_mps);
  n->set_steering_sigma_rad(p.noise.steering_sigma_rad);
  n->set_pixel_sigma_px(p.noise.pixel_sigma_px);
  // The GNSS process only when declared: an absent field is white noise to every reader.
  if (p.noise.gnss_correlation_time_s != 0.0) n->set_gnss_correlation_time_s(p.noise.gnss_correlation_time_s);
  if (p.noise.gnss_process_sigma_m != 0.0) n->set_gnss_process_sigma_m(p.noise.gnss_process_sigma_m);
  wire->mutable_odometry()->Reserve(static_cast<int>(p.odometry.size()));
  for (const OdometrySample& o : p.odometry) {
    pb::OdometrySample* w = wire->add_odometry();
    w->set_t_s(o.t_s);
    w->set_speed_mps(o.speed_mps);
    w->set_steering_rad(o.steering_rad);
  }
  for (const GnssFix& g : p.gnss) {
    pb::GnssFix* w = wire->add_gnss();
    w->set_t_s(g.t_s);
    w->set_lat_deg(g.lat_deg);
    w->set_lon_deg(g.lon_deg);
    MatrixToProto(g.cov_en_m2, w->mutable_cov_en_m2());
  }
  for (const Detection& d : p.detections) {
    pb::Detection* w = wire->add_detections();
    w->set_t_s(d.t_s);
    w->set_landmark_id(d.landmark_id);
    w->set_u_px(d.u_px);
  }
}

void LandmarkToProto(const Landmark& l, pb::Landmark* wire) {
  wire->set_id(l.id);
  wire->set_lat_deg(l.position.lat_deg);
  wire->set_lon_deg(l.position.lon_deg);
  MatrixToProto(l.cov_en_m2, wire->mutable_cov_en_m2());
  wire->set_version(l.version);
  wire->set_passages_seen(l.passages_seen);
  wire->set_last_seen_unix_ms(l.last_seen_unix_ms);
  wire->set_state(l.state == LandmarkState::kActive ? pb::LANDMARK_STATE_ACTIVE : pb::LANDMARK_STATE_UNSPECIFIED);
  const TileId tile = TileContaining(l.position);
  wire->mutable_tile()->set_z(tile.z);
  wire->mutable_tile()->set_x(tile.x);
  wire->mutable_tile()->set_y(tile.y);
}

void VehicleToProto(const VehicleCalibration& v, pb::Vehicle* wire) {
  wire->set_vehicle_id(v.vehicle_id);
  wire->set_camera_yaw_offset_rad(v.camera_yaw_offset_rad);
  wire->set_camera_yaw_sigma_rad(std::sqrt(v.camera_yaw_variance_rad2));
  wire->set_passages(v.passages);
  wire->set_map_version(v.version);
  wire->set_updated_unix_ms(v.updated_unix_ms);
}

VehicleCalibration VehicleFromProto(const pb::Vehicle& wire) {
  VehicleCalibration v;
  v.vehicle_id = wire.vehicle_id();
  v.camera_yaw_offset_rad = wire.camera_yaw_offset_rad();
  v.camera_yaw_variance_rad2 = wire.camera_yaw_sigma_rad() * wire.camera_yaw_sigma_rad();
  v.passages = wire.passages();
  v.version = wire.map_version();
  v.updated_unix_ms = wire.updated_unix_ms();
  return v;
}

Landmark LandmarkFromProto(const pb::Landmark& wire) {
  Landmark l;
  l.id = wire.id();
  l.position = {wire.lat_deg(), wire.lon_deg()};
  l.cov_en_m2 = MatrixFromProto(wire.cov_en_m2());
  l.version = wire.version();
  l.passages_seen = wire.passages_seen();
  l.last_seen_unix_ms = wire.last_seen_unix_ms();
  l.state = LandmarkState::kActive;
  return l;
}

absl::StatusOr<pb::CovarianceFormat> CovarianceFormatFromProto(int format, bool include_cross, const char* field) {
  if (!pb::CovarianceFormat_IsValid(format)) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": unknown value ", format));
  }
  if (format != pb::COVARIANCE_FORMAT_UNSPECIFIED && !include_cross) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": set without include_cross_covariance"));
  }
  return format == pb::COVARIANCE_FORMAT_PACKED ? pb::COVARIANCE_FORMAT_PACKED : pb::COVARIANCE_FORMAT_BLOCKS;
}

pb::CovarianceBound CovarianceBoundToProto(CovarianceBound bound) {
  switch (bound) {
    case CovarianceBound::kExact:
      return pb::COVARIANCE_BOUND_EXACT;
    case CovarianceBound::kConservative:
      return pb::COVARIANCE_BOUND_CONSERVATIVE;
    case CovarianceBound::kMayBeNarrower:
      return pb::COVARIANCE_BOUND_MAY_BE_NARROWER;
  }
  return pb::COVARIANCE_BOUND_UNSPECIFIED;
}

void CovarianceToBlocks(const LandmarkPage& page, google::protobuf::RepeatedPtrField<pb::CrossCovariance>* wire) {
  const Eigen::MatrixXd& cov = page.covariance;
  const int n = static_cast<int>(page.landmarks.size());
  wire->Reserve(wire->size() + n * (n - 1) / 2);
  for (int i = 0; i < n; ++i) {
    for (int j = i + 1; j < n; ++j) {
      const bool ordered = page.landmarks[i].id < page.landmarks[j].id;
      pb::CrossCovariance* c = wire->Add();
      c->set_first_id(page.landmarks[ordered ? i : j].id);
      c->set_second_id(page.landmarks[ordered ? j : i].id);
      MatrixToProto(ordered ? Eigen::Matrix2d(cov.block<2, 2>(2 * i, 2 * j))
                            : Eigen::Matrix2d(cov.block<2, 2>(2 * j, 2 * i)),
                    c->mutable_cov_m2());
    }
  }
}

void CovarianceToPacked(const Eigen::MatrixXd& covariance, pb::PackedCovariance* wire) {
  const int dim = static_cast<int>(covariance.rows());
  wire->set_dim(dim);
  google::protobuf::RepeatedField<double>* upper = wire->mutable_upper_m2();
  upper->Resize(dim * (dim + 1) / 2, 0.0);
  double* out = upper->mutable_data();
  for (int r = 0; r < dim; ++r) {
    for (int c = r; c < dim; ++c) *out++ = covariance(r, c);
  }
}

absl::StatusOr<Eigen::MatrixXd> CovarianceFromBlocks(const google::protobuf::RepeatedPtrField<pb::Landmark>& landmarks,
                                                     const google::protobuf::RepeatedPtrField<pb::CrossCovariance>& blocks,
                                                     const char* field) {
  const int n = landmarks.size();
  std::unordered_map<int64_t, int> index;
  Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  for (int i = 0; i < n; ++i) {
    index[landmarks[i].id()] = i;
    cov.block<2, 2>(2 * i, 2 * i) = MatrixFromProto(landmarks[i].cov_en_m2());
  }
  for (int k = 0; k < blocks.size(); ++k) {
    const pb::CrossCovariance& c = blocks[k];
    const auto a = index.find(c.first_id()), b = index.find(c.second_id());
    if (a == index.end() || b == index.end()) {
      return absl::InvalidArgumentError(absl::StrCat(field, "[", k, "]: landmarks ", c.first_id(), " and ",
                                                     c.second_id(), " are not both in the response"));
    }
    const Eigen::Matrix2d block = MatrixFromProto(c.cov_m2());
    cov.block<2, 2>(2 * a->second, 2 * b->second) = block;
    cov.block<2, 2>(2 * b->second, 2 * a->second) = block.transpose();
  }
  return cov;
}

absl::StatusOr<Eigen::MatrixXd> CovarianceFromPacked(const pb::PackedCovariance& wire, int landmarks,
                                                     const char* field) {
  const int dim = 2 * landmarks;
  if (wire.dim() != dim || wire.upper_m2_size() != dim * (dim + 1) / 2) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": dim ", wire.dim(), " with ", wire.upper_m2_size(),
                                                   " values for ", landmarks, " landmarks (want dim ", dim, " with ",
                                                   dim * (dim + 1) / 2, ")"));
  }
  Eigen::MatrixXd cov(dim, dim);
  const double* in = wire.upper_m2().data();
  for (int r = 0; r < dim; ++r) {
    for (int c = r; c < dim; ++c) cov(r, c) = cov(c, r) = *in++;
  }
  return cov;
}

pb::PassageState PassageStateToProto(PassageState state) {
  switch (state) {
    case PassageState::kQueued: return pb::PASSAGE_STATE_QUEUED;
    case PassageState::kProcessing: return pb::PASSAGE_STATE_PROCESSING;
    case PassageState::kApplied: return pb::PASSAGE_STATE_APPLIED;
    case PassageState::kRejected: return pb::PASSAGE_STATE_REJECTED;
    case PassageState::kFailed: return pb::PASSAGE_STATE_FAILED;
    case PassageState::kExcluded: return pb::PASSAGE_STATE_EXCLUDED;
    case PassageState::kQuarantined: return pb::PASSAGE_STATE_QUARANTINED;
    case PassageState::kDiscarded: return pb::PASSAGE_STATE_DISCARDED;
  }
  return pb::PASSAGE_STATE_UNSPECIFIED;
}

absl::StatusOr<std::optional<PassageState>> PassageStateFromProto(pb::PassageState state) {
  switch (state) {
    case pb::PASSAGE_STATE_UNSPECIFIED: return std::optional<PassageState>();
    case pb::PASSAGE_STATE_QUEUED: return std::optional<PassageState>(PassageState::kQueued);
    case pb::PASSAGE_STATE_PROCESSING: return std::optional<PassageState>(PassageState::kProcessing);
    case pb::PASSAGE_STATE_APPLIED: return std::optional<PassageState>(PassageState::kApplied);
    case pb::PASSAGE_STATE_REJECTED: return std::optional<PassageState>(PassageState::kRejected);
    case pb::PASSAGE_STATE_FAILED: return std::optional<PassageState>(PassageState::kFailed);
    case pb::PASSAGE_STATE_EXCLUDED: return std::optional<PassageState>(PassageState::kExcluded);
    case pb::PASSAGE_STATE_QUARANTINED: return std::optional<PassageState>(PassageState::kQuarantined);
    case pb::PASSAGE_STATE_DISCARDED: return std::optional<PassageState>(PassageState::kDiscarded);
    default: return Invalid("state", absl::StrCat("unknown passage state ", static_cast<int>(state)));
  }
}

void StoredPassageToProto(const StoredPassage& r, pb::PassageStatus* wire) {
  wire->set_id(r.id);
  wire->set_vehicle_id(r.vehicle_id);
  wire->set_passage_id(r.passage_id);
  wire->set_state(PassageStateToProto(r.state));
  wire->set_attempts(r.attempts);
  wire->set_error(r.error);
  wire->set_received_unix_ms(r.received_unix_ms);
  wire->set_finished_unix_ms(r.finished_unix_ms);
  wire->set_size_bytes(r.size_bytes);
  wire->set_payload_pruned_unix_ms(r.payload_pruned_unix_ms);
  if (!r.result) return;
  const PassageResult& s = *r.result;
  pb::PassageResult* out = wire->mutable_result();
  out->set_nodes(s.nodes);
  out->set_subgraphs(s.subgraphs);
  out->set_landmarks_updated(s.landmarks_updated);
  out->set_landmarks_created(s.landmarks_created);
  out->set_landmarks_conditioned(s.landmarks_conditioned);
  out->set_detections_used(s.detections_used);
  out->set_detections_dropped(s.detections_dropped);
  out->set_solver_iterations(s.solver_iterations);
  out->set_final_cost(s.final_cost);
  out->set_solve_ms(s.solve_ms);
  out->set_covariance_ms(s.covariance_ms);
  out->set_total_ms(s.total_ms);
  out->set_map_version(s.map_version);
  out->set_strategy(s.strategy);
}

absl::StatusOr<BoundingBox> BoundingBoxFromProto(const pb::BoundingBox& wire, const char* field) {
  const double v[4] = {wire.min_lat_deg(), wire.min_lon_deg(), wire.max_lat_deg(), wire.max_lon_deg()};
  const char* names[4] = {"min_lat_deg", "min_lon_deg", "max_lat_deg", "max_lon_deg"};
  for (int k = 0; k < 4; ++k) {
    const double limit = k % 2 == 0 ? 90.0 : 180.0;
    if (!std::isfinite(v[k]) || std::abs(v[k]) > limit) {
      return Invalid(absl::StrCat(field, ".", names[k]), absl::StrCat(v[k], " outside [-", limit, ", ", limit, "]"));
    }
  }
  if (v[0] > v[2]) return Invalid(absl::StrCat(field, ".min_lat_deg"), "greater than max_lat_deg");
  if (v[1] > v[3]) return Invalid(absl::StrCat(field, ".min_lon_deg"), "greater than max_lon_deg");
  return BoundingBox{v[0], v[1], v[2], v[3]};
}

void PassageLocalizationToProto(const PassageLocalization& localization, pb::LocalizePassageResponse* wire) {
  for (const LocalizedPose& p : localization.poses) {
    pb::LocalizedPose* out = wire->add_poses();
    out->set_t_s(p.t_s);
    out->set_lat_deg(p.position.lat_deg);
    out->set_lon_deg(p.position.lon_deg);
    out->set_heading_rad(p.heading_en_rad);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) out->add_covariance(p.cov_en(r, c));
    }
  }
  for (LandmarkId id : localization.landmarks_used) wire->add_landmarks_used(id);
  for (const RejectedDetection& r : localization.rejected) {
    pb::RejectedDetection* out = wire->add_rejected();
    out->set_t_s(r.t_s);
    out->set_landmark_id(r.landmark_id);
    out->set_u_px(r.u_px);
    out->set_whitened_residual(std::isfinite(r.whitened_residual) ? r.whitened_residual : 0.0);
    out->set_whole_landmark(r.whole_landmark);
  }
  wire->set_detections_used(localization.detections_used);
  wire->set_detections_unmapped(localization.detections_unmapped);
  wire->set_chi2(localization.chi2);
  wire->set_dof(localization.dof);
  wire->set_map_version(localization.map_version);
}

}  // namespace crowdmap
