#include "core/estimation/cramer_rao.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"
#include "core/estimation/graph_linearization.h"

namespace crowdmap {
namespace {

// All GNSS fixes of a passage as one residual block, whitened by the Cholesky factor of their
// joint covariance: with coloured noise (NoiseModel::gnss_correlation_time_s) the fixes' normalised
// errors z_j = S_j (antenna_j - y_j) are correlated exp(-|t_i - t_j| / tau) per axis. Written
// apart from the estimator's factors (GnssAr1Factor, a recursive whitening), from the process's
// correlation function, so that the bound can judge them.
class CorrelatedGnssSequence : public ceres::CostFunction {
 public:
  CorrelatedGnssSequence(const PassageGraph& graph, const Eigen::Vector2d& lever_arm,
                         const std::vector<int>& block_of_fix, int blocks)
      : graph_(graph), lever_arm_(lever_arm), block_of_fix_(block_of_fix) {
    const int n = static_cast<int>(graph.gnss.size());
    Eigen::MatrixXd correlation(n, n);
    for (int i = 0; i < n; ++i) {
      for (int j = 0; j < n; ++j) {
        correlation(i, j) = std::exp(-std::abs(graph.gnss[i].t_s - graph.gnss[j].t_s) / graph.gnss_correlation_time_s);
      }
    }
    const Eigen::LLT<Eigen::MatrixXd> llt(correlation);
    whitening_ = llt.matrixL().solve(Eigen::MatrixXd::Identity(n, n));
    for (const GnssObservation& o : graph.gnss) {
      sqrt_info_.push_back(Eigen::LLT<Eigen::Matrix2d>(o.cov_m2).matrixL().solve(Eigen::Matrix2d::Identity()));
    }
    set_num_residuals(2 * n);
    for (int b = 0; b < blocks; ++b) mutable_parameter_block_sizes()->push_back(3);
  }

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
    const int n = static_cast<int>(graph_.gnss.size());
    const int blocks = static_cast<int>(parameter_block_sizes().size());
    Eigen::VectorXd z(2 * n);
    Eigen::MatrixXd dz = Eigen::MatrixXd::Zero(2 * n, 3 * blocks);
    for (int j = 0; j < n; ++j) {
      const double* pose = parameters[block_of_fix_[j]];
      const double c = std::cos(pose[2]), s = std::sin(pose[2]);
      const Eigen::Vector2d antenna(pose[0] + c * lever_arm_.x() - s * lever_arm_.y(),
                                    pose[1] + s * lever_arm_.x() + c * lever_arm_.y());
      z.segment<2>(2 * j) = sqrt_info_[j] * (antenna - graph_.gnss[j].position_m);
      Eigen::Matrix<double, 2, 3> d;
      d << 1.0, 0.0, -s * lever_arm_.x() - c * lever_arm_.y(), 0.0, 1.0, c * lever_arm_.x() - s * lever_arm_.y();
      dz.block<2, 3>(2 * j, 3 * block_of_fix_[j]) = sqrt_info_[j] * d;
    }
    // r = (L^-1 kron I2) z, with axes interleaved per fix.
    const auto whiten = [&](const Eigen::MatrixXd& m) {
      Eigen::MatrixXd out(m.rows(), m.cols());
      for (int axis = 0; axis < 2; ++axis) {
        Eigen::MatrixXd rows(n, m.cols());
        for (int j = 0; j < n; ++j) rows.row(j) = m.row(2 * j + axis);
        rows = whitening_ * rows;
        for (int j = 0; j < n; ++j) out.row(2 * j + axis) = rows.row(j);
      }
      return out;
    };
    Eigen::Map<Eigen::VectorXd>(residuals, 2 * n) = whiten(z);
    if (jacobians != nullptr) {
      const Eigen::MatrixXd jr = whiten(dz);
      for (int b = 0; b < blocks; ++b) {
        if (jacobians[b] == nullptr) continue;
        Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>(jacobians[b], 2 * n, 3) =
            jr.middleCols<3>(3 * b);
      }
    }
    return true;
  }

