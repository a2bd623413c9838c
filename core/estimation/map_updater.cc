#include "core/estimation/map_updater.h"

#include <algorithm>
#include <chrono>
#include <cmath>
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
#include "core/estimation/graph_builder.h"
#include "core/estimation/graph_linearization.h"
#include "core/estimation/landmark_update.h"
#include "core/estimation/subdivision.h"
#include "core/estimation/triangulation.h"

namespace crowdmap {
namespace {

void Yield(const MapUpdateOptions& options) {
  if (options.yield_point) options.yield_point();
}

double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

// Passage-wide bookkeeping across its subgraphs.
struct PassageProgress {
  std::unordered_set<LandmarkId> counted;  // passages_seen already incremented
  std::unordered_set<LandmarkId> created;
  std::unordered_set<LandmarkId> updated;
  std::unordered_set<LandmarkId> conditioned;
};

// The detections of one subgraph grouped by landmark, with the landmarks' initial positions.
struct SubgraphLandmarks {
  std::vector<LandmarkId> ids;
  std::vector<bool> known;  // in the map
  std::vector<Eigen::Vector2d> initial;
  std::vector<std::vector<const CameraObservation*>> detections;
};

SubgraphLandmarks GroupDetections(const PassageGraph& graph, const NodeRange& range, const MapReaderInterface& map) {
  std::map<LandmarkId, std::vector<const CameraObservation*>> by_landmark;
  for (const CameraObservation& d : graph.detections) {
    if (d.node >= range.first && d.node <= range.last) by_landmark[d.landmark_id].push_back(&d);
  }
  SubgraphLandmarks out;
  for (auto& [id, detections] : by_landmark) {
    const Landmark* known = map.FindLandmark(id);
    out.ids.push_back(id);
    out.known.push_back(known != nullptr);
    out.initial.push_back(known ? graph.frame.ToLocal(known->position) : Eigen::Vector2d::Zero());
    out.detections.push_back(std::move(detections));
  }
  return out;
}

ceres::Solver::Options SolverOptions(int max_iterations) {
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = max_iterations;
  options.function_tolerance = 1e-10;
  options.gradient_tolerance = 1e-12;
  options.parameter_tolerance = 1e-10;
  options.num_threads = 1;
  options.logging_type = ceres::SILENT;
  return options;
}

// Calls options.yield_point after every solver iteration.
class YieldEachIteration : public ceres::IterationCallback {
 public:
  explicit YieldEachIteration(const std::function<void()>& yield_point) : yield_point_(yield_point) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary&) override {
    yield_point_();
    return ceres::SOLVER_CONTINUE;
  }

