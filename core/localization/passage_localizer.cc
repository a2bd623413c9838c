#include "core/localization/passage_localizer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <unordered_map>

#include <Eigen/Cholesky>
#include <ceres/ceres.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/estimation/factors.h"
#include "core/estimation/gnss_correlation.h"
#include "core/estimation/graph_builder.h"
#include "core/localization/dense_prior_solver.h"
#include "core/localization/pose_covariance.h"
#include "core/map/sparse_threads.h"
#include "core/model/camera_model.h"

namespace crowdmap {
namespace {

// Relative cost decrease at which the robust (gating) and the final solves stop. The robust solve
// only places the gates: 1e-4 instead of 1e-6 left the Table 5.5 reproduction as it was (`mapsim
// localize --runs 10`, seeds 1 to 5: the with-map errors within 0.01 m, but on seed 3 with 44
// landmarks one passage's solve lands in a wrong minimum under one coloured configuration or
// another, before as after).
constexpr double kGatingTolerance = 1e-4;
constexpr double kFinalTolerance = 1e-12;

// One detection of a map landmark: its graph observation and the landmark's index in the map.
struct MappedDetection {
  const CameraObservation* observation;
  int landmark;
  bool active = true;
};

// The map landmarks in the passage frame: means and joint covariance.
struct LocalPrior {
  std::vector<Eigen::Vector2d> mean;
  Eigen::MatrixXd cov;
  bool correlated = false;  // some cross-covariance is not zero
};

// The landmarks `keep` (indices into `map`, in order) with their joint covariance.
LocalizationMap Restrict(const LocalizationMap& map, const std::vector<int>& keep) {
  LocalizationMap out;
  out.version = map.version;
  const int n = static_cast<int>(keep.size());
  out.cov_en_m2.resize(2 * n, 2 * n);
  for (int a = 0; a < n; ++a) {
    out.ids.push_back(map.ids[keep[a]]);
    out.positions.push_back(map.positions[keep[a]]);
    for (int b = 0; b < n; ++b) out.cov_en_m2.block<2, 2>(2 * a, 2 * b) = map.cov_en_m2.block<2, 2>(2 * keep[a], 2 * keep[b]);
  }
  return out;
}

LocalPrior ToPassageFrame(const LocalizationMap& map, const LocalFrame& frame) {
  const int n = static_cast<int>(map.ids.size());
  LocalPrior prior;
  std::vector<Eigen::Matrix2d> rotation(n);
  for (int k = 0; k < n; ++k) {
    prior.mean.push_back(frame.ToLocal(map.positions[k]));
    rotation[k] = frame.EnToLocal(map.positions[k]);
  }
  prior.cov.resize(2 * n, 2 * n);
  for (int k = 0; k < n; ++k) {
    for (int l = 0; l < n; ++l) {
      const Eigen::Matrix2d block = map.cov_en_m2.block<2, 2>(2 * k, 2 * l);
      prior.cov.block<2, 2>(2 * k, 2 * l) = rotation[k] * block * rotation[l].transpose();
      prior.correlated |= k != l && !block.isZero(0.0);
    }
  }
  return prior;
}

// Starting poses: the odometry + GNSS poses refined against the bearings of the map landmarks held
// at their map positions (bounded residuals, robust loss): the pixel model cannot start from poses
// tens of metres off, which coloured GNSS errors produce.
void InitializePoses(const PassageGraph& graph, const Passage& passage, const LocalPrior& prior,
                     const std::vector<MappedDetection>& detections, const PassageLocalizerOptions& options,
                     std::vector<Pose2>* poses) {
  ceres::Problem problem;
  AddPoseGraphFactors(graph, 0, graph.node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr, nullptr, poses,
                      &problem);
  std::vector<Eigen::Vector2d> landmarks = prior.mean;
  for (const MappedDetection& d : detections) {
    problem.AddResidualBlock(
        BearingFactor::Create(d.observation->u_px, passage.noise.pixel_sigma_px, passage.calibration),
        new ceres::CauchyLoss(options.robust_loss_scale_sigmas), (*poses)[d.observation->node].data(),
        landmarks[d.landmark].data());
    problem.SetParameterBlockConstant(landmarks[d.landmark].data());
  }
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.max_num_iterations = options.max_solver_iterations;
  // A starting point only: with the landmarks held at their map positions most bearings lie in the
  // loss's tail and the robust solve crawls (70 iterations to 1e-6); the last 0.1% of the cost is
  // left to the pixel solves.
  solver.function_tolerance = 1e-3;
  solver.parameter_tolerance = 1e-6;
  solver.num_threads = 1;
  solver.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  FactorizeOnThisThreadOnly();
  ceres::Solve(solver, &problem, &summary);
}

// The joint problem: poses, the landmarks with (or without) their marginal map priors, the active
// detections.
struct JointProblem {
  std::unique_ptr<ceres::Problem> problem;
  std::vector<int> seen;  // landmarks with an active detection, in map order
  int parameters = 0;
};

// The gating rounds use each landmark's marginal prior (`marginal_priors`): they only need each
// landmark's disagreement with its own map position. The final solve of a correlated map has no
// prior in Ceres: SolveWithDensePrior adds the joint one.
// `yaw_offset` (nullptr: none) is the camera's yaw offset state, with its prior of `yaw_sigma`.
JointProblem BuildProblem(const PassageGraph& graph, const Passage& passage, const LocalPrior& prior,
                          const std::vector<MappedDetection>& detections, double robust_scale, bool marginal_priors,
                          std::vector<Pose2>* poses, std::vector<Eigen::Vector2d>* landmarks, double* yaw_offset,
                          double yaw_sigma) {
  JointProblem jp;
  jp.problem = std::make_unique<ceres::Problem>();
  ceres::Problem& problem = *jp.problem;
  AddPoseGraphFactors(graph, 0, graph.node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr, nullptr, poses,
                      &problem);
  jp.parameters = 3 * graph.node_count();
  std::vector<bool> seen(landmarks->size(), false);
  for (const MappedDetection& d : detections) {
    if (!d.active) continue;
    ceres::LossFunction* loss = robust_scale > 0.0 ? new ceres::CauchyLoss(robust_scale) : nullptr;
    AddCameraResidual(d.observation->u_px, passage.noise.pixel_sigma_px, passage.calibration, loss,
                      (*poses)[d.observation->node].data(), (*landmarks)[d.landmark].data(), yaw_offset, &problem);
    seen[d.landmark] = true;
  }
  if (yaw_offset != nullptr && problem.HasParameterBlock(yaw_offset)) {
    problem.AddResidualBlock(ScalarPriorFactor::Create(0.0, yaw_sigma), nullptr, yaw_offset);
    jp.parameters += 1;
  }
  for (int k = 0; k < static_cast<int>(seen.size()); ++k) {
    if (!seen[k]) continue;
    jp.seen.push_back(k);
    jp.parameters += 2;
    if (!marginal_priors) continue;
    const Eigen::Matrix2d cov = prior.cov.block<2, 2>(2 * k, 2 * k);
    problem.AddResidualBlock(new LandmarkPriorFactor(prior.mean[k], SqrtInformation(0.5 * (cov + cov.transpose()))),
                             nullptr, (*landmarks)[k].data());
  }
  return jp;
}

// The map's joint prior on `seen` (the marginal of the map's covariance on them).
DenseLandmarkPrior JointPrior(const LocalPrior& prior, const std::vector<int>& seen) {
  const int m = static_cast<int>(seen.size());
  DenseLandmarkPrior out;
  out.mean.resize(2 * m);
  out.cov.resize(2 * m, 2 * m);
  for (int a = 0; a < m; ++a) {
    out.mean.segment<2>(2 * a) = prior.mean[seen[a]];
    for (int b = 0; b < m; ++b) out.cov.block<2, 2>(2 * a, 2 * b) = prior.cov.block<2, 2>(2 * seen[a], 2 * seen[b]);
  }
  out.cov = 0.5 * (out.cov + out.cov.transpose());
  return out;
}

absl::Status Solve(const PassageLocalizerOptions& options, double function_tolerance, ceres::Problem* problem,
                   ceres::Solver::Summary* summary) {
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.max_num_iterations = options.max_solver_iterations;
  solver.function_tolerance = function_tolerance;
  solver.gradient_tolerance = 1e-12;
  solver.parameter_tolerance = 1e-12;
  solver.num_threads = 1;
  solver.logging_type = ceres::SILENT;
  FactorizeOnThisThreadOnly();
  ceres::Solve(solver, problem, summary);
  if (!summary->IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("localization solve failed: ", summary->message));
  }
  return absl::OkStatus();
}

// `camera`: the passage's calibration with the estimated yaw offset.
double WhitenedPixelResidual(const MappedDetection& d, const std::vector<Pose2>& poses,
                             const std::vector<Eigen::Vector2d>& landmarks, const Calibration& camera,
                             double pixel_sigma_px) {
  double u = 0.0;
  if (!ProjectLandmark(poses[d.observation->node].data(), landmarks[d.landmark].data(), camera, &u)) {
    return std::numeric_limits<double>::infinity();
  }
  return (u - d.observation->u_px) / pixel_sigma_px;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  const size_t mid = v.size() / 2;
  std::nth_element(v.begin(), v.begin() + mid, v.end());
  return v[mid];
}

// Gates the active detections at the current estimate; returns how many it rejected. The gates
// are scaled by the passage's own robust variance factor (never below 1): when every detection
// disagrees a little with an over-confident map, or the camera's yaw is off, the gates must still
// single out the detections that disagree much more than the others, not reject them all.
int Gate(const PassageGraph& graph, const Passage& passage, const Calibration& camera, const LocalPrior& prior,
         const std::vector<Pose2>& poses, const std::vector<Eigen::Vector2d>& landmarks,
         const PassageLocalizerOptions& options, std::vector<MappedDetection>* detections,
         std::vector<RejectedDetection>* rejected) {
  std::vector<double> residual(detections->size(), 0.0), abs_residuals;
  for (size_t i = 0; i < detections->size(); ++i) {
    if (!(*detections)[i].active) continue;
    residual[i] = WhitenedPixelResidual((*detections)[i], poses, landmarks, camera, passage.noise.pixel_sigma_px);
    abs_residuals.push_back(std::abs(residual[i]));
  }
  const int before = static_cast<int>(rejected->size());
  auto reject = [&](size_t i, bool whole_landmark) {
    MappedDetection& d = (*detections)[i];
    d.active = false;
    rejected->push_back({graph.node_times_s[d.observation->node], d.observation->landmark_id, d.observation->u_px,
                         residual[i], whole_landmark});
  };
  // The median absolute deviation of a unit normal is 0.6745.
  const double detection_scale = std::max(1.0, Median(abs_residuals) / 0.6745);
  for (size_t i = 0; i < detections->size(); ++i) {
    if ((*detections)[i].active && !(std::abs(residual[i]) <= options.detection_gate_sigmas * detection_scale)) {
      reject(i, false);
    }
  }
  // Per landmark: its detections' chi-square plus its shift from the map (marginal).
  const int n = static_cast<int>(landmarks.size());
  std::vector<double> chi2(n, 0.0);
  std::vector<int> count(n, 0);
  for (size_t i = 0; i < detections->size(); ++i) {
    const MappedDetection& d = (*detections)[i];
    if (!d.active) continue;
    chi2[d.landmark] += residual[i] * residual[i];
    ++count[d.landmark];
  }
  // The quantiles by number of detections (each a bisection: computed once per count).
  auto by_count = [](double probability) {
    return [probability, cache = std::unordered_map<int, double>()](int dof) mutable {
      auto [it, inserted] = cache.try_emplace(dof, 0.0);
      if (inserted) it->second = ChiSquareUpperQuantile(dof, probability);
      return it->second;
    };
  };
  auto median_quantile = by_count(0.5);
  auto gate_quantile = by_count(options.landmark_gate_probability);
  std::vector<double> ratios;
  for (int k = 0; k < n; ++k) {
    if (count[k] == 0) continue;
    const Eigen::Vector2d shift = landmarks[k] - prior.mean[k];
    chi2[k] += shift.dot(prior.cov.block<2, 2>(2 * k, 2 * k).ldlt().solve(shift));
    ratios.push_back(chi2[k] / median_quantile(count[k]));
  }
  const double landmark_scale = std::max(1.0, Median(ratios));
  for (int k = 0; k < n; ++k) {
    if (count[k] == 0 || chi2[k] <= landmark_scale * gate_quantile(count[k])) {
      continue;
    }
    for (size_t i = 0; i < detections->size(); ++i) {
      if ((*detections)[i].active && (*detections)[i].landmark == k) reject(i, true);
    }
  }
  return static_cast<int>(rejected->size()) - before;
}

}  // namespace

