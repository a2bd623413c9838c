#include "core/localization/streaming_localizer.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

#include <Eigen/Cholesky>
#include <ceres/ceres.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/estimation/factors.h"
#include "core/estimation/graph_builder.h"
#include "core/localization/pose_covariance.h"
#include "core/map/sparse_threads.h"

namespace crowdmap {

struct StreamingLocalizer::Measurement {
  std::unique_ptr<ceres::CostFunction> cost;  // whitened residual
  std::vector<int> offsets;                   // state row of each parameter block
};

namespace {

using RowMajorMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// One Jacobian block of a stacked update: rows from `row`, columns of the state from `offset`.
struct JacobianBlock {
  int row = 0;
  int offset = 0;
  Eigen::MatrixXd jacobian;
};

// Residual and Jacobian blocks of a cost function at the state x (parameter blocks at `offsets`).
bool EvaluateAt(const ceres::CostFunction& cost, const std::vector<int>& offsets, const Eigen::VectorXd& x, int row,
                Eigen::VectorXd* residual, std::vector<JacobianBlock>* blocks) {
  const std::vector<int32_t>& sizes = cost.parameter_block_sizes();
  const int rows = cost.num_residuals();
  std::vector<Eigen::VectorXd> values(sizes.size());
  std::vector<RowMajorMatrix> jacobians(sizes.size());
  std::vector<const double*> parameters(sizes.size());
  std::vector<double*> jacobian_ptrs(sizes.size());
  for (size_t i = 0; i < sizes.size(); ++i) {
    values[i] = x.segment(offsets[i], sizes[i]);
    jacobians[i].resize(rows, sizes[i]);
    parameters[i] = values[i].data();
    jacobian_ptrs[i] = jacobians[i].data();
  }
  residual->resize(rows);
  if (!cost.Evaluate(parameters.data(), residual->data(), jacobian_ptrs.data())) return false;
  if (!residual->allFinite()) return false;
  for (size_t i = 0; i < sizes.size(); ++i) {
    if (!jacobians[i].allFinite()) return false;
    blocks->push_back({row, offsets[i], jacobians[i]});
  }
  return true;
}

// d(start (+) delta)/d(start) and d(start (+) delta)/d(delta) (SE(2) composition, ComposeMotion).
void CompositionJacobians(const Pose2& start, const Pose2& delta, Eigen::Matrix3d* d_start, Eigen::Matrix3d* d_delta) {
  const double c = std::cos(start.z()), s = std::sin(start.z());
  *d_start << 1, 0, -s * delta.x() - c * delta.y(),  //
      0, 1, c * delta.x() - s * delta.y(),           //
      0, 0, 1;
  *d_delta << c, -s, 0,  //
      s, c, 0,           //
      0, 0, 1;
}

// The result of an input before the filter starts.
StreamingUpdate NotTracking() {
  StreamingUpdate out;
  out.pose.pose_m.setZero();
  out.pose.cov.setZero();
  out.pose.cov_en.setZero();
  return out;
}

}  // namespace

absl::Status StreamingLocalizerOptions::Validate() const {
  if (!(start_span_s >= 0.0)) return absl::InvalidArgumentError("start_span_s: must be >= 0");
  if (start_min_fixes < 2) return absl::InvalidArgumentError("start_min_fixes: must be >= 2");
  if (!(detection_gate_sigmas > 0.0)) return absl::InvalidArgumentError("detection_gate_sigmas: must be > 0");
  if (max_iterations < 1) return absl::InvalidArgumentError("max_iterations: must be >= 1");
  if (!(iteration_tolerance >= 0.0)) return absl::InvalidArgumentError("iteration_tolerance: must be >= 0");
  if (!(camera_yaw_sigma_rad >= 0.0 && camera_yaw_sigma_rad < M_PI)) {
    return absl::InvalidArgumentError("camera_yaw_sigma_rad: must lie in [0, pi)");
  }
  return absl::OkStatus();
}

std::string StreamingUpdate::Brief() const {
  if (!tracking) return "tracking=false";
  return absl::StrFormat("t=%.3f x=%.3f y=%.3f heading=%.4f sigma_en=%.3f,%.3f used=%d rejected=%d jump_sigmas=%.2f",
                         pose.t_s, pose.pose_m.x(), pose.pose_m.y(), pose.pose_m.z(), std::sqrt(pose.cov(0, 0)),
                         std::sqrt(pose.cov(1, 1)), detections_used, rejected.size(), correction_sigmas);
}

StreamingLocalizer::StreamingLocalizer(const Calibration& calibration, const NoiseModel& noise,
                                       const StreamingLocalizerOptions& options)
    : calibration_(calibration), noise_(noise), options_(options) {}

absl::StatusOr<std::unique_ptr<StreamingLocalizer>> StreamingLocalizer::Create(const Calibration& calibration,
                                                                              const NoiseModel& noise,
                                                                              const StreamingLocalizerOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  if (!(calibration.wheelbase_m > 0.0)) return absl::InvalidArgumentError("calibration.wheelbase_m: must be > 0");
  if (!(noise.pixel_sigma_px > 0.0)) return absl::InvalidArgumentError("noise.pixel_sigma_px: must be > 0");
  return std::unique_ptr<StreamingLocalizer>(new StreamingLocalizer(calibration, noise, options));
}

absl::Status StreamingLocalizer::AddMapLandmarks(const LocalizationMap& map) {
  if (absl::Status s = map.Validate(); !s.ok()) return s;
  if (!tracking_) {
    pending_.push_back(map);
    return absl::OkStatus();
  }
  std::vector<int> fresh;
  for (size_t k = 0; k < map.ids.size(); ++k) {
    if (slot_.count(map.ids[k]) == 0) fresh.push_back(static_cast<int>(k));
  }
  if (fresh.empty()) return absl::OkStatus();
  const int n = static_cast<int>(x_.size());
  const int m = static_cast<int>(fresh.size());
  std::vector<Eigen::Matrix2d> rotation(m);
  x_.conservativeResize(n + 2 * m);
  P_.conservativeResize(n + 2 * m, n + 2 * m);
  P_.rightCols(2 * m).setZero();
  P_.bottomRows(2 * m).setZero();
  for (int a = 0; a < m; ++a) {
    const LatLon& position = map.positions[fresh[a]];
    x_.segment<2>(n + 2 * a) = frame_->ToLocal(position);
    rotation[a] = frame_->EnToLocal(position);
    slot_[map.ids[fresh[a]]] = static_cast<int>(slot_ids_.size());
    slot_ids_.push_back(map.ids[fresh[a]]);
  }
  for (int a = 0; a < m; ++a) {
    for (int b = 0; b < m; ++b) {
      const Eigen::Matrix2d block = map.cov_en_m2.block<2, 2>(2 * fresh[a], 2 * fresh[b]);
      P_.block<2, 2>(n + 2 * a, n + 2 * b) = rotation[a] * block * rotation[b].transpose();
    }
  }
  return absl::OkStatus();
}

void StreamingLocalizer::RemoveMapLandmarks(const std::vector<LandmarkId>& ids) {
  if (!tracking_) {
    for (LocalizationMap& map : pending_) {
      std::vector<int> keep;
      for (size_t k = 0; k < map.ids.size(); ++k) {
        if (std::find(ids.begin(), ids.end(), map.ids[k]) == ids.end()) keep.push_back(static_cast<int>(k));
      }
      std::vector<int> rows;
      LocalizationMap kept;
      kept.version = map.version;
      for (int k : keep) {
        kept.ids.push_back(map.ids[k]);
        kept.positions.push_back(map.positions[k]);
        rows.push_back(2 * k);
        rows.push_back(2 * k + 1);
      }
      kept.cov_en_m2 = map.cov_en_m2(rows, rows);
      map = std::move(kept);
    }
    return;
  }
  std::vector<int> rows = {0, 1, 2};
  if (yaw_row() >= 0) rows.push_back(yaw_row());
  std::vector<LandmarkId> kept_ids;
  for (LandmarkId id : slot_ids_) {
    if (std::find(ids.begin(), ids.end(), id) != ids.end()) continue;
    const int row = landmark_row(slot_.at(id));
    rows.push_back(row);
    rows.push_back(row + 1);
    kept_ids.push_back(id);
  }
  if (kept_ids.size() == slot_ids_.size()) return;
  // Marginalising a Gaussian in covariance form: drop its rows and columns.
  Eigen::VectorXd x = x_(rows);
  Eigen::MatrixXd P = P_(rows, rows);
  x_ = std::move(x);
  P_ = std::move(P);
  slot_.clear();
  slot_ids_ = std::move(kept_ids);
  for (size_t k = 0; k < slot_ids_.size(); ++k) slot_[slot_ids_[k]] = static_cast<int>(k);
}

absl::Status StreamingLocalizer::CheckTime(double t_s) const {
  if (!std::isfinite(t_s)) return absl::InvalidArgumentError("t_s: not finite");
  if (tracking_ && t_s < state_t_s_ - 1e-9) {
    return absl::InvalidArgumentError(
        absl::StrFormat("t_s: %.6f is before the filter's time %.6f (inputs must come in time order)", t_s, state_t_s_));
  }
  return absl::OkStatus();
}

absl::StatusOr<StreamingUpdate> StreamingLocalizer::AddOdometry(const OdometrySample& sample) {
  if (!std::isfinite(sample.t_s) || !std::isfinite(sample.speed_mps) || !std::isfinite(sample.steering_rad)) {
    return absl::InvalidArgumentError("odometry: not finite");
  }
  const std::vector<OdometrySample>& previous = tracking_ ? odometry_ : start_odometry_;
  if (!previous.empty() && !(sample.t_s > previous.back().t_s)) {
    return absl::InvalidArgumentError(
        absl::StrFormat("odometry t_s: %.6f not after the previous sample's %.6f", sample.t_s, previous.back().t_s));
  }
  if (!tracking_) {
    start_odometry_.push_back(sample);
    return NotTracking();
  }
  odometry_.push_back(sample);
  if (sample.t_s <= state_t_s_) return Current();
  Pose2 pose;
  Eigen::Matrix3d cov;
  PredictPose(sample.t_s, &pose, &cov);
  return Output(sample.t_s, pose, cov);
}

absl::StatusOr<StreamingUpdate> StreamingLocalizer::AddGnss(const GnssFix& fix) {
  if (absl::Status s = CheckTime(fix.t_s); !s.ok()) return s;
  if (!std::isfinite(fix.lat_deg) || !std::isfinite(fix.lon_deg) || !fix.cov_en_m2.allFinite()) {
    return absl::InvalidArgumentError("gnss: not finite");
  }
  if (!tracking_) {
    if (!start_gnss_.empty() && !(fix.t_s > start_gnss_.back().t_s)) {
      return absl::InvalidArgumentError("gnss t_s: not after the previous fix's");
    }
    if (!frame_) frame_.emplace(LatLon{fix.lat_deg, fix.lon_deg});
    start_gnss_.push_back(fix);
    if (static_cast<int>(start_gnss_.size()) < options_.start_min_fixes ||
        start_gnss_.back().t_s - start_gnss_.front().t_s < options_.start_span_s) {
      return NotTracking();
    }
    if (absl::Status s = Start(); !s.ok()) return s;
    return Current();
  }
  Predict(fix.t_s);
  const Pose2 predicted = x_.head<3>();
  const Eigen::Matrix3d predicted_cov = P_.topLeftCorner<3, 3>();
  const LatLon position{fix.lat_deg, fix.lon_deg};
  const Eigen::Matrix2d rotation = frame_->EnToLocal(position);
  std::vector<Measurement> measurements(1);
  measurements[0].cost.reset(
      GnssFactor::Create(frame_->ToLocal(position), rotation * fix.cov_en_m2 * rotation.transpose(),
                         calibration_.gnss_lever_arm_m));
  measurements[0].offsets = {0};
  if (!Update(measurements)) return absl::InternalError("gnss update: the residual cannot be evaluated");
  StreamingUpdate out = Current();
  out.correction = x_.head<3>() - predicted;
  out.correction.z() = NormalizeAngle(out.correction.z());
  out.correction_sigmas = (out.correction.cwiseAbs().array() / predicted_cov.diagonal().cwiseSqrt().array()).maxCoeff();
  return out;
}

absl::StatusOr<StreamingUpdate> StreamingLocalizer::AddDetections(const std::vector<Detection>& frame) {
  if (frame.empty()) return tracking_ ? Current() : NotTracking();
  const double t_s = frame.front().t_s;
  for (const Detection& d : frame) {
    if (std::abs(d.t_s - t_s) > 1e-9) return absl::InvalidArgumentError("detections: one frame has one time");
    if (!std::isfinite(d.u_px)) return absl::InvalidArgumentError("detections: u_px not finite");
  }
  if (absl::Status s = CheckTime(t_s); !s.ok()) return s;
  if (!tracking_) return NotTracking();
  Predict(t_s);
  const Pose2 predicted = x_.head<3>();
  const Eigen::Matrix3d predicted_cov = P_.topLeftCorner<3, 3>();

  StreamingUpdate out = NotTracking();
  std::vector<Measurement> measurements;
  std::vector<const Detection*> kept;
  for (const Detection& d : frame) {
    const auto it = slot_.find(d.landmark_id);
    if (it == slot_.end()) {
      ++out.detections_unmapped;
      continue;
    }
    Measurement m;
    if (yaw_row() >= 0) {
      m.cost.reset(CameraYawFactor::Create(d.u_px, noise_.pixel_sigma_px, calibration_));
      m.offsets = {0, landmark_row(it->second), yaw_row()};
    } else {
      m.cost.reset(CameraFactor::Create(d.u_px, noise_.pixel_sigma_px, calibration_));
      m.offsets = {0, landmark_row(it->second)};
    }
    // The gate: the whitened innovation at the prediction, with the innovation variance
    // 1 + J P J^T (the residual is already in pixel sigmas).
    Eigen::VectorXd residual;
    std::vector<JacobianBlock> blocks;
    double whitened = std::numeric_limits<double>::infinity();
    if (EvaluateAt(*m.cost, m.offsets, x_, 0, &residual, &blocks)) {
      double variance = 1.0;
      for (const JacobianBlock& a : blocks) {
        for (const JacobianBlock& b : blocks) {
          variance += (a.jacobian * P_.block(a.offset, b.offset, a.jacobian.cols(), b.jacobian.cols()) *
                       b.jacobian.transpose())(0, 0);
        }
      }
      whitened = residual(0) / std::sqrt(variance);
    }
    if (!(std::abs(whitened) <= options_.detection_gate_sigmas)) {
      out.rejected.push_back({t_s, d.landmark_id, d.u_px, whitened, false});
      continue;
    }
    measurements.push_back(std::move(m));
    kept.push_back(&d);
  }
  if (!UpdateGated(t_s, &measurements, &kept, &out.rejected)) {
    return absl::InternalError("detection update: a residual cannot be evaluated");
  }
  StreamingUpdate current = Current();
  out.tracking = true;
  out.pose = current.pose;
  out.camera_yaw_offset_rad = current.camera_yaw_offset_rad;
  out.camera_yaw_sigma_rad = current.camera_yaw_sigma_rad;
  out.detections_used = static_cast<int>(measurements.size());
  out.correction = x_.head<3>() - predicted;
  out.correction.z() = NormalizeAngle(out.correction.z());
  out.correction_sigmas = (out.correction.cwiseAbs().array() / predicted_cov.diagonal().cwiseSqrt().array()).maxCoeff();
  return out;
}

absl::Status StreamingLocalizer::Start() {
  Passage passage;
  passage.calibration = calibration_;
  passage.noise = noise_;
  passage.odometry = start_odometry_;
  passage.gnss = start_gnss_;
  GraphOptions graph_options;
  graph_options.frame_origin = frame_->origin();
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();
  // The pose graph solved again to the end, for the covariance at the solution.
  std::vector<Pose2> poses = graph->initial_poses;
  ceres::Problem problem;
  AddPoseGraphFactors(*graph, 0, graph->node_count() - 1, calibration_.gnss_lever_arm_m, nullptr, nullptr, &poses,
                      &problem);
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.function_tolerance = 1e-12;
  solver.gradient_tolerance = 1e-12;
  solver.parameter_tolerance = 1e-12;
  solver.num_threads = 1;
  solver.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  FactorizeOnThisThreadOnly();
  ceres::Solve(solver, &problem, &summary);
  if (!summary.IsSolutionUsable()) return absl::InternalError(absl::StrCat("start solve failed: ", summary.message));
  std::vector<Eigen::Vector2d> no_landmarks;
  absl::StatusOr<std::vector<Eigen::Matrix3d>> covariances = PoseCovariances(&problem, &poses, &no_landmarks);
  if (!covariances.ok()) return covariances.status();

  const int start_rows = yaw_row() >= 0 ? 4 : 3;
  x_ = Eigen::VectorXd::Zero(start_rows);
  x_.head<3>() = poses.back();
  x_.z() = NormalizeAngle(x_.z());
  P_ = Eigen::MatrixXd::Zero(start_rows, start_rows);
  P_.topLeftCorner<3, 3>() = 0.5 * (covariances->back() + covariances->back().transpose());
  if (yaw_row() >= 0) P_(3, 3) = options_.camera_yaw_sigma_rad * options_.camera_yaw_sigma_rad;
  state_t_s_ = graph->node_times_s.back();
  tracking_ = true;
  odometry_ = std::move(start_odometry_);
  start_odometry_.clear();
  start_gnss_.clear();
  Predict(state_t_s_);  // prunes the odometry
  std::vector<LocalizationMap> pending = std::move(pending_);
  pending_.clear();
  for (const LocalizationMap& map : pending) {
    if (absl::Status s = AddMapLandmarks(map); !s.ok()) return s;
  }
  return absl::OkStatus();
}

void StreamingLocalizer::Predict(double t_s) {
  if (t_s > state_t_s_) {
    const RelativeMotion motion =
        Preintegrate(odometry_, state_t_s_, t_s, calibration_.wheelbase_m, noise_);
    const Pose2 start = x_.head<3>();
    Eigen::Matrix3d d_start, d_delta;
    CompositionJacobians(start, motion.delta, &d_start, &d_delta);
    x_.head<3>() = ComposeMotion(start, motion.delta);
    const int n = static_cast<int>(x_.size());
    P_.topLeftCorner<3, 3>() =
        d_start * P_.topLeftCorner<3, 3>() * d_start.transpose() + d_delta * motion.cov * d_delta.transpose();
    if (n > 3) {
      P_.topRightCorner(3, n - 3) = d_start * P_.topRightCorner(3, n - 3);
      P_.bottomLeftCorner(n - 3, 3) = P_.topRightCorner(3, n - 3).transpose();
    }
    state_t_s_ = t_s;
  }
  // Keep the sample held at the state's time and the later ones.
  auto it = std::upper_bound(odometry_.begin(), odometry_.end(), state_t_s_,
                             [](double t, const OdometrySample& o) { return t < o.t_s; });
  if (it - odometry_.begin() > 1) odometry_.erase(odometry_.begin(), it - 1);
}

void StreamingLocalizer::PredictPose(double t_s, Pose2* pose, Eigen::Matrix3d* cov) const {
  const RelativeMotion motion = Preintegrate(odometry_, state_t_s_, t_s, calibration_.wheelbase_m, noise_);
  const Pose2 start = x_.head<3>();
  Eigen::Matrix3d d_start, d_delta;
  CompositionJacobians(start, motion.delta, &d_start, &d_delta);
  *pose = ComposeMotion(start, motion.delta);
  *cov = d_start * P_.topLeftCorner<3, 3>() * d_start.transpose() + d_delta * motion.cov * d_delta.transpose();
}

struct StreamingLocalizer::Step {
  Eigen::VectorXd x;       // posterior state
  Eigen::MatrixXd factor;  // U = P H^T L^-T with L L^T = H P H^T + I, so that P+ = P - U U^T
  Eigen::MatrixXd hpht;    // H P H^T (m x m), at the last linearisation
};

// Iterated EKF (Gauss-Newton on the prior and the measurements): at each iterate x_i,
//   x_(i+1) = x_0 + K_i (-r(x_i) - H_i (x_0 - x_i)),  K_i = P H_i^T (H_i P H_i^T + I)^-1,
// and P+ = P - K H P with the last iterate's K and H. H has non-zero columns only at the pose and
// the detected landmarks, so P H^T is formed from those columns of P.
bool StreamingLocalizer::ComputeUpdate(const std::vector<Measurement>& measurements, Step* step) const {
  const int n = static_cast<int>(x_.size());
  int rows = 0;
  for (const Measurement& m : measurements) rows += m.cost->num_residuals();
  const Eigen::VectorXd& x0 = x_;
  Eigen::VectorXd xi = x_;
  bool updated = false;
  for (int iteration = 0; iteration < options_.max_iterations; ++iteration) {
    Eigen::VectorXd residual(rows);
    std::vector<JacobianBlock> blocks;
    int row = 0;
    bool evaluated = true;
    for (const Measurement& m : measurements) {
      Eigen::VectorXd r;
      if (!EvaluateAt(*m.cost, m.offsets, xi, row, &r, &blocks)) {
        evaluated = false;
        break;
      }
      residual.segment(row, r.size()) = r;
      row += static_cast<int>(r.size());
    }
    if (!evaluated) break;  // keep the previous iterate
    Eigen::MatrixXd pht = Eigen::MatrixXd::Zero(n, rows);
    for (const JacobianBlock& b : blocks) {
      pht.middleCols(b.row, b.jacobian.rows()).noalias() += P_.middleCols(b.offset, b.jacobian.cols()) * b.jacobian.transpose();
    }
    Eigen::MatrixXd hpht = Eigen::MatrixXd::Zero(rows, rows);
    Eigen::VectorXd innovation = -residual;
    const Eigen::VectorXd offset = x0 - xi;
    for (const JacobianBlock& b : blocks) {
      hpht.middleRows(b.row, b.jacobian.rows()).noalias() += b.jacobian * pht.middleRows(b.offset, b.jacobian.cols());
      innovation.segment(b.row, b.jacobian.rows()).noalias() -= b.jacobian * offset.segment(b.offset, b.jacobian.cols());
    }
    hpht = 0.5 * (hpht + hpht.transpose()).eval();
    const Eigen::LLT<Eigen::MatrixXd> llt(hpht + Eigen::MatrixXd::Identity(rows, rows));
    if (llt.info() != Eigen::Success) break;
    Eigen::MatrixXd factor = llt.matrixL().solve(pht.transpose()).transpose();
    Eigen::VectorXd next = x0 + factor * llt.matrixL().solve(innovation);
    const double change = (next.head<3>() - xi.head<3>()).cwiseAbs().maxCoeff();
    xi = next;
    step->x = std::move(next);
    step->factor = std::move(factor);
    step->hpht = std::move(hpht);
    updated = true;
    if (change < options_.iteration_tolerance) break;
  }
  return updated;
}

void StreamingLocalizer::Apply(const Step& step) {
  x_ = step.x;
  x_.z() = NormalizeAngle(x_.z());
  // K S K^T as U U^T: symmetric as computed, and one pass over P.
  P_.noalias() -= step.factor * step.factor.transpose();
}

bool StreamingLocalizer::Update(const std::vector<Measurement>& measurements) {
  Step step;
  if (!ComputeUpdate(measurements, &step)) return false;
  Apply(step);
  return true;
}

bool StreamingLocalizer::UpdateGated(double t_s, std::vector<Measurement>* measurements,
                                     std::vector<const Detection*>* detections,
                                     std::vector<RejectedDetection>* rejected) {
  while (!measurements->empty()) {
    Step step;
    if (!ComputeUpdate(*measurements, &step)) return false;
    if (measurements->size() < 2) {
      Apply(step);
      return true;
    }
    // Each detection is one row; the posterior residual's variance is ((H P H^T + I)^-1)_jj.
    const int m = static_cast<int>(measurements->size());
    const Eigen::MatrixXd residual_cov =
        (step.hpht + Eigen::MatrixXd::Identity(m, m)).llt().solve(Eigen::MatrixXd::Identity(m, m));
    int worst = -1;
    double worst_value = options_.detection_gate_sigmas, worst_studentized = 0.0;
    for (int j = 0; j < m; ++j) {
      Eigen::VectorXd r;
      std::vector<JacobianBlock> blocks;
      const Measurement& meas = (*measurements)[j];
      const double studentized = EvaluateAt(*meas.cost, meas.offsets, step.x, 0, &r, &blocks)
                                     ? r(0) / std::sqrt(residual_cov(j, j))
                                     : std::numeric_limits<double>::infinity();
      if (!(std::abs(studentized) <= worst_value)) {
        worst = j;
        worst_value = std::abs(studentized);
        worst_studentized = studentized;
      }
    }
    if (worst < 0) {
      Apply(step);
      return true;
    }
    const Detection& d = *(*detections)[worst];
    rejected->push_back({t_s, d.landmark_id, d.u_px, worst_studentized, false});
    measurements->erase(measurements->begin() + worst);
    detections->erase(detections->begin() + worst);
  }
  return true;
}

StreamingUpdate StreamingLocalizer::Output(double t_s, const Pose2& pose, const Eigen::Matrix3d& cov) const {
  StreamingUpdate out;
  out.tracking = true;
  out.pose = MakeLocalizedPose(*frame_, t_s, pose, cov);
  if (yaw_row() >= 0) {
    out.camera_yaw_offset_rad = x_[yaw_row()];
    out.camera_yaw_sigma_rad = std::sqrt(P_(yaw_row(), yaw_row()));
  }
  return out;
}

StreamingUpdate StreamingLocalizer::Current() const {
  return Output(state_t_s_, x_.head<3>(), P_.topLeftCorner<3, 3>());
}

}  // namespace crowdmap