 private:
  const std::function<void()>& yield_point_;
};

// ceres::Solve with options.yield_point called after each iteration and at the end.
void Solve(const MapUpdateOptions& options, ceres::Solver::Options solver_options, ceres::Problem* problem,
           ceres::Solver::Summary* summary) {
  YieldEachIteration callback(options.yield_point);
  if (options.yield_point) solver_options.callbacks.push_back(&callback);
  ceres::Solve(solver_options, problem, summary);
  Yield(options);
}

// Refines the subgraph's initial poses: odometry + GNSS + the bearings of the map landmarks held
// fixed, if any. The pixel model alone cannot start from poses tens of metres off (with coloured
// GNSS noise the GNSS-aligned guess often is), the bounded bearing residual can.
void InitializePoses(const PassageGraph& graph, const NodeRange& range, const Passage& passage,
                     const MapUpdateOptions& update_options, SubgraphLandmarks* landmarks, std::vector<Pose2>* poses) {
  ceres::Problem problem;
  AddPoseGraphFactors(graph, range.first, range.last, passage.calibration.gnss_lever_arm_m, nullptr, poses, &problem);
  for (size_t i = 0; i < landmarks->ids.size(); ++i) {
    if (!landmarks->known[i]) continue;
    for (const CameraObservation* d : landmarks->detections[i]) {
      problem.AddResidualBlock(BearingFactor::Create(d->u_px, passage.noise.pixel_sigma_px, passage.calibration),
                               nullptr, (*poses)[d->node - range.first].data(), landmarks->initial[i].data());
    }
    problem.SetParameterBlockConstant(landmarks->initial[i].data());
  }
  // Only an initial guess: it must reach the basin of the full solve, not converge tightly. It
  // gets the full solve's iteration budget: from a guess metres off it can take 20 or more
  // iterations, and one stopped short of the basin leaves the full solve in a wrong minimum (which
  // the consistency test then mistakes for a noisy passage and down-weights).
  ceres::Solver::Options options = SolverOptions(update_options.max_solver_iterations);
  options.function_tolerance = 1e-6;
  options.parameter_tolerance = 1e-6;
  ceres::Solver::Summary summary;
  Solve(update_options, options, &problem, &summary);
  // An unusable localisation leaves the poses as they were; the full solve still runs.
}

// The widest angle between two of the unit `directions`.
double WidestAngleRad(const std::vector<Eigen::Vector2d>& directions) {
  double widest = 0.0;
  for (size_t i = 0; i < directions.size(); ++i) {
    for (size_t j = i + 1; j < directions.size(); ++j) {
      const double cross = directions[i].x() * directions[j].y() - directions[i].y() * directions[j].x();
      widest = std::max(widest, std::abs(std::atan2(cross, directions[i].dot(directions[j]))));
    }
  }
  return widest;
}

// Initial positions of the new landmarks (intersection of their rays) and the detections usable
// at the initial guess: landmark in front of the camera and, for map landmarks and a positive
// `edge_margin_px`, predicted at least that far inside the image. A detector reports only
// detections inside the image, so one whose true pixel lies within a few sigma of the border has
// its noise cut on one side and is biased inwards, the same way on every passage; the prediction
// from the map does not depend on the detection, so leaving those out removes the bias without
// adding one. Landmarks that cannot be initialised, new ones with fewer than two usable rays, are
// left out. Returns the detections dropped.
int InitializeLandmarks(const std::vector<Pose2>& poses, const NodeRange& range, const Calibration& calib,
                        double edge_margin_px, double min_parallax_rad, SubgraphLandmarks* landmarks) {
  SubgraphLandmarks kept;
  int dropped = 0;
  for (size_t i = 0; i < landmarks->ids.size(); ++i) {
    const auto& detections = landmarks->detections[i];
    Eigen::Vector2d initial = landmarks->initial[i];
    if (!landmarks->known[i]) {
      RayIntersection lines;
      std::vector<Eigen::Vector2d> directions;
      for (const CameraObservation* d : detections) {
        const BearingRay ray = CameraRay(poses[d->node - range.first], calib, d->u_px);
        lines.Add(ray);
        directions.push_back(ray.direction);
      }
      std::optional<Eigen::Vector2d> p = lines.Solve();
      if (!p || WidestAngleRad(directions) < min_parallax_rad) {
        dropped += static_cast<int>(detections.size());
        continue;
      }
      initial = *p;
    }
    std::vector<const CameraObservation*> usable;
    for (const CameraObservation* d : detections) {
      double u;
      if (!ProjectLandmark(poses[d->node - range.first].data(), initial.data(), calib, &u)) continue;
      const bool near_border = u < edge_margin_px || u > calib.image_width_px - edge_margin_px;
      if (edge_margin_px > 0.0 && landmarks->known[i] && near_border) continue;
      usable.push_back(d);
    }
    if (usable.empty() || (!landmarks->known[i] && usable.size() < 2)) {
      dropped += static_cast<int>(detections.size());
      continue;
    }
    dropped += static_cast<int>(detections.size() - usable.size());
    kept.ids.push_back(landmarks->ids[i]);
    kept.known.push_back(landmarks->known[i]);
    kept.initial.push_back(initial);
    kept.detections.push_back(std::move(usable));
  }
  *landmarks = std::move(kept);
  return dropped;
}

// After a usable solve: the landmarks' marginal covariance at the solution and (if enabled) the
// second-order bias correction of the solution, with their times added to `summary`.
absl::StatusOr<GraphLinearization> LinearizeSolution(ceres::Problem* problem, const std::vector<double*>& landmark_blocks,
                                                     const MapUpdateOptions& options, PassageUpdateSummary* summary) {
  const auto covariance_start = std::chrono::steady_clock::now();
  absl::StatusOr<GraphLinearization> linearization = GraphLinearization::Compute(problem, landmark_blocks);
  if (!linearization.ok()) return linearization.status();
  summary->covariance_ms += MillisecondsSince(covariance_start);
  Yield(options);
  if (options.bias_correction) {
    BiasCorrectionStats bias;
    if (absl::Status s = linearization->CorrectSecondOrderBias(problem, &bias); !s.ok()) return s;
    summary->bias_correction_ms += bias.ms;
    summary->max_bias_correction_m = std::max(summary->max_bias_correction_m, bias.max_landmark_shift_m);
    Yield(options);
  }
  return linearization;
}

// Builds, solves and commits one subgraph. No map change if it sees no landmark.
absl::Status UpdateFromSubgraph(const Passage& passage, const PassageGraph& graph, const NodeRange& range,
                                const MapUpdateOptions& options, MapOverlay* map, PassageProgress* progress,
                                PassageUpdateSummary* summary) {
  const Calibration& calib = passage.calibration;
  SubgraphLandmarks landmarks = GroupDetections(graph, range, *map);
  if (landmarks.ids.empty()) return absl::OkStatus();
  std::vector<Pose2> poses(graph.initial_poses.begin() + range.first, graph.initial_poses.begin() + range.last + 1);
  const auto solve_start = std::chrono::steady_clock::now();
  InitializePoses(graph, range, passage, options, &landmarks, &poses);
  summary->detections_dropped +=
      InitializeLandmarks(poses, range, calib, options.edge_margin_sigmas * passage.noise.pixel_sigma_px,
                          options.min_new_landmark_parallax_rad, &landmarks);
  if (landmarks.ids.empty()) return absl::OkStatus();

  LandmarkUpdate update(graph.frame, map, landmarks.ids);
  // Weight of the passage's measurements: 1 until the consistency test asks for inflation.
  ceres::LossFunctionWrapper measurement_weight(new ceres::TrivialLoss(), ceres::TAKE_OWNERSHIP);
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  // The measurement weight scales every measurement residual; the map prior is never weighted.
  AddPoseGraphFactors(graph, range.first, range.last, calib.gnss_lever_arm_m, &measurement_weight, &poses, &problem);
  for (int i = 0; i < update.size(); ++i) {
    if (!update.in_map(i)) Eigen::Map<Eigen::Vector2d>(update.block(i)) = landmarks.initial[i];
    problem.AddParameterBlock(update.block(i), 2);
    for (const CameraObservation* d : landmarks.detections[i]) {
      problem.AddResidualBlock(CameraFactor::Create(d->u_px, passage.noise.pixel_sigma_px, calib),
                               &measurement_weight, poses[d->node - range.first].data(), update.block(i));
      ++summary->detections_used;
    }
  }
  const bool correlated = options.strategy != UpdateStrategy::kDecorrelated;
  LandmarkUpdateOptions update_options;
  update_options.correlated = correlated;
  update_options.window.hops = options.window_hops;
  update_options.vehicle_id = passage.vehicle_id;
  update_options.passage_id = passage.passage_id;
  if (absl::Status s = update.AddMapPrior(correlated, update_options.window, &problem); !s.ok()) return s;

  ceres::Solver::Summary solver_summary;
  Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
  summary->solver_iterations += static_cast<int>(solver_summary.iterations.size());
  if (!solver_summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("solver result unusable: ", solver_summary.message));
  }
  const int dof = problem.NumResiduals() - problem.NumParameters();
  double chi2 = 2.0 * solver_summary.final_cost;
  if (options.inflation_test_sigmas > 0.0 && dof > 0 &&
      chi2 > dof + options.inflation_test_sigmas * std::sqrt(2.0 * dof)) {
    const double variance_factor = chi2 / dof;
    summary->max_variance_factor = std::max(summary->max_variance_factor, variance_factor);
    measurement_weight.Reset(new ceres::ScaledLoss(nullptr, 1.0 / variance_factor, ceres::TAKE_OWNERSHIP),
                             ceres::TAKE_OWNERSHIP);
    Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
    summary->solver_iterations += static_cast<int>(solver_summary.iterations.size());
    if (!solver_summary.IsSolutionUsable()) {
      return absl::InternalError(absl::StrCat("solver result unusable after inflation: ", solver_summary.message));
    }
    chi2 = 2.0 * solver_summary.final_cost;
  }
  summary->solve_ms += MillisecondsSince(solve_start);
  summary->final_cost += solver_summary.final_cost;
  if (options.max_chi2_per_dof > 0.0 && dof > 0 && chi2 > options.max_chi2_per_dof * dof) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "solution inconsistent with the measurements: chi2=%.1f for %d degrees of freedom (limit %.1f per dof)",
        chi2, dof, options.max_chi2_per_dof));
  }

  std::vector<double*> landmark_blocks;
  for (int i = 0; i < update.size(); ++i) landmark_blocks.push_back(update.block(i));
  absl::StatusOr<GraphLinearization> linearization = LinearizeSolution(&problem, landmark_blocks, options, summary);
  if (!linearization.ok()) return linearization.status();

  const int64_t seen_ms = passage.start_time_unix_ms;
  auto touch = [&](Landmark* record) {
    if (!progress->counted.insert(record->id).second) return;
    record->passages_seen += 1;
    record->last_seen_unix_ms = std::max(record->last_seen_unix_ms, seen_ms);
  };
  absl::StatusOr<LandmarkUpdateStats> stats = update.Commit(linearization->landmark_covariance(), update_options, touch);
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
  return absl::OkStatus();
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
  if (detections_per_landmark < 0 || detections_per_landmark == 1) {
    return absl::InvalidArgumentError(absl::StrCat(
        "detections_per_landmark: must be 0 (all) or >= 2 (a new landmark needs two bearings), got ",
        detections_per_landmark));
  }
  if (!(min_new_landmark_parallax_rad >= 0.0 && min_new_landmark_parallax_rad < 1.5)) {
    return absl::InvalidArgumentError(
        absl::StrCat("min_new_landmark_parallax_rad: must lie in [0, 1.5), got ", min_new_landmark_parallax_rad));
  }
  if (window_hops < 0) {
    return absl::InvalidArgumentError(absl::StrCat("window_hops: must be >= 0 (0 = whole map), got ", window_hops));
  }
  if (!(inflation_test_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("inflation_test_sigmas: must be >= 0 (0 = off), got ", inflation_test_sigmas));
  }
  if (!(max_chi2_per_dof >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("max_chi2_per_dof: must be >= 0 (0 = off), got ", max_chi2_per_dof));
  }
  if (!(edge_margin_sigmas >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("edge_margin_sigmas: must be >= 0 (0 = off), got ", edge_margin_sigmas));
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
  if (max_solver_iterations < 1) {
    return absl::InvalidArgumentError(absl::StrCat("max_solver_iterations: must be >= 1, got ", max_solver_iterations));
  }
  return absl::OkStatus();
}