LocalizedPose MakeLocalizedPose(const LocalFrame& frame, double t_s, const Pose2& pose_m, const Eigen::Matrix3d& cov) {
  LocalizedPose p;
  p.t_s = t_s;
  p.pose_m = pose_m;
  p.pose_m.z() = NormalizeAngle(p.pose_m.z());
  p.position = frame.ToGeo(pose_m.head<2>());
  p.cov = 0.5 * (cov + cov.transpose());
  Eigen::Matrix3d to_en = Eigen::Matrix3d::Identity();
  to_en.topLeftCorner<2, 2>() = frame.EnToLocal(p.position).inverse();
  const Eigen::Vector2d forward = to_en.topLeftCorner<2, 2>() * Eigen::Vector2d(std::cos(p.pose_m.z()), std::sin(p.pose_m.z()));
  p.heading_en_rad = std::atan2(forward.y(), forward.x());
  p.cov_en = to_en * p.cov * to_en.transpose();
  return p;
}

absl::Status LocalizationMap::Validate() const {
  const int n = static_cast<int>(ids.size());
  if (static_cast<int>(positions.size()) != n) return absl::InvalidArgumentError("localization map: one position per id");
  if (cov_en_m2.rows() != 2 * n || cov_en_m2.cols() != 2 * n) {
    return absl::InvalidArgumentError(absl::StrCat("localization map: covariance must be ", 2 * n, " x ", 2 * n));
  }
  if (!cov_en_m2.allFinite()) return absl::InvalidArgumentError("localization map: covariance is not finite");
  return absl::OkStatus();
}