 private:
  const PassageGraph& graph_;
  Eigen::Vector2d lever_arm_;
  std::vector<int> block_of_fix_;
  Eigen::MatrixXd whitening_;
  std::vector<Eigen::Matrix2d> sqrt_info_;
};

}  // namespace

absl::StatusOr<PassageFisherInformation> PassageLandmarkInformation(
    const Passage& passage, const GraphOptions& options, const std::function<Pose2(double)>& true_pose,
    const std::function<std::optional<Eigen::Vector2d>(LandmarkId)>& true_landmark,
    std::optional<double> true_camera_yaw_offset_rad) {
  if (!options.frame_origin) return absl::InvalidArgumentError("frame_origin: must be set (the truth's frame)");
  GraphOptions graph_options = options;
  graph_options.refine_initial_poses = false;  // the graph is evaluated at the truth, not solved
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();
  std::vector<Pose2> poses;
  for (double t : graph->node_times_s) poses.push_back(true_pose(t));

  ceres::Problem::Options problem_options;
  ceres::Problem problem(problem_options);
  if (graph->gnss_correlation_time_s <= 0.0) {
    AddPoseGraphFactors(*graph, 0, graph->node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr, nullptr,
                        &poses, &problem);
  } else {
    PassageGraph odometry_only = *graph;
    odometry_only.gnss.clear();
    AddPoseGraphFactors(odometry_only, 0, graph->node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr,
                        nullptr, &poses, &problem);
    std::vector<int> block_of_fix;
    std::vector<double*> fix_blocks;
    std::map<int, int> block_of_node;
    for (const GnssObservation& o : graph->gnss) {
      auto [it, inserted] = block_of_node.emplace(o.node, static_cast<int>(fix_blocks.size()));
      if (inserted) fix_blocks.push_back(poses[o.node].data());
      block_of_fix.push_back(it->second);
    }
    problem.AddResidualBlock(new CorrelatedGnssSequence(*graph, passage.calibration.gnss_lever_arm_m, block_of_fix,
                                                        static_cast<int>(fix_blocks.size())),
                             nullptr, fix_blocks);
  }
  PassageFisherInformation out;
  std::map<LandmarkId, int> slot;
  std::vector<Eigen::Vector2d> positions;
  positions.reserve(graph->detections.size());  // no reallocation: the problem holds pointers
  std::vector<std::pair<int, const CameraObservation*>> cameras;
  for (const CameraObservation& d : graph->detections) {
    auto it = slot.find(d.landmark_id);
    if (it == slot.end()) {
      const std::optional<Eigen::Vector2d> truth = true_landmark(d.landmark_id);
      if (!truth) continue;
      it = slot.emplace(d.landmark_id, static_cast<int>(positions.size())).first;
      positions.push_back(*truth);
      out.landmarks.push_back(d.landmark_id);
    }
    cameras.emplace_back(it->second, &d);
  }
  double yaw_offset_rad = true_camera_yaw_offset_rad.value_or(0.0);
  for (const auto& [k, d] : cameras) {
    AddCameraResidual(d->u_px, passage.noise.pixel_sigma_px, passage.calibration, nullptr, poses[d->node].data(),
                      positions[k].data(), true_camera_yaw_offset_rad ? &yaw_offset_rad : nullptr, &problem);
  }
  std::vector<ceres::ResidualBlockId> residuals;
  problem.GetResidualBlocks(&residuals);
  std::vector<double*> blocks;
  for (Eigen::Vector2d& p : positions) blocks.push_back(p.data());
  if (true_camera_yaw_offset_rad && !cameras.empty()) {
    blocks.push_back(&yaw_offset_rad);
    out.camera_yaw_vehicle = passage.vehicle_id;
  }
  absl::StatusOr<LandmarkInformation> information = EliminateToLandmarks(&problem, residuals, blocks);
  if (!information.ok()) return information.status();
  out.information = std::move(information->information);
  return out;
}

int CramerRaoBound::Grow(int rows) {
  const int at = dim_;
  dim_ += rows;
  // The capacity doubles: with a yaw state per vehicle, a new variable comes with nearly every
  // passage.
  if (dim_ > information_.rows()) {
    const int capacity = std::max(dim_, 2 * static_cast<int>(information_.rows()));
    information_.conservativeResizeLike(Eigen::MatrixXd::Zero(capacity, capacity));
  }
  return at;
}