std::string PassageUpdateSummary::Brief() const {
  return absl::StrFormat(
      "nodes=%d subgraphs=%d updated=%d created=%d conditioned=%d detections=%d dropped=%d iterations=%d "
      "variance_factor=%.2f solve_ms=%.2f covariance_ms=%.2f bias_correction_ms=%.2f bias_correction_m=%.3f "
      "total_ms=%.2f version=%d joint_passages=%d joint_rejected=%d",
      nodes, subgraphs, landmarks_updated, landmarks_created, landmarks_conditioned, detections_used,
      detections_dropped, solver_iterations, max_variance_factor, solve_ms, covariance_ms, bias_correction_ms,
      max_bias_correction_m, total_ms, map_version, joint_passages, joint_rejected ? 1 : 0);
}

absl::StatusOr<PassageUpdate> ComputePassageUpdate(const Passage& passage, const MapUpdateOptions& options,
                                                   const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  GraphOptions graph_options;
  graph_options.detections_per_landmark = options.detections_per_landmark;
  graph_options.refine_initial_poses = false;  // done per subgraph, with the map
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
  if (!graph.ok()) return graph.status();
  Yield(options);

  PassageUpdateSummary summary;
  summary.nodes = graph->node_count();
  summary.detections_dropped = graph->detections_dropped;
  const int max_dim = options.strategy == UpdateStrategy::kCorrelatedSubdivided ? options.max_subgraph_dim : 0;
  const std::vector<NodeRange> ranges = SubdivideGraph(*graph, max_dim);
  summary.subgraphs = static_cast<int>(ranges.size());

  MapOverlay overlay(map);
  PassageProgress progress;
  for (const NodeRange& range : ranges) {
    if (absl::Status s = UpdateFromSubgraph(passage, *graph, range, options, &overlay, &progress, &summary); !s.ok()) {
      return absl::Status(s.code(), absl::StrCat("passage ", passage.passage_id, " nodes ", range.first, "-",
                                                 range.last, ": ", s.message()));
    }
  }
  if (progress.counted.empty()) {
    return absl::InvalidArgumentError("detections: no landmark of the passage could be estimated");
  }
  summary.landmarks_updated = static_cast<int>(progress.updated.size());
  summary.landmarks_created = static_cast<int>(progress.created.size());
  summary.map_version = overlay.version();
  summary.total_ms = MillisecondsSince(start);
  return PassageUpdate{overlay.TakeDelta(), summary};
}