absl::Status PassageLocalizerOptions::Validate() const {
  if (!(robust_loss_scale_sigmas > 0.0)) return absl::InvalidArgumentError("robust_loss_scale_sigmas: must be > 0");
  if (!(detection_gate_sigmas > 0.0)) return absl::InvalidArgumentError("detection_gate_sigmas: must be > 0");
  if (!(landmark_gate_probability > 0.0 && landmark_gate_probability < 0.5)) {
    return absl::InvalidArgumentError("landmark_gate_probability: must lie in (0, 0.5)");
  }
  if (max_gating_rounds < 1) return absl::InvalidArgumentError("max_gating_rounds: must be >= 1");
  if (max_solver_iterations < 1) return absl::InvalidArgumentError("max_solver_iterations: must be >= 1");
  if (absl::Status s = ValidateCorrelatedGnssMinLag1(correlated_gnss_min_lag1, "correlated_gnss_min_lag1"); !s.ok()) {
    return s;
  }
  if (!(camera_yaw_sigma_rad >= 0.0 && camera_yaw_sigma_rad < M_PI)) {
    return absl::InvalidArgumentError("camera_yaw_sigma_rad: must lie in [0, pi)");
  }
  return absl::OkStatus();
}

double ChiSquareUpperQuantile(double dof, double probability) {
  // z with P(N(0,1) > z) = probability, by bisection on erfc.
  double lo = -10.0, hi = 10.0;
  for (int i = 0; i < 100; ++i) {
    const double mid = 0.5 * (lo + hi);
    (0.5 * std::erfc(mid / std::sqrt(2.0)) > probability ? lo : hi) = mid;
  }
  const double z = 0.5 * (lo + hi);
  if (dof == 2.0) return -2.0 * std::log(probability);
  if (dof == 1.0) {
    // z' with P(|N(0,1)| > z') = probability.
    lo = 0.0, hi = 10.0;
    for (int i = 0; i < 100; ++i) {
      const double mid = 0.5 * (lo + hi);
      (std::erfc(mid / std::sqrt(2.0)) > probability ? lo : hi) = mid;
    }
    return lo * lo;
  }
  const double a = 2.0 / (9.0 * dof);
  return dof * std::pow(std::max(0.0, 1.0 - a + z * std::sqrt(a)), 3);
}

