#include "core/estimation/map_updater.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <unordered_set>

#include <ceres/ceres.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/estimation/factors.h"
#include "core/estimation/gnss_correlation.h"
#include "core/estimation/graph_builder.h"
#include "core/estimation/graph_linearization.h"
#include "core/estimation/landmark_update.h"
#include "core/estimation/passage_exclusion.h"
#include "core/estimation/passage_prior.h"
#include "core/estimation/subdivision.h"
#include "core/estimation/subgraph_steps.h"
#include "core/estimation/vehicle_calibration.h"

namespace crowdmap {
namespace {

// Passage-wide bookkeeping across its subgraphs.
struct PassageProgress {
  std::unordered_set<LandmarkId> counted;  // passages_seen already incremented
  std::unordered_set<LandmarkId> created;
  std::unordered_set<LandmarkId> updated;
  std::unordered_set<LandmarkId> conditioned;
  // Landmarks whose detections are set aside for the rest of the passage (LandmarksToSetAside).
  std::unordered_set<LandmarkId> held_back;
  // Detections set aside as outliers (OutlierDetections), by node and landmark.
  std::set<DetectionKey> outliers;
  // With the camera yaw estimated: the vehicle's record when the passage started (VehicleCameraYawPrior:
  // a new vehicle's prior), its offset applied to the calibration the passage is solved with (each
  // subgraph's yaw state is the further offset). The prior of a subgraph before the first one that
  // records the vehicle.
  VehicleCalibration vehicle_at_start;
  bool vehicle_counted = false;  // the vehicle's passage count incremented
};

// What a solve shows must be left out before anything is committed: the subgraph is solved again
// without it.
struct SetAsideRequest {
  std::vector<LandmarkId> landmarks;
  std::vector<DetectionKey> detections;
  bool empty() const { return landmarks.empty() && detections.empty(); }
};

// One camera residual of a subgraph's problem, for the outlier test.
struct CameraResidual {
  ceres::ResidualBlockId id;
  DetectionKey key;
};

// The detections whose residual at the solution exceeds options.max_detection_residual_sigmas
// pixel sigmas: a detection of another landmark reported under this one's id, or a false one. A
// Gaussian pixel error goes beyond 5 sigma once in two million.
std::vector<DetectionKey> OutlierDetections(ceres::Problem* problem, const std::vector<CameraResidual>& residuals,
                                            const MapUpdateOptions& options) {
  std::vector<DetectionKey> out;
  if (options.max_detection_residual_sigmas <= 0.0) return out;
  for (const CameraResidual& r : residuals) {
    double cost = 0.0, residual = 0.0;
    const bool evaluated = problem->EvaluateResidualBlock(r.id, /*apply_loss_function=*/false, &cost, &residual, nullptr);
    if (!evaluated || std::abs(residual) > options.max_detection_residual_sigmas) out.push_back(r.key);
  }
  return out;
}

// The landmarks whose detections a solve shows to be unfit for the map, which the subgraph is
// solved again without: new landmarks that its rays leave poorly determined (see
// WellDeterminedNewLandmark), and map landmarks it moves further from their map estimate than the
// map's own uncertainty allows (options.max_landmark_shift_mahalanobis2: the passage and the map
// disagree about them, a wrong association or a wrong map; either way the passage's
// detections of them are not trusted).
std::vector<LandmarkId> LandmarksToSetAside(const LandmarkUpdate& update, const SubgraphLandmarks& landmarks,
                                            const std::vector<Pose2>& poses, const NodeRange& range,
                                            const Passage& passage, const MapUpdateOptions& options,
                                            PassageUpdateSummary* summary) {
  std::vector<LandmarkId> unfit;
  for (int i = 0; i < update.size(); ++i) {
    if (update.in_map(i)) {
      if (options.max_landmark_shift_mahalanobis2 > 0.0 &&
          update.PriorShiftMahalanobis2(i) > options.max_landmark_shift_mahalanobis2) {
        unfit.push_back(update.id(i));
        ++summary->landmarks_disagreeing;
      }
      continue;
    }
    const RayGeometry geometry = NewLandmarkGeometry(poses, range.first, landmarks.detections[i], update.position(i),
                                                     passage.calibration, passage.noise.pixel_sigma_px);
    if (!WellDeterminedNewLandmark(geometry, options)) {
      unfit.push_back(update.id(i));
      ++summary->landmarks_held_back;
    }
  }
  return unfit;
}

// The new landmarks whose second-order bias correction moved them further from the solution
// (`solved`, in update order) than options.max_new_landmark_bias_sigmas of their sigmas: where the
// correction is larger than the uncertainty, the Gaussian the update would take in is not the
// landmark's (rays that barely cross, linearised at a point metres off along them), and the map
// would hold it with a covariance that does not show it. Held back as WellDeterminedNewLandmark's
// are; a later passage creates them.
std::vector<LandmarkId> NewLandmarksBentByTheirBias(const LandmarkUpdate& update,
                                                    const std::vector<Eigen::Vector2d>& solved,
                                                    const GraphLinearization& linearization,
                                                    const MapUpdateOptions& options) {
  std::vector<LandmarkId> unfit;
  if (!options.bias_correction || options.max_new_landmark_bias_sigmas <= 0.0) return unfit;
  const double limit2 = options.max_new_landmark_bias_sigmas * options.max_new_landmark_bias_sigmas;
  for (int i = 0; i < update.size(); ++i) {
    if (update.in_map(i)) continue;
    const Eigen::Vector2d shift = update.position(i) - solved[i];
    const Eigen::Matrix2d cov = linearization.landmark_covariance().block<2, 2>(2 * i, 2 * i);
    if (shift.dot(cov.ldlt().solve(shift)) > limit2) unfit.push_back(update.id(i));
  }
  return unfit;
}

// Builds, solves and commits one subgraph. No map change if it sees no landmark. When the solve
// shows outlier detections or landmarks unfit for the map, commits nothing and returns them (the
// caller sets them aside and calls again).
absl::StatusOr<SetAsideRequest> UpdateFromSubgraph(const Passage& passage, const PassageGraph& graph,
                                                   const NodeRange& range, const MapUpdateOptions& options,
                                                   PassagePrior* passage_prior, MapOverlay* map,
                                                   PassageProgress* progress, PassageUpdateSummary* summary) {
  const Calibration& calib = passage.calibration;
  SubgraphLandmarks landmarks = GroupDetections(graph, range, *map);
  summary->detections_dropped += SetAside(progress->held_back, progress->outliers, &landmarks);
  if (landmarks.ids.empty()) return SetAsideRequest{};
  std::vector<Pose2> poses(graph.initial_poses.begin() + range.first, graph.initial_poses.begin() + range.last + 1);
  const auto solve_start = std::chrono::steady_clock::now();
  InitializePoses(graph, range, passage, options, &landmarks, &poses);
  // The vehicle's estimate so far, earlier subgraphs of the passage included.
  const VehicleCalibration* recorded = map->FindVehicle(passage.vehicle_id);
  VehicleCalibration vehicle = recorded != nullptr ? *recorded : progress->vehicle_at_start;
  const double yaw_base_rad = progress->vehicle_at_start.camera_yaw_offset_rad;
  // The camera yaw offset's state, relative to the calibration the passage is solved with.
  double yaw_offset_rad = vehicle.camera_yaw_offset_rad - yaw_base_rad;
  // New landmarks are triangulated, and detections kept only in front of the camera, with the
  // camera as the solve starts (turned by the offset earlier subgraphs estimated): a detection in
  // front of the declared camera but behind the turned one fails the solve's first evaluation.
  Calibration start_calib = calib;
  if (options.estimate_camera_yaw) start_calib.camera_yaw_rad += yaw_offset_rad;
  summary->detections_dropped +=
      InitializeLandmarks(poses, range, start_calib, options.edge_margin_sigmas * passage.noise.pixel_sigma_px,
                          options.min_new_landmark_parallax_rad, options.min_new_landmark_detections, &landmarks);
  if (landmarks.ids.empty()) return SetAsideRequest{};

  LandmarkUpdate update(graph.frame, map, landmarks.ids);
  // Weights of the passage's measurements, per sensor: 1 until a consistency test asks for inflation.
  MeasurementWeights weights;
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  // The measurement weight scales every measurement residual; the map prior is never weighted.
  // The wheel-speed scale: this subgraph's own state, its prior the same in every subgraph.
  double speed_scale = 1.0;
  double* speed_scale_block = options.speed_scale_prior_sigma > 0.0 ? &speed_scale : nullptr;
  AddPoseGraphFactors(graph, range.first, range.last, calib.gnss_lever_arm_m,
                      weights.loss(MeasurementWeights::kOdometry), weights.loss(MeasurementWeights::kGnss), &poses,
                      &problem, /*independent_fixes=*/false, speed_scale_block);
  if (speed_scale_block != nullptr) {
    problem.AddResidualBlock(ScalarPriorFactor::Create(1.0, options.speed_scale_prior_sigma), nullptr,
                             speed_scale_block);
  }
  ceres::ResidualBlockId yaw_prior = nullptr;
  if (options.estimate_camera_yaw) {
    yaw_prior = problem.AddResidualBlock(
        ScalarPriorFactor::Create(yaw_offset_rad, std::sqrt(vehicle.camera_yaw_variance_rad2)), nullptr,
        &yaw_offset_rad);
  }
  std::vector<CameraResidual> camera_residuals;
  for (int i = 0; i < update.size(); ++i) {
    if (!update.in_map(i)) Eigen::Map<Eigen::Vector2d>(update.block(i)) = landmarks.initial[i];
    problem.AddParameterBlock(update.block(i), 2);
    for (const CameraObservation* d : landmarks.detections[i]) {
      const ceres::ResidualBlockId id = AddCameraResidual(
          d->u_px, passage.noise.pixel_sigma_px, calib, weights.loss(MeasurementWeights::kCamera),
          poses[d->node - range.first].data(),
          update.block(i), options.estimate_camera_yaw ? &yaw_offset_rad : nullptr, &problem);
      camera_residuals.push_back({id, {d->node, d->landmark_id}});
      ++summary->detections_used;
    }
  }
  const bool correlated = options.strategy != UpdateStrategy::kDecorrelated;
  LandmarkUpdateOptions update_options;
  update_options.correlated = correlated;
  update_options.passage_prior = passage_prior;
  update_options.window.hops = options.window_hops;
  update_options.vehicle_id = passage.vehicle_id;
  update_options.passage_id = passage.passage_id;
  if (absl::Status s = update.AddMapPrior(update_options, &problem); !s.ok()) return s;

  ceres::Solver::Summary solver_summary;
  Solve(options, SubgraphSolveOptions(options.max_solver_iterations), &problem, &solver_summary);
  summary->solver_iterations += static_cast<int>(solver_summary.iterations.size());
  if (!solver_summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("solver result unusable: ", solver_summary.message));
  }
  if (std::vector<DetectionKey> outliers = OutlierDetections(&problem, camera_residuals, options); !outliers.empty()) {
    summary->detections_outliers += static_cast<int>(outliers.size());
    return SetAsideRequest{{}, std::move(outliers)};
  }
  const int dof = problem.NumResiduals() - problem.NumParameters();
  double chi2 = 2.0 * solver_summary.final_cost;
  if (options.max_chi2_per_dof > 0.0 && dof > 0 && chi2 > options.max_chi2_per_dof * dof) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "inconsistent: the solution leaves chi2=%.1f for %d degrees of freedom (%.2f per degree, limit %.2f): "
        "the passage's measurements contradict their noise model or the map",
        chi2, dof, chi2 / dof, options.max_chi2_per_dof));
  }
  if (const double variance_factor = VarianceFactor(chi2, dof, options.inflation_test_sigmas); variance_factor > 1.0) {
    summary->max_variance_factor = std::max(summary->max_variance_factor, variance_factor);
    weights.InflateAll(variance_factor);
    Solve(options, SubgraphSolveOptions(options.max_solver_iterations), &problem, &solver_summary);
    summary->solver_iterations += static_cast<int>(solver_summary.iterations.size());
    if (!solver_summary.IsSolutionUsable()) {
      return absl::InternalError(absl::StrCat("solver result unusable after inflation: ", solver_summary.message));
    }
    chi2 = 2.0 * solver_summary.final_cost;
  }
  summary->solve_ms += MillisecondsSince(solve_start);
  // Before the linearisation, which needs every landmark determined; again below if the sensors'
  // own tests weight the solution anew. The creation rule judges the rays with the declared pixel
  // sigma: with the camera's weighted one it held back more new landmarks, and a 12-passage city
  // map with 2% of its detections mislabelled ended at NEES/dof 2.51 instead of 1.49.
  const auto set_aside = [&] {
    return LandmarksToSetAside(update, landmarks, poses, range, passage, options, summary);
  };
  if (std::vector<LandmarkId> unfit = set_aside(); !unfit.empty()) return SetAsideRequest{std::move(unfit), {}};
  const std::array<double, MeasurementWeights::kSensors> tested_factors = weights.factors();

  std::vector<double*> landmark_blocks;
  for (int i = 0; i < update.size(); ++i) landmark_blocks.push_back(update.block(i));
  // The map's factor leaves the yaw's prior out. The prior is the vehicle's record: what its
  // earlier passages said about its camera, measured against the map, and their factors are in the
  // map already. Kept in, every passage of the vehicle would add that information to the map again,
  // and the map would take the turn that all of a vehicle's passages share as known ever better
  // (docs/estimation.md, "Per-vehicle camera calibration"). The solve, its bias correction and the
  // record's update keep it (GraphLinearization's factor_covariance and factor_gradient).
  std::vector<ceres::ResidualBlockId> factor_leaves_out;
  if (yaw_prior != nullptr) factor_leaves_out.push_back(yaw_prior);
  std::vector<ceres::ResidualBlockId> blocks;
  problem.GetResidualBlocks(&blocks);
  absl::StatusOr<GraphLinearization> linearization =
      LinearizeTestingSensors(&problem, landmark_blocks, {{&blocks, &weights}},
                              SubgraphSolveOptions(options.max_solver_iterations), options, &solver_summary, summary,
                              factor_leaves_out);
  if (!linearization.ok()) return linearization.status();
  if (weights.factors() != tested_factors) {  // the solution to commit is another one
    if (std::vector<LandmarkId> unfit = set_aside(); !unfit.empty()) return SetAsideRequest{std::move(unfit), {}};
  }
  summary->final_cost += solver_summary.final_cost;
  std::vector<Eigen::Vector2d> solved(update.size());
  for (int i = 0; i < update.size(); ++i) solved[i] = update.position(i);
  if (absl::Status s = CorrectBias(&*linearization, &problem, options, summary); !s.ok()) return s;
  if (std::vector<LandmarkId> unfit = NewLandmarksBentByTheirBias(update, solved, *linearization, options);
      !unfit.empty()) {
    summary->landmarks_held_back += static_cast<int>(unfit.size());
    return SetAsideRequest{std::move(unfit), {}};
  }
  // The yaw state is eliminated with the poses in the landmarks' covariance; its own marginal, at
  // the bias-corrected solution, updates the vehicle's record.
  if (options.estimate_camera_yaw) {
    const GraphLinearization::ScalarMarginal yaw = linearization->MarginalVariance(&yaw_offset_rad);
    vehicle = ConsiderCameraYawSolve(vehicle, yaw_base_rad + yaw_offset_rad, yaw.given_landmarks,
                                     yaw.from_landmarks);
    vehicle.updated_unix_ms = passage.start_time_unix_ms;
  }
  if (speed_scale_block != nullptr) {
    const GraphLinearization::ScalarMarginal scale = linearization->MarginalVariance(speed_scale_block);
    summary->speed_scale = speed_scale;
    summary->speed_scale_sigma = std::sqrt(scale.given_landmarks + scale.from_landmarks);
  }

  const int64_t seen_ms = passage.start_time_unix_ms;
  auto touch = [&](Landmark* record) {
    if (!progress->counted.insert(record->id).second) return;
    record->passages_seen += 1;
    record->last_seen_unix_ms = std::max(record->last_seen_unix_ms, seen_ms);
  };
  absl::StatusOr<LandmarkUpdateStats> stats = update.Commit(
      linearization->factor_covariance(), linearization->factor_gradient(), update_options, touch);
  if (!stats.ok()) return stats.status();
  Yield(options);
  summary->covariance_ms += stats->covariance_ms;
  for (int i = 0; i < update.size(); ++i) {
    if (update.in_map(i)) {
      if (!progress->created.count(update.id(i))) progress->updated.insert(update.id(i));
    } else {
      progress->created.insert(update.id(i));
    }
  }
  summary->landmarks_conditioned += stats->conditioned;
  if (options.estimate_camera_yaw) {
    if (!progress->vehicle_counted) ++vehicle.passages;
    progress->vehicle_counted = true;
    vehicle.version = map->version();
    map->PutVehicle(vehicle);
    summary->camera_yaw_offset_rad = vehicle.camera_yaw_offset_rad;
    summary->camera_yaw_sigma_rad = std::sqrt(vehicle.camera_yaw_variance_rad2);
  }
  return SetAsideRequest{};
}

}  // namespace