namespace {

// The joint solve of ComputeBatchUpdate, started from `single`, the sequential update of the last
// passage on `map`.
absl::StatusOr<PassageUpdate> SolveJointly(const std::vector<Passage>& passages, const MapUpdateOptions& options,
                                           const MapReaderInterface& map, const PassageUpdate& single) {
  const auto start = std::chrono::steady_clock::now();
  const int count = static_cast<int>(passages.size());
  auto failed = [&](int p, const absl::Status& s) {
    return absl::Status(s.code(), absl::StrCat("passage ", passages[p].passage_id, ": ", s.message()));
  };

  // Every graph in one frame, with its odometry + GNSS poses.
  GraphOptions graph_options;
  graph_options.detections_per_landmark = options.detections_per_landmark;
  graph_options.frame_origin = LatLon{passages.front().gnss.front().lat_deg, passages.front().gnss.front().lon_deg};
  graph_options.refine_initial_poses = false;  // done piece by piece, with the map
  PassageUpdateSummary summary;
  summary.subgraphs = 1;
  summary.joint_passages = count;
  std::vector<PassageGraph> graphs;
  graphs.reserve(count);
  for (int p = 0; p < count; ++p) {
    absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passages[p], graph_options);
    if (!graph.ok()) return failed(p, graph.status());
    summary.nodes += graph->node_count();
    summary.detections_dropped += graph->detections_dropped;
    graphs.push_back(*std::move(graph));
  }
  const LocalFrame& frame = graphs.front().frame;