std::string PassageLocalization::Brief() const {
  return absl::StrFormat(
      "poses=%d landmarks=%d detections=%d rejected=%d chi2=%.1f dof=%d camera_yaw_offset_rad=%.5f+-%.5f "
      "map_version=%d solve_ms=%.1f%s",
      poses.size(), landmarks_used.size(), detections_used, rejected.size(), chi2, dof, camera_yaw_offset_rad,
      camera_yaw_sigma_rad, map_version, solve_ms,
      gnss_correlation_time_s > 0.0 ? absl::StrFormat(" gnss_correlation_time_s=%.1f", gnss_correlation_time_s)
                                    : std::string());
}

absl::StatusOr<LocalizationMap> ReadLocalizationMap(const MapReaderInterface& map, const Passage& passage,
                                                    const MapWindowOptions& window) {
  LocalizationMap out;
  out.version = map.version();
  std::vector<LandmarkId> detected;
  for (const Detection& d : passage.detections) detected.push_back(d.landmark_id);
  std::sort(detected.begin(), detected.end());
  detected.erase(std::unique(detected.begin(), detected.end()), detected.end());
  for (LandmarkId id : detected) {
    const Landmark* lm = map.FindLandmark(id);
    if (lm == nullptr) continue;
    out.ids.push_back(id);
    out.positions.push_back(lm->position);
  }
  if (out.ids.empty()) {
    out.cov_en_m2.resize(0, 0);
    return out;
  }
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, out.ids, window);
  if (!cov.ok()) return cov.status();
  out.cov_en_m2 = std::move(*cov);
  return out;
}