absl::StatusOr<UpdateStrategy> ParseUpdateStrategy(std::string_view name) {
  if (name == "cc") return UpdateStrategy::kCorrelated;
  if (name == "dc") return UpdateStrategy::kDecorrelated;
  if (name == "cc-gsd") return UpdateStrategy::kCorrelatedSubdivided;
  return absl::InvalidArgumentError(absl::StrCat("strategy: unknown '", std::string(name), "' (expected cc, dc or cc-gsd)"));
}

const char* UpdateStrategyName(UpdateStrategy strategy) {
  switch (strategy) {
    case UpdateStrategy::kCorrelated:
      return "cc";
    case UpdateStrategy::kDecorrelated:
      return "dc";
    case UpdateStrategy::kCorrelatedSubdivided:
      return "cc-gsd";
  }
  return "?";
}

absl::Status MapUpdateOptions::Validate() const {
  if (max_subgraph_dim < 30) {
    return absl::InvalidArgumentError(absl::StrCat("max_subgraph_dim: must be >= 30, got ", max_subgraph_dim));
  }
  if (detections_per_landmark < 0 ||
      (detections_per_landmark > 0 && detections_per_landmark < std::max(2, min_new_landmark_detections))) {
    return absl::InvalidArgumentError(absl::StrCat(
        "detections_per_landmark: must be 0 (all) or >= ", std::max(2, min_new_landmark_detections),
        " (min_new_landmark_detections: with fewer no landmark could be created), got ", detections_per_landmark));
  }
  if (!(detection_spacing_s >= 0.0 && detection_spacing_s <= 60.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("detection_spacing_s: must lie in [0, 60] s, got ", detection_spacing_s));
  }
  if (!(detection_spacing_m >= 0.0 && detection_spacing_m <= 100.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("detection_spacing_m: must lie in [0, 100] m, got ", detection_spacing_m));
  }
  if (!(min_new_landmark_parallax_rad >= 0.0 && min_new_landmark_parallax_rad < 1.5)) {
    return absl::InvalidArgumentError(
        absl::StrCat("min_new_landmark_parallax_rad: must lie in [0, 1.5), got ", min_new_landmark_parallax_rad));
  }
  if (!(max_detection_residual_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_detection_residual_sigmas: must be >= 0 (0 = off), got ", max_detection_residual_sigmas));
  }
  if (!(max_unfit_detection_fraction >= 0.0 && max_unfit_detection_fraction < 1.0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "max_unfit_detection_fraction: must lie in [0, 1) (0 = off), got ", max_unfit_detection_fraction));
  }
  if (!(max_new_landmark_range_m > 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_new_landmark_range_m: must be > 0, got ", max_new_landmark_range_m));
  }
  if (min_new_landmark_detections < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat("min_new_landmark_detections: must be >= 2 (two rays fix a point), got ", min_new_landmark_detections));
  }
  if (!(max_landmark_shift_mahalanobis2 >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_landmark_shift_mahalanobis2: must be >= 0 (0 = off), got ", max_landmark_shift_mahalanobis2));
  }
  if (!(max_update_shift_mahalanobis2 >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_update_shift_mahalanobis2: must be >= 0 (0 = off), got ", max_update_shift_mahalanobis2));
  }
  if (!(max_new_landmark_ray_sigma_m > 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_new_landmark_ray_sigma_m: must be > 0, got ", max_new_landmark_ray_sigma_m));
  }
  if (!(max_new_landmark_bias_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_new_landmark_bias_sigmas: must be >= 0 (0 = no test), got ", max_new_landmark_bias_sigmas));
  }
  const int joint = JointSolvePassages(*this) + 1;
  if (retain_passages < 0 || (retain_passages > 0 && retain_passages < joint)) {
    return absl::InvalidArgumentError(absl::StrCat("retain_passages: must be 0 (keep all) or at least ", joint,
                                                   " (the young map's joint solves take that many again), got ",
                                                   retain_passages));
  }
  if (window_hops < 0) {
    return absl::InvalidArgumentError(absl::StrCat("window_hops: must be >= 0 (0 = whole map), got ", window_hops));
  }
  if (!(inflation_test_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("inflation_test_sigmas: must be >= 0 (0 = off), got ", inflation_test_sigmas));
  }
  if (!(sensor_test_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("sensor_test_sigmas: must be >= 0 (0 = off), got ", sensor_test_sigmas));
  }
  if (!(max_chi2_per_dof >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("max_chi2_per_dof: must be >= 0 (0 = off), got ", max_chi2_per_dof));
  }
  if (!(edge_margin_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("edge_margin_sigmas: must be >= 0 (0 = off), got ", edge_margin_sigmas));
  }
  if (!(relinearize_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("relinearize_sigmas: must be >= 0 (0 = off), got ", relinearize_sigmas));
  }
  if (relinearize_area_passages < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("relinearize_area_passages: must be >= 0 (0 = the passage's subgraphs anew), got ",
                     relinearize_area_passages));
  }
  if (relinearizations_per_passage < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("relinearizations_per_passage: must be >= 0, got ", relinearizations_per_passage));
  }
  if (!(max_joint_mahalanobis2 > 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_joint_mahalanobis2: must be > 0, got ", max_joint_mahalanobis2));
  }
  if (warmup_passages < 0) {
    return absl::InvalidArgumentError(absl::StrCat("warmup_passages: must be >= 0 (0 = off), got ", warmup_passages));
  }
  if (relinearize_until_passages < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("relinearize_until_passages: must be >= 0 (0 = off), got ", relinearize_until_passages));
  }
  if (!(camera_yaw_prior_sigma_rad > 0.0 && camera_yaw_prior_sigma_rad < 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera_yaw_prior_sigma_rad: must lie in (0, 1), got ", camera_yaw_prior_sigma_rad));
  }
  if (!(speed_scale_prior_sigma >= 0.0 && speed_scale_prior_sigma <= 0.2)) {
    return absl::InvalidArgumentError(
        absl::StrCat("speed_scale_prior_sigma: must lie in [0, 0.2] (0 = off), got ", speed_scale_prior_sigma));
  }
  if (fleet_camera_yaw_prior_vehicles < 0) {
    return absl::InvalidArgumentError(absl::StrCat("fleet_camera_yaw_prior_vehicles: must be >= 0 (0 = off), got ",
                                                   fleet_camera_yaw_prior_vehicles));
  }
  if (absl::Status s = ValidateCorrelatedGnssMinLag1(correlated_gnss_min_lag1, "correlated_gnss_min_lag1"); !s.ok()) {
    return s;
  }
  if (max_solver_iterations < 1) {
    return absl::InvalidArgumentError(absl::StrCat("max_solver_iterations: must be >= 1, got ", max_solver_iterations));
  }
  return absl::OkStatus();
}

std::string PassageUpdateSummary::Brief() const {
  return absl::StrFormat(
      "nodes=%d subgraphs=%d updated=%d created=%d held_back=%d disagreeing=%d conditioned=%d detections=%d dropped=%d "
      "outliers=%d iterations=%d "
      "variance_factor=%.2f solve_ms=%.2f covariance_ms=%.2f bias_correction_ms=%.2f bias_correction_m=%.3f "
      "total_ms=%.2f version=%d joint_passages=%d joint_rejected=%d",
      nodes, subgraphs, landmarks_updated, landmarks_created, landmarks_held_back, landmarks_disagreeing, landmarks_conditioned, detections_used,
      detections_dropped, detections_outliers, solver_iterations, max_variance_factor, solve_ms, covariance_ms, bias_correction_ms,
      max_bias_correction_m, total_ms, map_version, joint_passages, joint_rejected ? 1 : 0) +
         (camera_yaw_sigma_rad > 0.0 ? absl::StrFormat(" camera_yaw_deg=%.3f camera_yaw_sigma_deg=%.3f",
                                                        camera_yaw_offset_rad * 180.0 / M_PI,
                                                        camera_yaw_sigma_rad * 180.0 / M_PI)
                                     : std::string()) +
         SpeedScaleBrief() + GnssBrief() + SensorBrief();
}

const char* PassageSensorName(int sensor) {
  static const char* const kNames[kPassageSensors] = {"odometry", "gnss", "camera"};
  return sensor >= 0 && sensor < kPassageSensors ? kNames[sensor] : "unknown";
}

std::string PassageUpdateSummary::SensorBrief() const {
  if (std::all_of(std::begin(sensor_test_factors), std::end(sensor_test_factors), [](double f) { return f <= 1.0; })) {
    return "";
  }
  std::string out;
  for (int s = 0; s < kPassageSensors; ++s) {
    absl::StrAppendFormat(&out, " %s_factor=%.2f", PassageSensorName(s), sensor_test_factors[s]);
  }
  return out;
}

std::string PassageUpdateSummary::GnssBrief() const {
  if (gnss_residual_lag1 == 0.0) return "";
  std::string out = absl::StrFormat(" gnss_residual_lag1=%.2f", gnss_residual_lag1);
  if (gnss_correlation_time_s > 0.0) absl::StrAppendFormat(&out, " gnss_correlation_time_s=%.0f", gnss_correlation_time_s);
  return out;
}

std::string PassageUpdateSummary::SpeedScaleBrief() const {
  if (!(speed_scale_sigma > 0.0)) return "";
  return absl::StrFormat(" speed_scale=%.4f speed_scale_sigma=%.4f", speed_scale, speed_scale_sigma);
}

namespace {

// ComputePassageUpdate's work, written into `overlay`; fills `summary` but its total time.
absl::Status ApplyPassage(const Passage& declared, const MapUpdateOptions& options, MapOverlay* overlay,
                          PassageUpdateSummary* summary) {
  PassageProgress progress;
  // With the camera yaw estimated, the passage is solved (initial guesses included) with the
  // vehicle's offset so far applied to the camera yaw it declares.
  Passage calibrated;
  if (options.estimate_camera_yaw) {
    progress.vehicle_at_start = VehicleCameraYawPrior(declared.vehicle_id, options, *overlay);
    calibrated = WithVehicleCameraYaw(declared, progress.vehicle_at_start);
  }
  const Passage& passage = options.estimate_camera_yaw ? calibrated : declared;
  GraphOptions graph_options = UpdateGraphOptions(options);
  graph_options.refine_initial_poses = false;  // done per subgraph, with the map
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();
  Yield(options);

  summary->nodes = graph->node_count();
  summary->detections_dropped = graph->detections_dropped;
  if (graph->gnss_residuals) summary->gnss_residual_lag1 = graph->gnss_residuals->lag1;
  if (graph->correlated_gnss) summary->gnss_correlation_time_s = graph->correlated_gnss->correlation_time_s;
  const int max_dim = options.strategy == UpdateStrategy::kCorrelatedSubdivided ? options.max_subgraph_dim : 0;
  const std::vector<NodeRange> ranges = SubdivideGraph(*graph, max_dim);
  summary->subgraphs = static_cast<int>(ranges.size());
  // CC: the map is factorised once for the passage, and its subgraphs condition the joint
  // distribution of the landmarks it sees (PassagePrior).
  std::optional<PassagePrior> passage_prior;
  if (options.strategy != UpdateStrategy::kDecorrelated) {
    std::vector<LandmarkId> seen;
    for (const CameraObservation& d : graph->detections) seen.push_back(d.landmark_id);
    MapWindowOptions window;
    window.hops = options.window_hops;
    absl::StatusOr<PassagePrior> built = PassagePrior::Build(*overlay, seen, window);
    if (!built.ok()) {
      return absl::Status(built.status().code(), absl::StrCat("passage ", passage.passage_id, ": ", built.status().message()));
    }
    passage_prior.emplace(std::move(*built));
  }

  for (const NodeRange& range : ranges) {
    // Each round sets aside at least one more landmark or detection, so this ends.
    for (;;) {
      PassageUpdateSummary attempt = *summary;
      absl::StatusOr<SetAsideRequest> unfit =
          UpdateFromSubgraph(passage, *graph, range, options, passage_prior ? &*passage_prior : nullptr, overlay,
                             &progress, &attempt);
      if (!unfit.ok()) {
        return absl::Status(unfit.status().code(), absl::StrCat("passage ", passage.passage_id, " nodes ", range.first,
                                                                "-", range.last, ": ", unfit.status().message()));
      }
      if (unfit->empty()) {
        *summary = attempt;
        break;
      }
      summary->solver_iterations = attempt.solver_iterations;
      summary->solve_ms = attempt.solve_ms;
      summary->landmarks_held_back = attempt.landmarks_held_back;
      summary->landmarks_disagreeing = attempt.landmarks_disagreeing;
      summary->detections_outliers = attempt.detections_outliers;
      progress.held_back.insert(unfit->landmarks.begin(), unfit->landmarks.end());
      progress.outliers.insert(unfit->detections.begin(), unfit->detections.end());
    }
  }
  if (progress.counted.empty()) {
    // What set its landmarks aside, so that an operator can tell a detector's fault from a
    // trajectory's (a GNSS jump or an odometry fault leaves every ray pointing somewhere else).
    return absl::InvalidArgumentError(absl::StrFormat(
        "detections: no landmark of the passage could be estimated (%d detection(s) dropped at the initial guess, "
        "%d landmark(s) not pinned down by its rays, %d disagreeing with the map, %d detection(s) beyond %.1f sigma; "
        "a fault of its GNSS or odometry does this as well as one of its detections)",
        summary->detections_dropped, summary->landmarks_held_back, summary->landmarks_disagreeing,
        summary->detections_outliers, options.max_detection_residual_sigmas));
  }
  if (absl::Status s = CheckDetectionsFit(static_cast<int>(progress.outliers.size()),
                                          static_cast<int>(graph->detections.size()), options);
      !s.ok()) {
    return absl::Status(s.code(), absl::StrCat("passage ", passage.passage_id, ": ", s.message()));
  }
  if (passage_prior) {
    absl::StatusOr<int> conditioned = passage_prior->Finish(overlay->version(), overlay);
    if (!conditioned.ok()) {
      return absl::Status(conditioned.status().code(),
                          absl::StrCat("passage ", passage.passage_id, ": ", conditioned.status().message()));
    }
    summary->landmarks_conditioned += *conditioned;
  }
  summary->landmarks_updated = static_cast<int>(progress.updated.size());
  summary->landmarks_created = static_cast<int>(progress.created.size());
  summary->map_version = overlay->version();
  return absl::OkStatus();
}

// The delta in `overlay`, once it keeps the map's invariants.
absl::StatusOr<PassageUpdate> TakeUpdate(MapOverlay* overlay, PassageUpdateSummary summary,
                                         std::chrono::steady_clock::time_point start) {
  MapDelta delta = overlay->TakeDelta();
  if (absl::Status s = CheckDeltaInvariants(delta); !s.ok()) return s;
  summary.total_ms = MillisecondsSince(start);
  return PassageUpdate{std::move(delta), summary};
}

// Refused (FailedPrecondition naming the landmarks) when `delta` moves an established landmark
// of `map` further than options.max_update_shift_mahalanobis2 allows.
absl::Status CheckUpdateShifts(const MapDelta& delta, const MapReaderInterface& map, const MapUpdateOptions& options) {
  if (options.max_update_shift_mahalanobis2 <= 0.0) return absl::OkStatus();
  std::vector<std::pair<double, std::string>> moved;  // (sigmas, description)
  for (const auto& [id, changed] : delta.landmarks) {
    const Landmark* before = map.FindLandmark(id);
    if (before == nullptr || before->passages_seen < kEstablishedLandmarkPassages) continue;
    const Eigen::Vector2d shift = EastNorthOffset(before->position, changed.position);
    const Eigen::LDLT<Eigen::Matrix2d> cov(before->cov_en_m2);
    const double mahalanobis2 = shift.dot(cov.solve(shift));
    if (mahalanobis2 <= options.max_update_shift_mahalanobis2) continue;
    moved.emplace_back(std::sqrt(mahalanobis2),
                       absl::StrFormat("landmark %d by %.2f m (%.1f sigma)", id, shift.norm(), std::sqrt(mahalanobis2)));
  }
  if (moved.empty()) return absl::OkStatus();
  std::sort(moved.rbegin(), moved.rend());
  std::string list;
  for (size_t k = 0; k < moved.size() && k < 5; ++k) absl::StrAppend(&list, k ? ", " : "", moved[k].second);
  if (moved.size() > 5) absl::StrAppend(&list, " and ", moved.size() - 5, " more");
  return absl::FailedPreconditionError(absl::StrFormat(
      "the update would move %d established landmark(s) further than %.1f of their sigmas: %s; the map is unchanged "
      "(a fault of the passage, or noise it does not declare: GNSS errors correlated over minutes declared white "
      "give this; see NoiseModel.gnss_correlation_time_s)",
      moved.size(), std::sqrt(options.max_update_shift_mahalanobis2), list));
}

}  // namespace

absl::StatusOr<PassageUpdate> ComputePassageUpdate(const Passage& passage, const MapUpdateOptions& options,
                                                   const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  MapOverlay overlay(map);
  PassageUpdateSummary summary;
  if (absl::Status s = ApplyPassage(passage, options, &overlay, &summary); !s.ok()) return s;
  absl::StatusOr<PassageUpdate> update = TakeUpdate(&overlay, summary, start);
  if (!update.ok()) return update;
  if (absl::Status s = CheckUpdateShifts(update->delta, map, options); !s.ok()) {
    return absl::Status(s.code(), absl::StrCat("passage ", passage.passage_id, ": ", s.message()));
  }
  return update;
}

GraphOptions UpdateGraphOptions(const MapUpdateOptions& options) {
  GraphOptions graph;
  graph.detections_per_landmark = options.detections_per_landmark;
  graph.spread_detections = options.spread_detections;
  graph.detection_spacing_s = options.detection_spacing_s;
  graph.detection_spacing_m = options.detection_spacing_m;
  graph.detect_correlated_gnss = CorrelatedGnssCheck(options.correlated_gnss_min_lag1);
  return graph;
}

absl::StatusOr<PassageUpdate> ComputePassageRelinearization(const Passage& passage, const MapUpdateOptions& options,
                                                            const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  MapOverlay overlay(map);
  PassageUpdateSummary exclusion, summary;
  absl::StatusOr<std::vector<LandmarkId>> left = ExcludePassage(
      passage.vehicle_id, passage.passage_id, options, kRelinearizationMaxLeftSigmaM, &overlay, &exclusion);
  if (!left.ok()) return left.status();
  // The landmarks the passage gave most of what the map knows of them (what is left fixes them
  // less than an exclusion requires): taken again, the passage must fix them as required. One it
  // sets aside this time would be left free along a ray, and later passages could drag it
  // hundreds of metres (test RelinearizingAYoungCityMapMovesNoLandmarkFarOff).
  std::vector<LandmarkId> weak;
  for (LandmarkId id : *left) {
    if (ConditionalSigmaM(overlay, id) > options.max_new_landmark_ray_sigma_m) weak.push_back(id);
  }
  if (absl::Status s = ApplyPassage(passage, options, &overlay, &summary); !s.ok()) return s;
  for (LandmarkId id : weak) {
    if (const double sigma_m = ConditionalSigmaM(overlay, id); !(sigma_m <= options.max_new_landmark_ray_sigma_m)) {
      return absl::FailedPreconditionError(absl::StrFormat(
          "landmark %d would be left undetermined by passage %s/%s taken again (sigma %.3g m along its weakest "
          "direction, over %.3g m allowed)",
          id, passage.vehicle_id, passage.passage_id, sigma_m, options.max_new_landmark_ray_sigma_m));
    }
  }
  return TakeUpdate(&overlay, summary, start);
}

namespace {

int64_t RelinearizeUntil(const MapUpdateOptions& options) {
  return options.strategy == UpdateStrategy::kDecorrelated ? 0 : options.relinearize_until_passages;
}

}  // namespace

bool IsJointSolvePassage(int64_t count, const MapUpdateOptions& options) {
  const int64_t warmup = options.warmup_passages;
  if (count <= warmup) return true;
  if (warmup == 0 || count > RelinearizeUntil(options)) return false;
  int64_t doubling = warmup;
  while (doubling < count) doubling *= 2;
  return doubling == count;
}

int JointSolvePassages(const MapUpdateOptions& options) {
  int64_t last = options.warmup_passages;  // count of the last joint solve
  while (last > 0 && 2 * last <= RelinearizeUntil(options)) last *= 2;
  return static_cast<int>(std::max<int64_t>(0, last - 1));  // it takes the passages before it
}

MapUpdater::MapUpdater(const MapUpdateOptions& options, std::vector<Passage> applied, int64_t applied_count,
                       const MapState* map)
    : options_(options),
      kept_(std::move(applied)),
      applied_count_(std::max<int64_t>(applied_count, kept_.size())),
      taken_count_(applied_count_) {
  const size_t needed = JointSolvePassages(options_);
  if (kept_.size() > needed) kept_.resize(needed);
  if (map == nullptr) return;
  // The retained passages, in the order of their first factors.
  std::map<PassageKey, int64_t> first_factor;
  map->ForEachFactor([&](const MapFactor& f) {
    auto [it, inserted] = first_factor.try_emplace({f.vehicle_id, f.passage_id}, f.id);
    if (!inserted) it->second = std::min(it->second, f.id);
  });
  std::vector<std::pair<int64_t, PassageKey>> by_id;
  for (const auto& [key, id] : first_factor) by_id.emplace_back(id, key);
  std::sort(by_id.begin(), by_id.end());
  for (const auto& [id, key] : by_id) retained_.push_back(key);
}

size_t MapUpdater::Leaving() const {
  const size_t retain = static_cast<size_t>(options_.retain_passages);
  return retain == 0 || retained_.size() < retain ? 0 : retained_.size() + 1 - retain;
}

MapUpdater::Plan MapUpdater::PlanFor(Mode mode) const {
  Plan plan;
  plan.options = options_;
  if (mode.vouched) {
    plan.options.max_chi2_per_dof = 0.0;
    plan.options.max_landmark_shift_mahalanobis2 = 0.0;
    plan.options.max_update_shift_mahalanobis2 = 0.0;
    plan.options.max_unfit_detection_fraction = 0.0;
  }
  plan.joint = joint_next() && !mode.sequential;
  if (plan.joint) plan.kept = kept_;
  plan.applied_count = applied_count_;
  return plan;
}

absl::StatusOr<PassageUpdate> MapUpdater::ComputePlanned(const Plan& plan, const Passage& passage,
                                                         const MapReaderInterface& map) {
  if (!plan.joint) return ComputePassageUpdate(passage, plan.options, map);
  std::vector<Passage> batch = plan.kept;
  batch.push_back(passage);
  return ComputeBatchUpdate(batch, plan.options, map);
}

void MapUpdater::AddFolding(const MapReaderInterface& map, MapDelta* delta) const {
  for (size_t i = 0; i < Leaving(); ++i) {
    map.AppendPassageFactorIds(retained_[i].first, retained_[i].second, &delta->folded_factors);
  }
}

absl::StatusOr<PassageUpdate> MapUpdater::Compute(const Passage& passage, const MapReaderInterface& map,
                                                  Mode mode) const {
  absl::StatusOr<PassageUpdate> update = ComputePlanned(PlanFor(mode), passage, map);
  if (update.ok()) AddFolding(map, &update->delta);
  return update;
}

void MapUpdater::Excluded(const std::string& vehicle_id, const std::string& passage_id) {
  const PassageKey key{vehicle_id, passage_id};
  linearized_at_.erase(key);
  retained_.erase(std::remove(retained_.begin(), retained_.end(), key), retained_.end());
  const auto it = std::find_if(kept_.begin(), kept_.end(), [&](const Passage& p) {
    return p.vehicle_id == vehicle_id && p.passage_id == passage_id;
  });
  if (it != kept_.end()) kept_.erase(it);
  applied_count_ = std::max<int64_t>(0, applied_count_ - 1);
}

void MapUpdater::Applied(const Passage& passage, const MapDelta& delta) {
  const size_t leaving = Leaving();
  for (size_t i = 0; i < leaving; ++i) linearized_at_.erase(retained_[i]);
  retained_.erase(retained_.begin(), retained_.begin() + leaving);
  RecordLinearization(delta);
  const PassageKey key{passage.vehicle_id, passage.passage_id};
  if (std::find(retained_.begin(), retained_.end(), key) == retained_.end()) retained_.push_back(key);
  const int64_t kept = static_cast<int64_t>(kept_.size());
  if (kept == applied_count_ && kept < JointSolvePassages(options_)) kept_.push_back(passage);
  ++applied_count_;
  ++taken_count_;
}

void MapUpdater::RecordLinearization(const MapDelta& delta) {
  std::map<PassageKey, std::vector<std::pair<LandmarkId, LatLon>>> taken;
  for (const auto& [id, factor] : delta.added_factors) {
    auto& landmarks = taken[{factor.vehicle_id, factor.passage_id}];
    for (LandmarkId l : factor.landmarks) {
      const auto it = delta.landmarks.find(l);
      if (it != delta.landmarks.end()) landmarks.emplace_back(l, it->second.position);
    }
  }
  for (auto& [key, landmarks] : taken) linearized_at_[key] = std::move(landmarks);
}

double MapUpdater::Staleness(const std::vector<std::pair<LandmarkId, LatLon>>& landmarks,
                             const MapReaderInterface& map) {
  double largest = 0.0;
  for (const auto& [id, then] : landmarks) {
    const Landmark* now = map.FindLandmark(id);
    if (now == nullptr) continue;
    const Eigen::Vector2d moved = EastNorthOffset(then, now->position);
    largest = std::max(largest, moved.dot(now->cov_en_m2.ldlt().solve(moved)));
  }
  return largest;
}

std::optional<MapUpdater::PassageKey> MapUpdater::StalestPassage(const MapReaderInterface& map,
                                                                 const std::set<PassageKey>& skip) const {
  if (options_.relinearize_sigmas <= 0.0) return std::nullopt;
  std::optional<PassageKey> stalest;
  double largest = options_.relinearize_sigmas * options_.relinearize_sigmas;
  for (const auto& [key, landmarks] : linearized_at_) {
    if (skip.count(key) > 0) continue;
    if (const double staleness = Staleness(landmarks, map); staleness > largest) {
      largest = staleness;
      stalest = key;
    }
  }
  return stalest;
}

std::vector<MapUpdater::PassageKey> MapUpdater::AreaOf(const PassageKey& stalest, const MapReaderInterface& map) const {
  std::vector<PassageKey> area = {stalest};
  const auto it = linearized_at_.find(stalest);
  if (options_.relinearize_area_passages < 2 || it == linearized_at_.end()) return area;
  std::set<LandmarkId> its;
  for (const auto& [id, then] : it->second) its.insert(id);
  std::vector<std::pair<double, PassageKey>> neighbours;
  for (const auto& [key, landmarks] : linearized_at_) {
    if (key == stalest) continue;
    const bool shares = std::any_of(landmarks.begin(), landmarks.end(),
                                    [&](const std::pair<LandmarkId, LatLon>& l) { return its.count(l.first) > 0; });
    if (!shares) continue;
    if (const double staleness = Staleness(landmarks, map); staleness > 1.0) neighbours.emplace_back(staleness, key);
  }
  std::sort(neighbours.rbegin(), neighbours.rend());
  for (const auto& [staleness, key] : neighbours) {
    if (static_cast<int>(area.size()) >= options_.relinearize_area_passages) break;
    area.push_back(key);
  }
  return area;
}

absl::StatusOr<PassageUpdate> ComputeRelinearization(const std::vector<Passage>& area, const MapUpdateOptions& options,
                                                     const MapReaderInterface& map) {
  if (area.empty()) return absl::InvalidArgumentError("passages: nothing to re-linearise");
  if (options.relinearize_area_passages >= 1) {
    absl::StatusOr<PassageUpdate> joint = ComputeAreaRelinearization(area, options, map);
    if (joint.ok() || joint.status().code() == absl::StatusCode::kAborted) return joint;  // Aborted: read again
    spdlog::info("passage={} vehicle={} its area of {} passages not solved jointly, the passage alone instead: {}",
                 area.front().passage_id, area.front().vehicle_id, area.size(), joint.status().ToString());
  }
  return ComputePassageRelinearization(area.front(), options, map);
}

int MapUpdater::RelinearizeStale(const MapReaderInterface& map,
                                 const std::function<absl::StatusOr<Passage>(const PassageKey&)>& passage_of,
                                 const std::function<absl::Status(const PassageKey&, const PassageUpdate&)>& apply,
                                 const std::function<void(const PassageKey&, const absl::Status&)>& on_error) {
  int applied = 0;
  for (int round = 0; round < options_.relinearizations_per_passage; ++round) {
    const std::optional<PassageKey> key = StalestPassage(map);
    if (!key) break;
    std::vector<Passage> area;
    absl::Status status;
    for (const PassageKey& member : AreaOf(*key, map)) {
      absl::StatusOr<Passage> passage = passage_of(member);
      if (passage.ok()) {
        area.push_back(*std::move(passage));
      } else if (area.empty()) {
        status = passage.status();  // the stalest itself; another is just left out
        break;
      }
    }
    absl::StatusOr<PassageUpdate> update = status.ok() ? ComputeRelinearization(area, options_, map) : status;
    status = update.ok() ? apply(*key, *update) : update.status();
    if (!status.ok()) {
      RelinearizationFailed(*key);
      if (on_error) on_error(*key, status);
      continue;
    }
    Relinearized(update->delta);
    ++applied;
  }
  return applied;
}

int RelinearizeStaleInMemory(const std::function<absl::StatusOr<Passage>(const MapUpdater::PassageKey&)>& passage_of,
                             MapUpdater* updater, MapState* map) {
  return updater->RelinearizeStale(
      *map, passage_of,
      [map](const MapUpdater::PassageKey&, const PassageUpdate& update) {
        map->Apply(update.delta);
        return absl::OkStatus();
      },
      [](const MapUpdater::PassageKey& key, const absl::Status& status) {
        spdlog::warn("passage={} vehicle={} relinearization failed: {}", key.second, key.first, status.ToString());
      });
}

}  // namespace crowdmap