  // Starting point: `map` with the last passage applied on its own, the basin the sequential
  // update finds (the intersection of all rays is no start when each passage's GNSS is metres
  // off in its own way); landmarks it lacks start at the intersection of their rays.
  MapOverlay guess(map);
  for (const auto& [id, record] : single.delta.landmarks) guess.PutLandmark(record);
  std::map<LandmarkId, RayIntersection> rays;
  for (int p = 0; p < count; ++p) {
    for (const CameraObservation& d : graphs[p].detections) {
      rays[d.landmark_id].Add(CameraRay(graphs[p].initial_poses[d.node], passages[p].calibration, d.u_px));
    }
  }
  std::map<LandmarkId, Eigen::Vector2d> initial;
  for (const auto& [id, lines] : rays) {
    if (const Landmark* known = guess.FindLandmark(id)) {
      initial[id] = frame.ToLocal(known->position);
    } else if (std::optional<Eigen::Vector2d> x = lines.Solve()) {
      initial[id] = *x;
    }
  }
  std::vector<std::vector<Pose2>> poses(count);
  std::vector<SubgraphLandmarks> seen(count);  // per passage: its detections of initialised landmarks
  for (int p = 0; p < count; ++p) {
    const NodeRange all{0, graphs[p].node_count() - 1};
    poses[p] = graphs[p].initial_poses;
    std::map<LandmarkId, std::vector<const CameraObservation*>> by_landmark;
    for (const CameraObservation& d : graphs[p].detections) {
      if (initial.count(d.landmark_id)) {
        by_landmark[d.landmark_id].push_back(&d);
      } else {
        ++summary.detections_dropped;
      }
    }
    for (auto& [id, detections] : by_landmark) {
      seen[p].ids.push_back(id);
      seen[p].known.push_back(true);
      seen[p].initial.push_back(initial[id]);
      seen[p].detections.push_back(std::move(detections));
    }
    // The poses are localised against `map` piece by piece, exactly as the sequential update
    // does, not against the guess: the guess holds landmarks this very passage placed, some of
    // them tens of metres off (nearly parallel rays), and held fixed as anchors they can turn the
    // poses of a sharp turn around.
    for (const NodeRange& range : SubdivideGraph(graphs[p], options.max_subgraph_dim)) {
      SubgraphLandmarks known = GroupDetections(graphs[p], range, map);
      std::vector<Pose2> piece(poses[p].begin() + range.first, poses[p].begin() + range.last + 1);
      InitializePoses(graphs[p], range, passages[p], options, &known, &piece);
      std::copy(piece.begin(), piece.end(), poses[p].begin() + range.first);
    }
    summary.detections_dropped +=
        InitializeLandmarks(poses[p], all, passages[p].calibration,
                            options.edge_margin_sigmas * passages[p].noise.pixel_sigma_px,
                            options.min_new_landmark_parallax_rad, &seen[p]);
  }

  // Landmarks with a usable detection, how many passages saw each, and when last.
  std::map<LandmarkId, int> seen_by;
  std::map<LandmarkId, int64_t> last_seen_ms;
  for (int p = 0; p < count; ++p) {
    for (LandmarkId id : seen[p].ids) {
      ++seen_by[id];
      last_seen_ms[id] = std::max(last_seen_ms[id], passages[p].start_time_unix_ms);
    }
  }
  if (seen_by.empty()) return absl::InvalidArgumentError("detections: no landmark of the passages could be estimated");
  std::vector<LandmarkId> ids;
  for (const auto& [id, n] : seen_by) ids.push_back(id);
  std::map<LandmarkId, Eigen::Vector2d> position;  // the landmarks' parameter blocks
  for (LandmarkId id : ids) position[id] = initial[id];
  std::map<LandmarkId, double*> block_of;
  std::vector<double*> landmark_blocks;
  for (auto& [id, x] : position) {
    block_of[id] = x.data();
    landmark_blocks.push_back(x.data());
  }