void CramerRaoBound::Add(const PassageFisherInformation& passage) {
  // Each of the passage's rows and where it goes.
  std::vector<int> to;
  for (LandmarkId id : passage.landmarks) {
    auto it = landmark_offset_.find(id);
    if (it == landmark_offset_.end()) {
      it = landmark_offset_.emplace(id, Grow(2)).first;
      if (landmark_prior_sigma_m_ > 0.0) {
        const double prior = 1.0 / (landmark_prior_sigma_m_ * landmark_prior_sigma_m_);
        information_(it->second, it->second) += prior;
        information_(it->second + 1, it->second + 1) += prior;
      }
    }
    to.push_back(it->second);
    to.push_back(it->second + 1);
  }
  if (passage.camera_yaw_vehicle) {
    auto it = vehicle_offset_.find(*passage.camera_yaw_vehicle);
    if (it == vehicle_offset_.end()) {
      it = vehicle_offset_.emplace(*passage.camera_yaw_vehicle, Grow(1)).first;
      if (camera_yaw_prior_sigma_rad_ > 0.0) {
        information_(it->second, it->second) += 1.0 / (camera_yaw_prior_sigma_rad_ * camera_yaw_prior_sigma_rad_);
      }
    }
    to.push_back(it->second);
  }
  for (size_t a = 0; a < to.size(); ++a) {
    for (size_t b = 0; b < to.size(); ++b) information_(to[a], to[b]) += passage.information(a, b);
  }
}

absl::StatusOr<Eigen::MatrixXd> CramerRaoBound::Inverse() const {
  const auto information = information_.topLeftCorner(dim_, dim_);
  const Eigen::LLT<Eigen::MatrixXd> llt(0.5 * (information + information.transpose()));
  if (llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError("Cramer-Rao bound: the passages' information does not determine every landmark");
  }
  return Eigen::MatrixXd(llt.solve(Eigen::MatrixXd::Identity(dim_, dim_)));
}

absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> CramerRaoBound::Covariances() const {
  std::map<LandmarkId, Eigen::Matrix2d> out;
  if (landmark_offset_.empty()) return out;
  absl::StatusOr<Eigen::MatrixXd> cov = Inverse();
  if (!cov.ok()) return cov.status();
  for (const auto& [id, i] : landmark_offset_) out[id] = cov->block<2, 2>(i, i);
  return out;
}

absl::StatusOr<Eigen::MatrixXd> CramerRaoBound::JointCovariance(const std::vector<LandmarkId>& ids) const {
  std::vector<int> rows;
  for (LandmarkId id : ids) {
    const auto it = landmark_offset_.find(id);
    if (it == landmark_offset_.end()) {
      return absl::InvalidArgumentError(absl::StrCat("Cramer-Rao bound: no passage saw landmark ", id));
    }
    rows.push_back(it->second);
    rows.push_back(it->second + 1);
  }
  if (rows.empty()) return Eigen::MatrixXd(0, 0);
  absl::StatusOr<Eigen::MatrixXd> cov = Inverse();
  if (!cov.ok()) return cov.status();
  return Eigen::MatrixXd((*cov)(rows, rows));
}

double ExpectedDistance(const Eigen::Matrix2d& cov) {
  // e = (a x, b y) along the principal axes with x, y standard normal: in polar coordinates
  // |e| = r sqrt(a^2 cos^2 t + b^2 sin^2 t), r Rayleigh with mean sqrt(pi / 2), t uniform.
  const Eigen::Vector2d lambda =
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(0.5 * (cov + cov.transpose())).eigenvalues().cwiseMax(0.0);
  constexpr int kSteps = 256;
  double mean = 0.0;
  for (int k = 0; k < kSteps; ++k) {
    const double t = 2.0 * M_PI * (k + 0.5) / kSteps;
    mean += std::sqrt(lambda(0) * std::cos(t) * std::cos(t) + lambda(1) * std::sin(t) * std::sin(t)) / kSteps;
  }
  return std::sqrt(M_PI / 2.0) * mean;
}

}  // namespace crowdmap
