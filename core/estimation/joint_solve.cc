// The joint solve of passages: a young map's (warm-up and re-solves, ComputeBatchUpdate) and the
// retained passages of one area of a grown map (ComputeAreaRelinearization).
#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <set>
#include <unordered_map>
#include <unordered_set>

#include <Eigen/Eigenvalues>
#include <ceres/ceres.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/map/map_window.h"
#include "core/estimation/factors.h"
#include "core/estimation/landmark_update.h"
#include "core/estimation/map_updater.h"
#include "core/estimation/passage_exclusion.h"
#include "core/estimation/subgraph_steps.h"

namespace crowdmap {
namespace {

// The joint solve of `passages`. The map without their factors is its prior: nothing in a young
// map whose every factor is theirs (ComputeBatchUpdate, which gives `single`, the sequential update
// of the last passage on `map`, a map that holds the others), the rest of the map around them when
// they were all applied before (`single` null: ComputeAreaRelinearization). The landmarks of
// `held_back` are left out, their detections set aside. A landmark only the passages inform that
// their rays do not pin down at the joint solution fails the solve and is added to `*unpinned`
// (ComputeBatchUpdate solves again without it; an area's solve is refused).
absl::StatusOr<PassageUpdate> SolveJointly(const std::vector<Passage>& passages, const MapUpdateOptions& options,
                                           const MapReaderInterface& map, const PassageUpdate* single,
                                           const std::set<LandmarkId>& held_back, std::vector<LandmarkId>* unpinned) {
  const bool area = single == nullptr;
  const auto start = std::chrono::steady_clock::now();
  const int count = static_cast<int>(passages.size());
  auto failed = [&](int p, const absl::Status& s) {
    return absl::Status(s.code(), absl::StrCat("passage ", passages[p].passage_id, ": ", s.message()));
  };

  // Every graph in one frame, with its odometry + GNSS poses.
  GraphOptions graph_options = UpdateGraphOptions(options);
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
  // off in its own way). Only landmarks the sequential updates created are estimated: those they
  // hold back (too few rays, too little parallax, too far: the creation rules of
  // MapUpdateOptions) are no better determined here, and two rays can place them kilometres off.
  MapOverlay guess(map);
  if (single != nullptr) {
    for (const auto& [id, record] : single->delta.landmarks) guess.PutLandmark(record);
  }
  std::map<LandmarkId, Eigen::Vector2d> initial;
  for (int p = 0; p < count; ++p) {
    for (const CameraObservation& d : graphs[p].detections) {
      if (initial.count(d.landmark_id) || held_back.count(d.landmark_id)) continue;
      if (const Landmark* known = guess.FindLandmark(d.landmark_id)) initial[d.landmark_id] = frame.ToLocal(known->position);
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
                            options.min_new_landmark_parallax_rad, /*min_new_detections=*/2, &seen[p]);
  }

  // The map without the passages' factors, re-solved where they were: the solve's prior. A
  // landmark they alone informed leaves it. Every landmark a factor of theirs was on must be
  // estimated again: it would otherwise lose their information, down to none at all.
  const bool correlated = options.strategy != UpdateStrategy::kDecorrelated;
  MapWindowOptions window;
  window.hops = correlated ? options.window_hops : 1;
  MapOverlay overlay(map);
  const int64_t version = overlay.BumpVersion();
  std::map<LandmarkId, std::string> touched;  // a landmark their factors were on: one such passage
  for (const Passage& passage : passages) {
    std::vector<int64_t> factor_ids;
    overlay.AppendPassageFactorIds(passage.vehicle_id, passage.passage_id, &factor_ids);
    for (int64_t id : factor_ids) {
      const MapFactor* factor = overlay.FindFactor(id);
      if (factor == nullptr) return RemovedWhileRead("factor", id);
      for (LandmarkId l : factor->landmarks) touched.emplace(l, passage.passage_id);
      overlay.RemoveFactor(id);
    }
  }
  auto informed = [&](LandmarkId id) {
    return overlay.FindLandmark(id) != nullptr && overlay.Information(id, id).factors > 0;
  };

  // A landmark left with a single usable detection over all the passages (its others behind the
  // camera at the localised poses) and nothing else on it is not determined by the joint solve:
  // set it aside with it.
  std::map<LandmarkId, int> usable_detections;
  for (int p = 0; p < count; ++p) {
    for (size_t i = 0; i < seen[p].ids.size(); ++i) usable_detections[seen[p].ids[i]] += seen[p].detections[i].size();
  }
  std::unordered_set<LandmarkId> undetermined;
  for (const auto& [id, n] : usable_detections) {
    if (n < 2 && !informed(id)) undetermined.insert(id);
  }
  for (int p = 0; p < count; ++p) summary.detections_dropped += SetAside(undetermined, {}, &seen[p]);

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

  for (const auto& [id, passage_id] : touched) {
    if (!seen_by.count(id) && !(held_back.count(id) && !informed(id))) {
      return absl::FailedPreconditionError(absl::StrCat("landmark ", id, ": passage ", passage_id,
                                                        " informs it, but the joint solve could not use its "
                                                        "detections of it"));
    }
  }
  std::vector<LandmarkId> left, removed;
  for (const auto& [id, passage_id] : touched) {
    if (!informed(id)) {
      overlay.RemoveLandmark(id);
      removed.push_back(id);
      continue;
    }
    // What is left must fix the landmark as a new one is fixed. A prior weaker than that (a ray or
    // two of other passages: its mean anywhere along them) let an area's joint solve slide one 67 m
    // along it (at an 11.9 m sigma). Refused, the passages are taken one at a time instead.
    if (const double sigma_m = ConditionalSigmaM(overlay, id); !(sigma_m <= options.max_new_landmark_ray_sigma_m)) {
      return absl::FailedPreconditionError(absl::StrFormat(
          "landmark %d would be left weakly determined without the %d passages (sigma %.3g m along its weakest "
          "direction, over %.3g m allowed): not solved jointly",
          id, count, sigma_m, options.max_new_landmark_ray_sigma_m));
    }
    left.push_back(id);
  }
  if (!left.empty()) {
    MarginalRefresh refresh;
    refresh.others = true;  // information was removed: every marginal in the window grows
    absl::StatusOr<int> conditioned = ResolveAround(left, refresh, window, version, [](Landmark*) {}, &overlay);
    if (!conditioned.ok()) return conditioned.status();
  }

  // The landmarks' parameter blocks; their prior, the map without the passages (its mean is
  // where the blocks stand when it is added; the solve then starts from the guess).
  LandmarkUpdate landmarks(frame, &overlay, ids);
  std::map<LandmarkId, int> index_of;
  std::map<LandmarkId, double*> block_of;
  std::vector<double*> landmark_blocks;
  for (int i = 0; i < landmarks.size(); ++i) {
    index_of[landmarks.id(i)] = i;
    block_of[landmarks.id(i)] = landmarks.block(i);
    landmark_blocks.push_back(landmarks.block(i));
  }

  // One problem; each passage's measurements carry their own weight (consistency test below).
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  LandmarkUpdateOptions prior_options;
  prior_options.correlated = correlated;
  prior_options.window = window;
  if (absl::Status s = landmarks.AddMapPrior(prior_options, &problem); !s.ok()) return s;
  for (int i = 0; i < landmarks.size(); ++i) Eigen::Map<Eigen::Vector2d>(landmarks.block(i)) = initial[landmarks.id(i)];
  std::vector<std::unique_ptr<MeasurementWeights>> weights;
  std::vector<std::vector<ceres::ResidualBlockId>> blocks_of(count);
  std::vector<double> landmark_dims_of(count, 0.0);  // the landmarks' dimensions, shared by detections
  std::unordered_map<ceres::ResidualBlockId, const CameraObservation*> camera_blocks;  // the detection of each
  std::map<LandmarkId, int> detections_of;
  for (int p = 0; p < count; ++p) {
    for (size_t i = 0; i < seen[p].ids.size(); ++i) detections_of[seen[p].ids[i]] += seen[p].detections[i].size();
  }
  // With the camera yaw estimated: one offset per passage, each with the prior of a new vehicle
  // (the vehicles' stored estimates already hold these passages, so taking them as priors here
  // would count the passages twice). Per passage, the passages' factors stay independent. Unlike a
  // sequential update's, each factor keeps its prior: a young map has nothing else that fixes the
  // passages' yaws, and factors without it were taken at points their own information did not
  // support (docs/results.md, "The vehicle's record left out of the map's factors").
  std::vector<double> yaw_offset_rad(count, 0.0);
  // With the wheel-speed scale estimated: one scale per passage, each with the fixed prior.
  std::vector<double> speed_scale(count, 1.0);
  const bool scaled = options.speed_scale_prior_sigma > 0.0;
  for (int p = 0; p < count; ++p) {
    weights.push_back(std::make_unique<MeasurementWeights>());
    std::vector<ceres::ResidualBlockId> before;
    problem.GetResidualBlocks(&before);
    AddPoseGraphFactors(graphs[p], 0, graphs[p].node_count() - 1, passages[p].calibration.gnss_lever_arm_m,
                        weights[p]->loss(MeasurementWeights::kOdometry), weights[p]->loss(MeasurementWeights::kGnss),
                        &poses[p], &problem, /*independent_fixes=*/false,
                        scaled ? &speed_scale[p] : nullptr);
    problem.GetResidualBlocks(&blocks_of[p]);
    blocks_of[p].erase(blocks_of[p].begin(), blocks_of[p].begin() + before.size());
    if (scaled) {
      blocks_of[p].push_back(problem.AddResidualBlock(
          ScalarPriorFactor::Create(1.0, options.speed_scale_prior_sigma), nullptr, &speed_scale[p]));
    }
    if (options.estimate_camera_yaw) {
      blocks_of[p].push_back(problem.AddResidualBlock(
          ScalarPriorFactor::Create(0.0, options.camera_yaw_prior_sigma_rad), nullptr, &yaw_offset_rad[p]));
    }
    for (size_t i = 0; i < seen[p].ids.size(); ++i) {
      const LandmarkId id = seen[p].ids[i];
      for (const CameraObservation* d : seen[p].detections[i]) {
        blocks_of[p].push_back(AddCameraResidual(d->u_px, passages[p].noise.pixel_sigma_px, passages[p].calibration,
                                                 weights[p]->loss(MeasurementWeights::kCamera),
                                                 poses[p][d->node].data(), block_of[id],
                                                 options.estimate_camera_yaw ? &yaw_offset_rad[p] : nullptr, &problem));
        camera_blocks.emplace(blocks_of[p].back(), d);
        ++summary.detections_used;
      }
      // (a landmark of the prior is fixed by it: its dimensions cost the passages nothing)
      if (!landmarks.in_map(index_of[id])) landmark_dims_of[p] += 2.0 * seen[p].detections[i].size() / detections_of[id];
    }
  }

  const auto solve_start = std::chrono::steady_clock::now();
  ceres::Solver::Summary solver_summary;
  Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
  summary.solver_iterations += static_cast<int>(solver_summary.iterations.size());
  if (!solver_summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("joint solve unusable: ", solver_summary.message));
  }
  // An area's passages were each applied with the residual test of the sequential update
  // (options.max_detection_residual_sigmas): their detections beyond it are set aside here too, and
  // the solve is repeated without them. So are a young map's from its first re-solve on (more
  // passages than the warm-up's): each of its passages enters every later joint solve with all its
  // detections, and a passage's detections reported under the wrong ids moved established
  // landmarks by 3 to 4 of their sigmas through one (a 64-passage re-solve with a hostile upload;
  // its sequential update had set all but one of them aside). In the warm-up the estimate the
  // residuals are taken at may still be metres off.
  const bool outlier_test = area || count > options.warmup_passages;
  if (outlier_test && options.max_detection_residual_sigmas > 0.0) {
    int outliers = 0;
    for (int p = 0; p < count; ++p) {
      std::unordered_set<const CameraObservation*> set_aside;
      auto outlier = [&](ceres::ResidualBlockId id) {
        const auto camera = camera_blocks.find(id);
        if (camera == camera_blocks.end()) return false;
        double cost = 0.0, residual = 0.0;
        if (problem.EvaluateResidualBlock(id, /*apply_loss_function=*/false, &cost, &residual, nullptr) &&
            std::abs(residual) <= options.max_detection_residual_sigmas) {
          return false;
        }
        problem.RemoveResidualBlock(id);
        set_aside.insert(camera->second);
        ++outliers;
        return true;
      };
      blocks_of[p].erase(std::remove_if(blocks_of[p].begin(), blocks_of[p].end(), outlier), blocks_of[p].end());
      // The rays left are what the landmarks' creation rule below judges them on.
      for (std::vector<const CameraObservation*>& rays : seen[p].detections) {
        rays.erase(std::remove_if(rays.begin(), rays.end(),
                                  [&](const CameraObservation* d) { return set_aside.count(d) > 0; }),
                   rays.end());
      }
    }
    if (outliers > 0) {
      summary.detections_outliers += outliers;
      summary.detections_used -= outliers;
      Solve(options, SolverOptions(options.max_solver_iterations), &problem, &solver_summary);
      summary.solver_iterations += static_cast<int>(solver_summary.iterations.size());
      if (!solver_summary.IsSolutionUsable()) {
        return absl::InternalError(absl::StrCat("joint solve unusable without its outliers: ", solver_summary.message));
      }
    }
  }
  // At the solution as declared (before any inflation below), as UpdateFromSubgraph's limit.
  const int joint_dof = problem.NumResiduals() - problem.NumParameters();
  if (options.max_chi2_per_dof > 0.0 && joint_dof > 0 &&
      2.0 * solver_summary.final_cost > options.max_chi2_per_dof * joint_dof) {
    return absl::FailedPreconditionError(
        absl::StrFormat("solution inconsistent with the measurements: chi2=%.1f for %d degrees of freedom (limit %.1f "
                        "per dof)",
                        2.0 * solver_summary.final_cost, joint_dof, options.max_chi2_per_dof));
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
      // (a yaw offset or a speed scale is one more parameter; its prior is among the residuals)
      const double dof = static_cast<double>(residuals.size()) - 3.0 * poses[p].size() - landmark_dims_of[p] -
                         (options.estimate_camera_yaw ? 1.0 : 0.0) - (scaled ? 1.0 : 0.0);
      const double chi2 = 2.0 * cost;
      if (const double variance_factor = VarianceFactor(chi2, dof, options.inflation_test_sigmas);
          variance_factor > 1.0) {
        summary.max_variance_factor = std::max(summary.max_variance_factor, variance_factor);
        weights[p]->InflateAll(variance_factor);
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
  // Each passage's sensors tested on their own, as a subgraph's are.
  std::vector<WeightedBlocks> weighted;
  for (int p = 0; p < count; ++p) weighted.push_back({&blocks_of[p], weights[p].get()});
  absl::StatusOr<GraphLinearization> linearization =
      LinearizeTestingSensors(&problem, landmark_blocks, weighted, SolverOptions(options.max_solver_iterations),
                              options, &solver_summary, &summary);
  if (!linearization.ok()) return linearization.status();
  // A landmark only these passages informed re-enters the map as a new one would: the rays of one
  // of them must pin it down at the joint solution (WellDeterminedNewLandmark). Rays that barely
  // cross let the solve slide it far along them, and the map would hold it there. In a young map
  // that is every landmark: a joint solve of its first 4 passages, each of which fitted its
  // measurements, moved one 611 m along its rays from where the sequential updates had it (a
  // fleet of varied lenses, docs/results.md, "Joint solves held to the creation rules").
  for (int i = 0; i < landmarks.size(); ++i) {
    if (landmarks.in_map(i)) continue;  // the rest of the map holds it
    const LandmarkId id = landmarks.id(i);
    bool pinned = false;
    for (int p = 0; p < count && !pinned; ++p) {
      const auto it = std::find(seen[p].ids.begin(), seen[p].ids.end(), id);
      if (it == seen[p].ids.end()) continue;
      const RayGeometry geometry = NewLandmarkGeometry(
          poses[p], 0, seen[p].detections[it - seen[p].ids.begin()], landmarks.position(index_of.at(id)),
          passages[p].calibration, passages[p].noise.pixel_sigma_px);
      pinned = WellDeterminedNewLandmark(geometry, options);
    }
    if (!pinned) unpinned->push_back(id);
  }
  if (!unpinned->empty()) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "landmark %d: only the %d passages inform it, and none of their rays pins it down as a new landmark's must",
        unpinned->front(), count));
  }
  summary.final_cost = solver_summary.final_cost;
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
  if (absl::Status s = CorrectBias(&*linearization, &problem, options, &summary); !s.ok()) return s;