  // One problem; each passage's measurements carry their own weight (consistency test below).
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  std::vector<std::unique_ptr<ceres::LossFunctionWrapper>> weights;
  std::vector<std::vector<ceres::ResidualBlockId>> blocks_of(count);
  std::vector<double> landmark_dims_of(count, 0.0);  // the landmarks' dimensions, shared by detections
  std::map<LandmarkId, int> detections_of;
  for (int p = 0; p < count; ++p) {
    for (size_t i = 0; i < seen[p].ids.size(); ++i) detections_of[seen[p].ids[i]] += seen[p].detections[i].size();
  }
  for (int p = 0; p < count; ++p) {
    weights.push_back(std::make_unique<ceres::LossFunctionWrapper>(new ceres::TrivialLoss(), ceres::TAKE_OWNERSHIP));
    std::vector<ceres::ResidualBlockId> before;
    problem.GetResidualBlocks(&before);
    AddPoseGraphFactors(graphs[p], 0, graphs[p].node_count() - 1, passages[p].calibration.gnss_lever_arm_m,
                        weights[p].get(), &poses[p], &problem);
    problem.GetResidualBlocks(&blocks_of[p]);
    blocks_of[p].erase(blocks_of[p].begin(), blocks_of[p].begin() + before.size());
    for (size_t i = 0; i < seen[p].ids.size(); ++i) {
      const LandmarkId id = seen[p].ids[i];
      for (const CameraObservation* d : seen[p].detections[i]) {
        blocks_of[p].push_back(problem.AddResidualBlock(
            CameraFactor::Create(d->u_px, passages[p].noise.pixel_sigma_px, passages[p].calibration), weights[p].get(),
            poses[p][d->node].data(), block_of[id]));
        ++summary.detections_used;
      }
      landmark_dims_of[p] += 2.0 * seen[p].detections[i].size() / detections_of[id];
    }
  }

