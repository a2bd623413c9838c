#include "core/estimation/subgraph_steps.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <optional>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_format.h"
#include "core/estimation/factors.h"
#include "core/estimation/triangulation.h"
#include "core/map/sparse_threads.h"

namespace crowdmap {
namespace {

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

}  // namespace

void Yield(const MapUpdateOptions& options) {
  if (options.yield_point) options.yield_point();
}

double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}



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

int SetAside(const std::unordered_set<LandmarkId>& landmarks_aside, const std::set<DetectionKey>& detections_aside,
             SubgraphLandmarks* landmarks) {
  if (landmarks_aside.empty() && detections_aside.empty()) return 0;
  SubgraphLandmarks kept;
  int removed = 0;
  for (size_t i = 0; i < landmarks->ids.size(); ++i) {
    std::vector<const CameraObservation*> detections;
    if (!landmarks_aside.count(landmarks->ids[i])) {
      for (const CameraObservation* d : landmarks->detections[i]) {
        if (!detections_aside.count({d->node, d->landmark_id})) detections.push_back(d);
      }
    }
    removed += static_cast<int>(landmarks->detections[i].size() - detections.size());
    if (detections.empty()) continue;
    kept.ids.push_back(landmarks->ids[i]);
    kept.known.push_back(landmarks->known[i]);
    kept.initial.push_back(landmarks->initial[i]);
    kept.detections.push_back(std::move(detections));
  }
  *landmarks = std::move(kept);
  return removed;
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

ceres::Solver::Options SubgraphSolveOptions(int max_iterations) {
  ceres::Solver::Options options = SolverOptions(max_iterations);
  // Levenberg-Marquardt's first steps close to Gauss-Newton's. Ceres's default radius (1e4) damps
  // the Jacobi-scaled normal equations by 1e-4, which held back the weakly determined directions
  // (landmarks along their rays, headings): from the refined initial poses a city subgraph took
  // 5-6 iterations whose steps shrank by a third each, where Gauss-Newton's shrink quadratically
  // (1 m, 1.5 cm, 0.5 mm). The radius still shrinks after a step that does not lower the cost. Not
  // for the initial alignments, which start metres off (docs/results.md, "Subgraph solves started
  // near Gauss-Newton").
  options.initial_trust_region_radius = 1e6;
  return options;
}

// ceres::Solve with options.yield_point called after each iteration and at the end.
void Solve(const MapUpdateOptions& options, ceres::Solver::Options solver_options, ceres::Problem* problem,
           ceres::Solver::Summary* summary) {
  YieldEachIteration callback(options.yield_point);
  if (options.yield_point) solver_options.callbacks.push_back(&callback);
  FactorizeOnThisThreadOnly();
  ceres::Solve(solver_options, problem, summary);
  Yield(options);
}

namespace {

// Under coloured GNSS noise the initial poses follow fixes that can be tens of metres off, the same
// way for minutes. Solved from there against the bearings to the map, a piece of the trajectory
// can wind through a full turn (a wrong minimum the full solve keeps: headings are only known
// modulo 2 pi). First the trajectory is moved, its shape held, by a smooth offset (piecewise
// linear, knots half a correlation time apart, the GNSS process's statistics as its prior) that
// best fits the bearings to the map landmarks (Cauchy loss: some detections may not fit).
void AlignToMap(const PassageGraph& graph, const NodeRange& range, const Passage& passage,
                const SubgraphLandmarks& landmarks, const MapUpdateOptions& update_options, std::vector<Pose2>* poses) {
  const double tau = graph.gnss_correlation_time_s;
  if (!(tau > 0.0) || graph.gnss.empty()) return;
  const double t0 = graph.node_times_s[range.first], span = graph.node_times_s[range.last] - t0;
  if (!(span > 0.0)) return;
  const int knots = 1 + std::max(1, static_cast<int>(std::ceil(span / std::max(5.0, 0.5 * tau))));
  const double spacing = span / (knots - 1);
  const double sigma = std::sqrt(0.5 * graph.gnss.front().cov_m2.trace());
  std::vector<Eigen::Vector2d> offset(knots, Eigen::Vector2d::Zero());
  // A node's offset: (1 - w) offset[a] + w offset[a + 1].
  const auto knot_of = [&](int node) {
    const double x = (graph.node_times_s[node] - t0) / spacing;
    const int a = std::clamp(static_cast<int>(std::floor(x)), 0, knots - 2);
    return std::make_pair(a, x - a);
  };
  ceres::Problem problem;
  int bearings = 0;
  for (size_t i = 0; i < landmarks.ids.size(); ++i) {
    if (!landmarks.known[i]) continue;
    for (const CameraObservation* d : landmarks.detections[i]) {
      const auto [a, w] = knot_of(d->node);
      problem.AddResidualBlock(
          ShiftedBearingFactor::Create((*poses)[d->node - range.first], landmarks.initial[i], w, d->u_px,
                                       passage.noise.pixel_sigma_px, passage.calibration),
          new ceres::CauchyLoss(3.0), offset[a].data(), offset[a + 1].data());
      ++bearings;
    }
  }
  if (bearings == 0) return;
  problem.AddResidualBlock(new LandmarkPriorFactor(Eigen::Vector2d::Zero(), Eigen::Matrix2d::Identity() / sigma),
                           nullptr, offset[0].data());
  for (int j = 1; j < knots; ++j) {
    problem.AddResidualBlock(Ar1StepFactor::Create(std::exp(-spacing / tau), sigma), nullptr, offset[j - 1].data(),
                             offset[j].data());
  }
  // A starting point only: decimetres are plenty for the pose solve that follows.
  ceres::Solver::Options options = SolverOptions(update_options.max_solver_iterations);
  options.function_tolerance = 1e-4;
  options.parameter_tolerance = 1e-4;
  ceres::Solver::Summary summary;
  Solve(update_options, options, &problem, &summary);
  if (!summary.IsSolutionUsable()) return;
  for (int k = range.first; k <= range.last; ++k) {
    const auto [a, w] = knot_of(k);
    (*poses)[k - range.first].head<2>() += (1.0 - w) * offset[a] + w * offset[a + 1];
  }
}

}  // namespace

// Refines the subgraph's initial poses: odometry + GNSS + the bearings of the map landmarks held
// fixed, if any. The pixel model alone cannot start from poses tens of metres off (with coloured
// GNSS noise the GNSS-aligned guess often is), the bounded bearing residual can.
void InitializePoses(const PassageGraph& graph, const NodeRange& range, const Passage& passage,
                     const MapUpdateOptions& update_options, SubgraphLandmarks* landmarks, std::vector<Pose2>* poses) {
  AlignToMap(graph, range, passage, *landmarks, update_options, poses);
  ceres::Problem problem;
  AddPoseGraphFactors(graph, range.first, range.last, passage.calibration.gnss_lever_arm_m, nullptr, nullptr, poses,
                      &problem, /*independent_fixes=*/true);
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

// Initial positions of the new landmarks (intersection of their rays) and the detections usable
// at the initial guess: landmark in front of the camera and, for map landmarks and a positive
// `edge_margin_px`, predicted at least that far inside the image. A detector reports only
// detections inside the image, so one whose true pixel lies within a few sigma of the border has
// its noise cut on one side and is biased inwards, the same way on every passage; the prediction
// from the map does not depend on the detection, so leaving those out removes the bias without
// adding one. Landmarks that cannot be initialised, new ones with fewer than `min_new_detections` usable rays,
// are left out. Returns the detections dropped.
int InitializeLandmarks(const std::vector<Pose2>& poses, const NodeRange& range, const Calibration& calib,
                        double edge_margin_px, double min_parallax_rad, int min_new_detections,
                        SubgraphLandmarks* landmarks) {
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
    if (usable.empty() || (!landmarks->known[i] && static_cast<int>(usable.size()) < min_new_detections)) {
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

RayGeometry NewLandmarkGeometry(const std::vector<Pose2>& poses, int first_node,
                                const std::vector<const CameraObservation*>& detections,
                                const Eigen::Vector2d& position, const Calibration& calib, double pixel_sigma_px) {
  using Jet = ceres::Jet<double, 2>;
  RayGeometry geometry;
  Eigen::Matrix2d information = Eigen::Matrix2d::Zero();
  const Jet landmark[2] = {Jet(position.x(), 0), Jet(position.y(), 1)};
  for (const CameraObservation* d : detections) {
    const Pose2& pose = poses[d->node - first_node];
    const Jet pose_jet[3] = {Jet(pose[0]), Jet(pose[1]), Jet(pose[2])};
    geometry.max_range_m = std::max(geometry.max_range_m, (position - pose.head<2>()).norm());
    Jet u;
    if (!ProjectLandmark(pose_jet, landmark, calib, &u)) {
      geometry.sigma_m = std::numeric_limits<double>::infinity();  // behind a camera that saw it
      return geometry;
    }
    information += u.v * u.v.transpose() / (pixel_sigma_px * pixel_sigma_px);
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(information);
  const double smallest = eig.eigenvalues()(0);
  geometry.sigma_m = smallest > 0.0 ? 1.0 / std::sqrt(smallest) : std::numeric_limits<double>::infinity();
  return geometry;
}

bool WellDeterminedNewLandmark(const RayGeometry& geometry, const MapUpdateOptions& options) {
  return geometry.max_range_m <= options.max_new_landmark_range_m &&
         geometry.sigma_m <= options.max_new_landmark_ray_sigma_m;
}

absl::Status CheckDetectionsFit(int unfit, int total, const MapUpdateOptions& options) {
  if (options.max_unfit_detection_fraction <= 0.0 || unfit < MapUpdateOptions::kMinUnfitDetections ||
      unfit <= options.max_unfit_detection_fraction * total) {
    return absl::OkStatus();
  }
  return absl::FailedPreconditionError(absl::StrFormat(
      "detections do not fit: %d of its %d detections lie beyond %.1f pixel sigmas of the solution (more than %.0f%% "
      "allowed); the map is unchanged (its camera reports landmarks under wrong ids or detections of nothing, or its "
      "trajectory is wrong where it saw them)",
      unfit, total, options.max_detection_residual_sigmas, 100.0 * options.max_unfit_detection_fraction));
}

absl::StatusOr<GraphLinearization> Linearize(ceres::Problem* problem, const std::vector<double*>& landmark_blocks,
                                             const MapUpdateOptions& options, PassageUpdateSummary* summary,
                                             const std::vector<ceres::ResidualBlockId>& factor_leaves_out) {
  const auto covariance_start = std::chrono::steady_clock::now();
  absl::StatusOr<GraphLinearization> linearization =
      GraphLinearization::Compute(problem, landmark_blocks, factor_leaves_out);
  if (!linearization.ok()) return linearization.status();
  summary->covariance_ms += MillisecondsSince(covariance_start);
  Yield(options);
  return linearization;
}

absl::StatusOr<GraphLinearization> LinearizeTestingSensors(
    ceres::Problem* problem, const std::vector<double*>& landmark_blocks, const std::vector<WeightedBlocks>& passages,
    const ceres::Solver::Options& solver_options, const MapUpdateOptions& options,
    ceres::Solver::Summary* solver_summary, PassageUpdateSummary* summary,
    const std::vector<ceres::ResidualBlockId>& factor_leaves_out) {
  absl::StatusOr<GraphLinearization> linearization =
      Linearize(problem, landmark_blocks, options, summary, factor_leaves_out);
  std::vector<std::array<double, MeasurementWeights::kSensors>> before;
  for (const WeightedBlocks& p : passages) before.push_back(p.weights->factors());
  for (int round = 0; round < kSensorTestRounds && linearization.ok() && options.sensor_test_sigmas > 0.0;
       ++round) {
    const std::unordered_map<ceres::ResidualBlockId, double> redundancies = linearization->Redundancies();
    bool raised = false;
    for (const WeightedBlocks& p : passages) {
      raised |= RaiseSensorVarianceFactors(SensorResidualsOf(problem, *p.blocks, redundancies, *p.weights),
                                           options.sensor_test_sigmas, p.weights);
    }
    if (!raised) break;
    const auto solve_start = std::chrono::steady_clock::now();
    Solve(options, solver_options, problem, solver_summary);
    summary->solve_ms += MillisecondsSince(solve_start);
    summary->solver_iterations += static_cast<int>(solver_summary->iterations.size());
    if (!solver_summary->IsSolutionUsable()) {
      return absl::InternalError(absl::StrCat("solver result unusable after a sensor's inflation: ",
                                              solver_summary->message));
    }
    linearization = Linearize(problem, landmark_blocks, options, summary, factor_leaves_out);
  }
  for (size_t p = 0; p < passages.size(); ++p) {
    for (int s = 0; s < MeasurementWeights::kSensors; ++s) {
      summary->sensor_test_factors[s] =
          std::max(summary->sensor_test_factors[s], passages[p].weights->factors()[s] / before[p][s]);
    }
  }
  return linearization;
}

absl::Status CorrectBias(GraphLinearization* linearization, ceres::Problem* problem, const MapUpdateOptions& options,
                         PassageUpdateSummary* summary) {
  if (!options.bias_correction) return absl::OkStatus();
  BiasCorrectionStats bias;
  if (absl::Status s = linearization->CorrectSecondOrderBias(problem, &bias); !s.ok()) return s;
  summary->bias_correction_ms += bias.ms;
  summary->max_bias_correction_m = std::max(summary->max_bias_correction_m, bias.max_landmark_shift_m);
  Yield(options);
  return absl::OkStatus();
}

double VarianceFactor(double chi2, double dof, double test_sigmas) {
  if (test_sigmas <= 0.0 || dof <= 0.0 || chi2 <= dof + test_sigmas * std::sqrt(2.0 * dof)) return 1.0;
  return chi2 / dof;
}

MeasurementWeights::MeasurementWeights()
    : losses_{{new ceres::TrivialLoss(), ceres::TAKE_OWNERSHIP},
              {new ceres::TrivialLoss(), ceres::TAKE_OWNERSHIP},
              {new ceres::TrivialLoss(), ceres::TAKE_OWNERSHIP}} {}

int MeasurementWeights::SensorOf(const ceres::LossFunction* loss) const {
  for (int s = 0; s < kSensors; ++s) {
    if (loss == &losses_[s]) return s;
  }
  return -1;
}

void MeasurementWeights::Inflate(Sensor sensor, double factor) {
  factors_[sensor] *= factor;
  losses_[sensor].Reset(new ceres::ScaledLoss(nullptr, 1.0 / factors_[sensor], ceres::TAKE_OWNERSHIP),
                        ceres::TAKE_OWNERSHIP);
}

void MeasurementWeights::InflateAll(double factor) {
  for (int s = 0; s < kSensors; ++s) Inflate(static_cast<Sensor>(s), factor);
}

SensorResiduals SensorResidualsOf(ceres::Problem* problem, const std::vector<ceres::ResidualBlockId>& blocks,
                                  const std::unordered_map<ceres::ResidualBlockId, double>& redundancies,
                                  const MeasurementWeights& weights) {
  SensorResiduals out;
  for (ceres::ResidualBlockId id : blocks) {
    const int sensor = weights.SensorOf(problem->GetLossFunctionForResidualBlock(id));
    const auto redundancy = redundancies.find(id);
    double cost = 0.0;
    if (sensor < 0 || redundancy == redundancies.end() ||
        !problem->EvaluateResidualBlock(id, /*apply_loss_function=*/true, &cost, nullptr, nullptr)) {
      continue;
    }
    out.chi2[sensor] += 2.0 * cost;
    out.redundancy[sensor] += redundancy->second;
  }
  return out;
}

bool RaiseSensorVarianceFactors(const SensorResiduals& residuals, double test_sigmas, MeasurementWeights* weights) {
  bool raised = false;
  for (int s = 0; s < MeasurementWeights::kSensors; ++s) {
    // Less than one degree of freedom tells nothing about a variance (a sensor the graph's other
    // measurements barely check, e.g. two fixes on a short piece).
    if (residuals.redundancy[s] < 1.0) continue;
    if (const double factor = VarianceFactor(residuals.chi2[s], residuals.redundancy[s], test_sigmas); factor > 1.0) {
      weights->Inflate(static_cast<MeasurementWeights::Sensor>(s), factor);
      raised = true;
    }
  }
  return raised;
}

}  // namespace crowdmap