  // The result replaces the factors of the passages, at one new version of `map`; a passage's
  // factor carries its share of the bias correction. A landmark that left the map with them comes
  // back with its record (its anchor); its estimate and marginal are written below.
  const auto covariance_start = std::chrono::steady_clock::now();
  if (area) {
    for (LandmarkId id : removed) {
      absl::StatusOr<Landmark> record = LandmarkStillThere(map, id);
      if (!record.ok()) return record.status();
      overlay.PutLandmark(*record);
    }
  }
  auto position = [&](LandmarkId id) { return landmarks.position(index_of.at(id)); };
  if (correlated) {
    // At the corrected solution x_c = x* + b: Lambda_p x_c - g_p(x*) sums to Lambda x_c - g(x*),
    // the joint solution less the solver's shortfall (zero at an exact optimum).
    for (int p = 0; p < count; ++p) {
      const int k = static_cast<int>(seen[p].ids.size());
      Eigen::VectorXd x(2 * k);
      for (int i = 0; i < k; ++i) x.segment<2>(2 * i) = position(seen[p].ids[i]);
      MapFactor f;
      f.vehicle_id = passages[p].vehicle_id;
      f.passage_id = passages[p].passage_id;
      f.landmarks = seen[p].ids;
      f.information = information[p].information;
      f.information_vector = information[p].information * x - information[p].gradient;
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
      f.information_vector = f.information * position(ids[i]);
      AddLocalFactor(frame, position(ids[i]), std::move(f), &overlay);
    }
  }
  // A young map's passages are all it has seen; an area's were counted when they were applied.
  auto touch = [&](Landmark* record) {
    if (const Landmark* before = map.FindLandmark(record->id); area && before != nullptr) {
      record->passages_seen = before->passages_seen;
      record->last_seen_unix_ms = before->last_seen_unix_ms;
      return;
    }
    record->passages_seen = seen_by[record->id];
    record->last_seen_unix_ms = last_seen_ms[record->id];
  };
  // Every factor of the passages replaced: their landmarks' marginals and those of the window.
  MarginalRefresh refresh;
  refresh.others = true;  // other landmarks' factors are replaced too, when the passages saw them
  absl::StatusOr<int> conditioned = ResolveAround(ids, refresh, window, version, touch, &overlay);
  if (!conditioned.ok()) return conditioned.status();
  summary.landmarks_conditioned = *conditioned;
  Yield(options);
  summary.covariance_ms += MillisecondsSince(covariance_start);
  // What only the passages informed, they must fix again as a new landmark must be fixed: a
  // landmark they now set aside would be left free along a ray.
  if (area) {
    for (LandmarkId id : removed) {
      if (const double sigma_m = ConditionalSigmaM(overlay, id); !(sigma_m <= options.max_new_landmark_ray_sigma_m)) {
        return absl::FailedPreconditionError(absl::StrFormat(
            "landmark %d would be left undetermined by the %d passages solved jointly (sigma %.3g m along its weakest "
            "direction, over %.3g m allowed)",
            id, count, sigma_m, options.max_new_landmark_ray_sigma_m));
      }
    }
  }
  MapDelta delta = overlay.TakeDelta();
  // The vehicles' estimates are those of the sequential update of the last passage; an area's
  // passages were all taken into their vehicles' records when they were applied.
  if (single != nullptr) delta.vehicles = single->delta.vehicles;
  for (auto& [id, vehicle] : delta.vehicles) vehicle.version = delta.version;
  for (const auto& [id, record] : delta.landmarks) {
    if (seen_by.count(id)) ++(map.FindLandmark(id) != nullptr ? summary.landmarks_updated : summary.landmarks_created);
  }
  summary.map_version = delta.version;
  summary.total_ms = MillisecondsSince(start);
  if (absl::Status s = CheckDeltaInvariants(delta); !s.ok()) return s;
  return PassageUpdate{std::move(delta), summary};
}