  const auto solve_start = std::chrono::steady_clock::now();
  ceres::Solver::Summary solver_summary;
  Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
  summary.solver_iterations += static_cast<int>(solver_summary.iterations.size());
  if (!solver_summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("joint solve unusable: ", solver_summary.message));
  }
  // The consistency test of UpdateFromSubgraph, passage by passage: the chi-square of each
  // passage's residuals against its share of the degrees of freedom.
  if (options.inflation_test_sigmas > 0.0) {
    bool inflated = false;
    for (int p = 0; p < count; ++p) {
      ceres::Problem::EvaluateOptions evaluate;
      evaluate.residual_blocks = blocks_of[p];
      double cost = 0.0;
      std::vector<double> residuals;
      if (!problem.Evaluate(evaluate, &cost, &residuals, nullptr, nullptr)) continue;
      const double dof = static_cast<double>(residuals.size()) - 3.0 * poses[p].size() - landmark_dims_of[p];
      const double chi2 = 2.0 * cost;
      if (dof > 0 && chi2 > dof + options.inflation_test_sigmas * std::sqrt(2.0 * dof)) {
        const double variance_factor = chi2 / dof;
        summary.max_variance_factor = std::max(summary.max_variance_factor, variance_factor);
        weights[p]->Reset(new ceres::ScaledLoss(nullptr, 1.0 / variance_factor, ceres::TAKE_OWNERSHIP),
                          ceres::TAKE_OWNERSHIP);
        inflated = true;
      }
    }
    if (inflated) {
      Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
      summary.solver_iterations += static_cast<int>(solver_summary.iterations.size());
      if (!solver_summary.IsSolutionUsable()) {
        return absl::InternalError(absl::StrCat("joint solve unusable after inflation: ", solver_summary.message));
      }
    }
  }
  summary.solve_ms = MillisecondsSince(solve_start);
  summary.final_cost = solver_summary.final_cost;
  const int dof = problem.NumResiduals() - problem.NumParameters();
  if (options.max_chi2_per_dof > 0.0 && dof > 0 && 2.0 * solver_summary.final_cost > options.max_chi2_per_dof * dof) {
    return absl::FailedPreconditionError(
        absl::StrFormat("solution inconsistent with the measurements: chi2=%.1f for %d degrees of freedom (limit %.1f "
                        "per dof)",
                        2.0 * solver_summary.final_cost, dof, options.max_chi2_per_dof));
  }

  // Each passage's own factor, at the solution: its poses are disjoint from the others', so the
  // joint information is exactly the sum of these.
  std::vector<LandmarkInformation> information(count);
  std::vector<std::vector<double*>> blocks_seen(count);
  for (int p = 0; p < count; ++p) {
    for (LandmarkId id : seen[p].ids) blocks_seen[p].push_back(block_of[id]);
    absl::StatusOr<LandmarkInformation> info = EliminateToLandmarks(&problem, blocks_of[p], blocks_seen[p]);
    if (!info.ok()) return failed(p, info.status());
    information[p] = *std::move(info);
  }
  absl::StatusOr<GraphLinearization> linearization = LinearizeSolution(&problem, landmark_blocks, options, &summary);
  if (!linearization.ok()) return linearization.status();

  // The result replaces the factors of the passages, at one new version of `map`; a passage's
  // factor carries its share of the bias correction.
  const auto covariance_start = std::chrono::steady_clock::now();
  MapOverlay overlay(map);
  std::vector<int64_t> factor_ids;
  for (LandmarkId id : ids) {
    if (map.FindLandmark(id) != nullptr) map.AppendFactorIds(id, &factor_ids);
  }
  std::set<std::pair<std::string, std::string>> batch;
  for (const Passage& passage : passages) batch.emplace(passage.vehicle_id, passage.passage_id);
  for (int64_t id : factor_ids) {
    const MapFactor* f = overlay.FindFactor(id);
    if (f != nullptr && batch.count({f->vehicle_id, f->passage_id})) overlay.RemoveFactor(id);
  }
  const bool correlated = options.strategy != UpdateStrategy::kDecorrelated;
  if (correlated) {
    // The passages' factors must sum to the joint solution: Lambda_p (x_c + c) - g_p does, with
    // x_c the corrected solution and c = Lambda^-1 sum_p g_p (zero at an exact optimum; a solve
    // stopped by its function tolerance leaves a small gradient in weakly determined directions).
    std::map<LandmarkId, int> column;
    for (LandmarkId id : ids) column.emplace(id, static_cast<int>(2 * column.size()));
    const int n = static_cast<int>(2 * ids.size());
    Eigen::MatrixXd total = Eigen::MatrixXd::Zero(n, n);
    Eigen::VectorXd gradient = Eigen::VectorXd::Zero(n);
    for (int p = 0; p < count; ++p) {
      const int k = static_cast<int>(seen[p].ids.size());
      for (int i = 0; i < k; ++i) {
        const int ci = column[seen[p].ids[i]];
        gradient.segment<2>(ci) += information[p].gradient.segment<2>(2 * i);
        for (int j = 0; j < k; ++j) {
          total.block<2, 2>(ci, column[seen[p].ids[j]]) += information[p].information.block<2, 2>(2 * i, 2 * j);
        }
      }
    }
    const Eigen::VectorXd correction = total.ldlt().solve(gradient);
    for (int p = 0; p < count; ++p) {
      const int k = static_cast<int>(seen[p].ids.size());
      Eigen::VectorXd x(2 * k), c(2 * k);
      for (int i = 0; i < k; ++i) {
        x.segment<2>(2 * i) = position[seen[p].ids[i]];
        c.segment<2>(2 * i) = correction.segment<2>(column[seen[p].ids[i]]);
      }
      MapFactor f;
      f.vehicle_id = passages[p].vehicle_id;
      f.passage_id = passages[p].passage_id;
      f.landmarks = seen[p].ids;
      f.information = information[p].information;
      f.information_vector = information[p].information * (x + c) - information[p].gradient;
      AddLocalFactor(frame, x, std::move(f), &overlay);
    }
  } else {
    // dc: one factor per landmark from the joint marginals, attributed to the last passage.
    const Eigen::MatrixXd& cov = linearization->landmark_covariance();
    for (size_t i = 0; i < ids.size(); ++i) {
      MapFactor f;
      f.vehicle_id = passages.back().vehicle_id;
      f.passage_id = passages.back().passage_id;
      f.landmarks = {ids[i]};
      f.information = cov.block<2, 2>(2 * i, 2 * i).inverse();
      f.information_vector = f.information * position[ids[i]];
      AddLocalFactor(frame, position[ids[i]], std::move(f), &overlay);
    }
  }
  const int64_t version = overlay.BumpVersion();
  auto touch = [&](Landmark* record) {
    record->passages_seen = seen_by[record->id];
    record->last_seen_unix_ms = last_seen_ms[record->id];
  };
  MapWindowOptions window;
  window.hops = correlated ? options.window_hops : 1;
  // The joint solve's marginals are the map's: no prior, every factor of the passages replaced.
  MarginalRefresh refresh;
  refresh.others = true;  // other landmarks' factors are replaced too, when the passages saw them
  absl::StatusOr<int> conditioned = ResolveAround(ids, refresh, window, version, touch, &overlay);
  if (!conditioned.ok()) return conditioned.status();
  Yield(options);
  summary.covariance_ms += MillisecondsSince(covariance_start);
  MapDelta delta = overlay.TakeDelta();
  for (const auto& [id, record] : delta.landmarks) {
    if (seen_by.count(id)) ++(map.FindLandmark(id) != nullptr ? summary.landmarks_updated : summary.landmarks_created);
  }
  summary.map_version = delta.version;
  summary.total_ms = MillisecondsSince(start);
  return PassageUpdate{std::move(delta), summary};
}