absl::StatusOr<PassageLocalization> LocalizePassage(const Passage& passage, const LocalizationMap& map,
                                                    const PassageLocalizerOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  if (absl::Status s = map.Validate(); !s.ok()) return s;
  GraphOptions graph_options;
  graph_options.detections_per_landmark = 0;
  // InitializePoses refines the aligned dead reckoning against the GNSS and the map's bearings in
  // one solve: the graph's own GNSS-only refinement before it would be undone.
  graph_options.refine_initial_poses = false;
  graph_options.detect_correlated_gnss = CorrelatedGnssCheck(options.correlated_gnss_min_lag1);
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();

  PassageLocalization out;
  out.frame = graph->frame;
  out.map_version = map.version;
  if (graph->correlated_gnss) out.gnss_correlation_time_s = graph->correlated_gnss->correlation_time_s;
  // The map landmarks the passage detects, in map order (the map may hold many more).
  std::unordered_map<LandmarkId, int> index;
  for (size_t k = 0; k < map.ids.size(); ++k) index[map.ids[k]] = -1;
  for (const CameraObservation& o : graph->detections) {
    const auto it = index.find(o.landmark_id);
    if (it != index.end()) it->second = 0;
  }
  std::vector<int> detected;
  for (size_t k = 0; k < map.ids.size(); ++k) {
    int& slot = index[map.ids[k]];
    if (slot < 0) continue;
    slot = static_cast<int>(detected.size());
    detected.push_back(static_cast<int>(k));
  }
  const LocalizationMap seen = Restrict(map, detected);
  const LocalPrior prior = ToPassageFrame(seen, graph->frame);
  std::vector<MappedDetection> detections;
  for (const CameraObservation& o : graph->detections) {
    const auto it = index.find(o.landmark_id);
    if (it == index.end()) {
      ++out.detections_unmapped;
    } else {
      detections.push_back({&o, it->second});
    }
  }

  std::vector<Pose2> poses = graph->initial_poses;
  InitializePoses(*graph, passage, prior, detections, options, &poses);
  std::vector<Eigen::Vector2d> landmarks = prior.mean;
  // A detection whose map landmark is behind the camera at the localised initial guess cannot be
  // evaluated (and does not fit): rejected before the first solve.
  for (MappedDetection& d : detections) {
    const double r = WhitenedPixelResidual(d, poses, landmarks, passage.calibration, passage.noise.pixel_sigma_px);
    if (std::isfinite(r)) continue;
    d.active = false;
    out.rejected.push_back({graph->node_times_s[d.observation->node], d.observation->landmark_id, d.observation->u_px,
                            r, false});
  }
  // Round 0 is robust and only feeds the gates; later rounds solve the kept detections plainly
  // (a correlated map's with its joint prior) until the gates reject nothing more, or the rounds
  // run out: then the last rejections are solved without.
  JointProblem problem;
  std::vector<Eigen::Matrix3d> covariances;  // a correlated map's, from its solve
  double cost = 0.0;
  // The camera's yaw offset, when estimated, and its variance from the last solve.
  double yaw_offset = 0.0, yaw_variance = 0.0;
  double* const yaw = options.camera_yaw_sigma_rad > 0.0 ? &yaw_offset : nullptr;
  const auto camera = [&]() {
    Calibration turned = passage.calibration;
    turned.camera_yaw_rad += yaw_offset;
    return turned;
  };
  // The offset's block when the problem has it (some detection of a map landmark is kept).
  const auto yaw_blocks = [&]() {
    return yaw != nullptr && problem.problem->HasParameterBlock(yaw) ? std::vector<double*>{yaw}
                                                                      : std::vector<double*>{};
  };
  auto solve_plainly = [&]() -> absl::Status {
    problem = BuildProblem(*graph, passage, prior, detections, 0.0, /*marginal_priors=*/!prior.correlated, &poses,
                           &landmarks, yaw, options.camera_yaw_sigma_rad);
    if (!prior.correlated) {
      ceres::Solver::Summary summary;
      if (absl::Status s = Solve(options, kFinalTolerance, problem.problem.get(), &summary); !s.ok()) return s;
      cost = summary.final_cost;
      return absl::OkStatus();
    }
    std::vector<double*> blocks;
    for (int k : problem.seen) blocks.push_back(landmarks[k].data());
    DensePriorSolverOptions dense_options;
    dense_options.max_iterations = options.max_solver_iterations;
    // A tenth of a millimetre: far below any pose's uncertainty; the chord steps converge
    // linearly, so each further digit costs about one more step. The pose covariances may come
    // from a linearisation up to 10 cm and 10 mrad away (instead of a last factorisation at the
    // solution): on the LocalizePassage benchmark's passages this changed the sum of the poses'
    // sigmas by at most 3e-5 of itself, and the poses by 1e-5 m.
    dense_options.step_tolerance = 1e-4;
    dense_options.covariance_tolerance_m = 0.1;
    dense_options.covariance_tolerance_rad = 0.01;
    absl::StatusOr<DensePriorSolution> solution = SolveWithDensePrior(
        problem.problem.get(), &poses, blocks, JointPrior(prior, problem.seen), dense_options, yaw_blocks());
    if (!solution.ok()) return solution.status();
    covariances = std::move(solution->pose_covariances);
    if (!solution->angle_variances.empty()) yaw_variance = solution->angle_variances[0];
    cost = solution->cost;
    return absl::OkStatus();
  };
  {
    problem = BuildProblem(*graph, passage, prior, detections, options.robust_loss_scale_sigmas,
                           /*marginal_priors=*/true, &poses, &landmarks, yaw, options.camera_yaw_sigma_rad);
    // Its last digits do not change a decision (the robust reweighting converges linearly, a
    // dozen iterations to 1e-12).
    ceres::Solver::Summary summary;
    if (absl::Status s = Solve(options, kGatingTolerance, problem.problem.get(), &summary); !s.ok()) return s;
    Gate(*graph, passage, camera(), prior, poses, landmarks, options, &detections, &out.rejected);
  }
  bool gated = false;
  for (int round = 1; round < options.max_gating_rounds && !gated; ++round) {
    if (absl::Status s = solve_plainly(); !s.ok()) return s;
    gated = Gate(*graph, passage, camera(), prior, poses, landmarks, options, &detections, &out.rejected) == 0;
  }
  if (!gated) {
    if (absl::Status s = solve_plainly(); !s.ok()) return s;
  }
  if (!prior.correlated) {
    const std::vector<double*> others = yaw_blocks();
    std::vector<double> other_variances;
    absl::StatusOr<std::vector<Eigen::Matrix3d>> marginals =
        PoseCovariances(problem.problem.get(), &poses, &landmarks, others, &other_variances);
    if (!marginals.ok()) return marginals.status();
    covariances = *std::move(marginals);
    if (!other_variances.empty()) yaw_variance = other_variances[0];
  }
  if (!yaw_blocks().empty()) {
    out.camera_yaw_offset_rad = yaw_offset;
    out.camera_yaw_sigma_rad = std::sqrt(yaw_variance);
  }

  out.chi2 = 2.0 * cost;
  // The joint prior's residuals are not in the Ceres problem of a correlated map.
  out.dof = problem.problem->NumResiduals() + (prior.correlated ? 2 * static_cast<int>(problem.seen.size()) : 0) -
            problem.parameters;
  std::vector<bool> used(landmarks.size(), false);
  for (const MappedDetection& d : detections) {
    if (!d.active) continue;
    ++out.detections_used;
    used[d.landmark] = true;
  }
  for (size_t k = 0; k < used.size(); ++k) {
    if (used[k]) out.landmarks_used.push_back(seen.ids[k]);
  }
  for (int k = 0; k < graph->node_count(); ++k) {
    out.poses.push_back(MakeLocalizedPose(graph->frame, graph->node_times_s[k], poses[k], covariances[k]));
  }
  out.solve_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace crowdmap