// Why the joint solution `joint` must not be used, or "" if it may: a landmark that the joint
// solve moved out of the confidence region of the sequential estimate (the update `single` of
// the last passage on `map`, or `map`'s own for the landmarks that update did not touch). Both
// estimate the same landmarks from nearly the same information, so they differ by far less than
// that region, unless the joint solve converged to another minimum.
std::string JointSolutionRejected(const MapReaderInterface& map, const MapDelta& single, const PassageUpdate& joint,
                                  double max_mahalanobis2) {
  for (const auto& [id, joint_record] : joint.delta.landmarks) {
    const auto it = single.landmarks.find(id);
    const Landmark* sequential = it != single.landmarks.end() ? &it->second : map.FindLandmark(id);
    if (sequential == nullptr) continue;
    const Eigen::Vector2d offset = EastNorthOffset(sequential->position, joint_record.position);
    const Eigen::LDLT<Eigen::Matrix2d> cov(sequential->cov_en_m2);
    if (cov.info() != Eigen::Success || !cov.isPositive()) continue;
    const double mahalanobis2 = offset.dot(cov.solve(offset));
    if (!(mahalanobis2 <= max_mahalanobis2)) {
      return absl::StrFormat("landmark %d is %.2f m from the sequential estimate (Mahalanobis^2 %.1f > %.1f)", id,
                             offset.norm(), mahalanobis2, max_mahalanobis2);
    }
  }
  return "";
}