// Why the joint solution `joint` must not be used, or "" if it may: a landmark of the sequential
// update `single` that the joint solve moved out of the sequential estimate's confidence region.
// Both estimate the same landmarks from nearly the same information, so they differ by far less
// than that region, unless the joint solve converged to another minimum.
std::string JointSolutionRejected(const PassageUpdate& single, const PassageUpdate& joint, double max_mahalanobis2) {
  for (const auto& [id, sequential] : single.delta.landmarks) {
    const auto it = joint.delta.landmarks.find(id);
    if (it == joint.delta.landmarks.end()) continue;  // only conditioned by the sequential update
    const Eigen::Vector2d offset = EastNorthOffset(sequential.position, it->second.position);
    const Eigen::LDLT<Eigen::Matrix2d> cov(sequential.cov_en_m2);
    if (cov.info() != Eigen::Success || !cov.isPositive()) continue;
    const double mahalanobis2 = offset.dot(cov.solve(offset));
    if (!(mahalanobis2 <= max_mahalanobis2)) {
      return absl::StrFormat("landmark %d is %.2f m from the sequential estimate (Mahalanobis^2 %.1f > %.1f)", id,
                             offset.norm(), mahalanobis2, max_mahalanobis2);
    }
  }
  return "";
}

}  // namespace

absl::StatusOr<PassageUpdate> ComputeBatchUpdate(const std::vector<Passage>& passages,
                                                 const MapUpdateOptions& given_options, const MapReaderInterface& map) {
  if (absl::Status s = given_options.Validate(); !s.ok()) return s;
  // No border margin in the warm-up: the predictions it selects on come from a map that is still
  // metres off, and which detections are used would depend on where the solve starts, so on the
  // passages' order. The warm-up's few passages weigh little in a map of hundreds.
  MapUpdateOptions options = given_options;
  options.edge_margin_sigmas = 0.0;
  if (passages.empty()) return absl::InvalidArgumentError("passages: a joint solve needs at least one passage");
  if (passages.front().gnss.empty()) return absl::InvalidArgumentError("gnss: passage needs at least 2 GNSS fixes");
  absl::StatusOr<PassageUpdate> single = ComputePassageUpdate(passages.back(), options, map);
  if (!single.ok()) return single.status();
  absl::StatusOr<PassageUpdate> joint = SolveJointly(passages, options, map, *single);
  const std::string rejected = joint.ok() ? JointSolutionRejected(*single, *joint, options.max_joint_mahalanobis2)
                                          : std::string(joint.status().message());
  if (rejected.empty()) return joint;
  // The sequential update is a valid map change on its own: the passage is not lost.
  spdlog::warn("joint solve of {} passages not used, sequential update of passage {} instead: {}", passages.size(),
               passages.back().passage_id, rejected);
  single->summary.joint_rejected = true;
  return single;
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

MapUpdater::MapUpdater(const MapUpdateOptions& options, std::vector<Passage> applied, int64_t applied_count)
    : options_(options), kept_(std::move(applied)), applied_count_(std::max<int64_t>(applied_count, kept_.size())) {
  const size_t needed = JointSolvePassages(options_);
  if (kept_.size() > needed) kept_.resize(needed);
}

absl::StatusOr<PassageUpdate> MapUpdater::Compute(const Passage& passage, const MapReaderInterface& map) const {
  if (!joint_next()) return ComputePassageUpdate(passage, options_, map);
  std::vector<Passage> batch = kept_;
  batch.push_back(passage);
  return ComputeBatchUpdate(batch, options_, map);
}

void MapUpdater::Excluded(const std::string& vehicle_id, const std::string& passage_id) {
  const auto it = std::find_if(kept_.begin(), kept_.end(), [&](const Passage& p) {
    return p.vehicle_id == vehicle_id && p.passage_id == passage_id;
  });
  if (it != kept_.end()) kept_.erase(it);
  applied_count_ = std::max<int64_t>(0, applied_count_ - 1);
}

void MapUpdater::Applied(const Passage& passage) {
  const int64_t kept = static_cast<int64_t>(kept_.size());
  if (kept == applied_count_ && kept < JointSolvePassages(options_)) kept_.push_back(passage);
  ++applied_count_;
}

}  // namespace crowdmap
