#include "core/estimation/cramer_rao.h"

#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"
#include "core/estimation/graph_linearization.h"

namespace crowdmap {

absl::StatusOr<PassageFisherInformation> PassageLandmarkInformation(
    const Passage& passage, const GraphOptions& options, const std::function<Pose2(double)>& true_pose,
    const std::function<std::optional<Eigen::Vector2d>(LandmarkId)>& true_landmark) {
  if (!options.frame_origin) return absl::InvalidArgumentError("frame_origin: must be set (the truth's frame)");
  GraphOptions graph_options = options;
  graph_options.refine_initial_poses = false;  // the graph is evaluated at the truth, not solved
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();
  std::vector<Pose2> poses;
  for (double t : graph->node_times_s) poses.push_back(true_pose(t));

  ceres::Problem::Options problem_options;
  ceres::Problem problem(problem_options);
  AddPoseGraphFactors(*graph, 0, graph->node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr, &poses,
                      &problem);
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
  for (const auto& [k, d] : cameras) {
    problem.AddResidualBlock(CameraFactor::Create(d->u_px, passage.noise.pixel_sigma_px, passage.calibration), nullptr,
                             poses[d->node].data(), positions[k].data());
  }
  std::vector<ceres::ResidualBlockId> residuals;
  problem.GetResidualBlocks(&residuals);
  std::vector<double*> blocks;
  for (Eigen::Vector2d& p : positions) blocks.push_back(p.data());
  absl::StatusOr<LandmarkInformation> information = EliminateToLandmarks(&problem, residuals, blocks);
  if (!information.ok()) return information.status();
  out.information = std::move(information->information);
  return out;
}

void CramerRaoBound::Add(const PassageFisherInformation& passage) {
  std::vector<int> at;
  for (LandmarkId id : passage.landmarks) {
    auto [it, inserted] = index_.emplace(id, static_cast<int>(index_.size()));
    at.push_back(it->second);
  }
  const int n = 2 * static_cast<int>(index_.size());
  if (information_.rows() < n) information_.conservativeResizeLike(Eigen::MatrixXd::Zero(n, n));
  for (size_t a = 0; a < at.size(); ++a) {
    for (size_t b = 0; b < at.size(); ++b) {
      information_.block<2, 2>(2 * at[a], 2 * at[b]) += passage.information.block<2, 2>(2 * a, 2 * b);
    }
  }
}

absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> CramerRaoBound::Covariances() const {
  std::map<LandmarkId, Eigen::Matrix2d> out;
  if (index_.empty()) return out;
  const Eigen::LLT<Eigen::MatrixXd> llt(0.5 * (information_ + information_.transpose()));
  if (llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError("Cramer-Rao bound: the passages' information does not determine every landmark");
  }
  const Eigen::MatrixXd cov = llt.solve(Eigen::MatrixXd::Identity(information_.rows(), information_.cols()));
  for (const auto& [id, i] : index_) out[id] = cov.block<2, 2>(2 * i, 2 * i);
  return out;
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