// Why the joint solution leaves a landmark undetermined, or "" if it does not: a marginal standard
// deviation beyond `max_sigma_m` in some direction. Rays that are nearly parallel fit a landmark
// anywhere along them, so such a solution can fit every passage's measurements: the joint solve
// of a young map's first two passages (AR(1) GNSS) moved one 98 km along its rays, sigma 3 km,
// and after 60 passages it was still there.
std::string UndeterminedLandmark(const PassageUpdate& joint, double max_sigma_m) {
  for (const auto& [id, record] : joint.delta.landmarks) {
    const double sigma_m = std::sqrt(Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(record.cov_en_m2).eigenvalues()(1));
    if (!(sigma_m <= max_sigma_m)) {
      return absl::StrFormat("landmark %d is left undetermined (sigma %.0f m > %.0f m)", id, sigma_m, max_sigma_m);
    }
  }
  return "";
}

// Whether the joint solution fits every passage's measurements: the consistency test found no
// passage's chi-square beyond its degrees of freedom (none had its variance inflated). Such a
// solution is the optimum of all the passages' measurements together. A sequential map can be
// further off than its covariance says: a short passage whose GNSS was metres off, solved against
// a young map, placed its new landmarks 8 to 17 m off with sigmas of 1 to 2 m, and every later
// passage's detections of them were set aside as disagreeing, so nothing sequential moved them
// back (docs/results.md, "The warm-up guard"). A joint solve caught in a wrong minimum leaves
// residuals that do not fit (a variance factor of 669 in the measured case), and the guard then
// keeps the sequential update.
bool FitsEveryPassage(const PassageUpdate& joint, const MapUpdateOptions& options) {
  return options.inflation_test_sigmas > 0.0 && joint.summary.max_variance_factor <= 1.0;
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
  // Landmarks the joint solution leaves unpinned are held back and the passages solved again
  // without them, as a sequential update holds back its new landmarks (a few rounds: each can
  // leave others unpinned).
  constexpr int kHoldBackRounds = 3;
  std::set<LandmarkId> held_back;
  std::vector<LandmarkId> unpinned;
  absl::StatusOr<PassageUpdate> joint = SolveJointly(passages, options, map, &*single, held_back, &unpinned);
  for (int round = 1; !joint.ok() && !unpinned.empty() && round < kHoldBackRounds; ++round) {
    spdlog::info("joint solve of {} passages: {} landmark(s) the passages' rays do not pin down (first {}) held back, "
                 "solved again",
                 passages.size(), unpinned.size(), unpinned.front());
    held_back.insert(unpinned.begin(), unpinned.end());
    unpinned.clear();
    joint = SolveJointly(passages, options, map, &*single, held_back, &unpinned);
  }
  // A map that changed while it was read (a worker's, under other workers' commits): the whole
  // computation is made again, not its sequential half kept.
  if (joint.status().code() == absl::StatusCode::kAborted) return joint.status();
  if (joint.ok()) joint->summary.landmarks_held_back = static_cast<int>(held_back.size());
  std::string rejected = joint.ok() ? JointSolutionRejected(map, single->delta, *joint, options.max_joint_mahalanobis2)
                                    : std::string(joint.status().message());
  if (joint.ok() && !rejected.empty() && FitsEveryPassage(*joint, options)) {
    if (const std::string undetermined = UndeterminedLandmark(*joint, options.max_new_landmark_range_m);
        !undetermined.empty()) {
      rejected = absl::StrCat(rejected, ", and although it fits every passage's measurements, ", undetermined);
    } else {
      spdlog::info("joint solve of {} passages used although {}: it fits every passage's measurements",
                   passages.size(), rejected);
      rejected.clear();
    }
  }
  if (rejected.empty()) return joint;
  // The sequential update is a valid map change on its own: the passage is not lost.
  spdlog::warn("joint solve of {} passages not used, sequential update of passage {} instead: {}", passages.size(),
               passages.back().passage_id, rejected);
  single->summary.joint_rejected = true;
  return single;
}

absl::StatusOr<PassageUpdate> ComputeAreaRelinearization(const std::vector<Passage>& passages,
                                                         const MapUpdateOptions& options, const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  if (passages.empty()) return absl::InvalidArgumentError("passages: a joint solve needs at least one passage");
  if (options.strategy == UpdateStrategy::kDecorrelated) {
    return absl::InvalidArgumentError("strategy: an area's joint solve needs the map's correlations (cc or cc-gsd)");
  }
  for (const Passage& passage : passages) {
    if (passage.gnss.empty()) return absl::InvalidArgumentError("gnss: passage needs at least 2 GNSS fixes");
  }
  std::vector<LandmarkId> unpinned;
  absl::StatusOr<PassageUpdate> joint = SolveJointly(passages, options, map, nullptr, {}, &unpinned);
  if (!joint.ok()) return joint.status();
  if (const std::string rejected = JointSolutionRejected(map, MapDelta(), *joint, options.max_joint_mahalanobis2);
      !rejected.empty()) {
    return absl::FailedPreconditionError(absl::StrCat("joint solve of ", passages.size(), " passages: ", rejected));
  }
  return joint;
}

}  // namespace crowdmap
