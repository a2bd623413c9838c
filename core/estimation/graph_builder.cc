#include "core/estimation/graph_builder.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include <ceres/ceres.h>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"
#include "core/map/sparse_threads.h"

namespace crowdmap {
namespace {

// Where the vehicle is along its path (m from the passage start) at each of `times` (sorted): the
// odometry's speeds, each held until the next sample, integrated with their signs. Where the view
// changes, not how far the wheels turned: a vehicle that backs up and drives on returns to where
// it was, and the noise of speeds read while standing still (zero-mean) does not add up to
// travel as their absolute values would (at 0.56 m/s and 25 Hz, 27 m a minute).
std::vector<double> PathPositionAt(const std::vector<OdometrySample>& odometry, const std::vector<double>& times) {
  std::vector<double> position;
  position.reserve(times.size());
  double s = 0.0;  // at odometry[i].t_s
  size_t i = 0;
  for (double t : times) {
    while (i + 1 < odometry.size() && odometry[i + 1].t_s <= t) {
      s += odometry[i].speed_mps * (odometry[i + 1].t_s - odometry[i].t_s);
      ++i;
    }
    const bool inside = i < odometry.size() && t > odometry[i].t_s;
    position.push_back(s + (inside ? odometry[i].speed_mps * (t - odometry[i].t_s) : 0.0));
  }
  return position;
}

// The last K detections of every landmark (all with K = 0), in time order; with `spread`, K spread
// evenly over its track instead, its first and last among them. With a spacing in time
// or distance, only detections of "grid frames" count: the first camera frame (distinct detection
// time, within `tolerance_s`) in each interval [n spacing_s, (n + 1) spacing_s) of the passage's
// time that is taken once the vehicle is spacing_m along its path from the grid frame before. Every
// landmark then keeps detections of the same frames, which share pose nodes whatever the camera's
// rate (at a rate of 1 / spacing_s or less every frame is a grid frame while the vehicle moves),
// and a vehicle standing still adds no frame: a camera that does not move sees the same view with
// the same detector error, which counted again and again would make the passage sure of it.
std::vector<const Detection*> SelectDetections(const std::vector<Detection>& detections,
                                               const std::vector<OdometrySample>& odometry, int per_landmark,
                                               bool spread, double spacing_s, double spacing_m, double tolerance_s) {
  std::vector<double> grid_frames;  // sorted
  const bool grid = spacing_s > 0.0 || spacing_m > 0.0;
  if (grid) {
    std::vector<double> times;
    times.reserve(detections.size());
    for (const Detection& d : detections) times.push_back(d.t_s);
    std::sort(times.begin(), times.end());
    const std::vector<double> along = PathPositionAt(odometry, times);
    double bucket = -std::numeric_limits<double>::infinity();
    double last_frame_t = -std::numeric_limits<double>::infinity(), last_frame_m = 0.0;
    for (size_t i = 0; i < times.size(); ++i) {
      const double t = times[i];
      if (t - last_frame_t <= tolerance_s) continue;  // the same frame
      const double b = spacing_s > 0.0 ? std::floor((t + tolerance_s) / spacing_s) : t;
      const bool first = grid_frames.empty();
      if (first || (b > bucket && std::abs(along[i] - last_frame_m) >= spacing_m)) {
        grid_frames.push_back(t);
        bucket = b;
        last_frame_t = t;
        last_frame_m = along[i];
      }
    }
  }
  const auto on_grid = [&](double t) {
    if (!grid) return true;
    const auto it = std::lower_bound(grid_frames.begin(), grid_frames.end(), t - tolerance_s);
    return it != grid_frames.end() && *it <= t + tolerance_s;
  };
  std::map<LandmarkId, std::vector<int>> track;  // each landmark's detections on the grid, in order
  for (size_t i = 0; i < detections.size(); ++i) {
    if (on_grid(detections[i].t_s)) track[detections[i].landmark_id].push_back(static_cast<int>(i));
  }
  std::vector<char> keep(detections.size(), 0);
  for (const auto& [id, frames] : track) {
    const int n = static_cast<int>(frames.size());
    if (per_landmark == 0 || n <= per_landmark) {
      for (int i : frames) keep[i] = 1;
      continue;
    }
    for (int k = 0; k < per_landmark; ++k) {
      // (n > K: the spread indices rise by more than 1 per step, so none repeats)
      const int i = spread && per_landmark > 1 ? static_cast<int>(std::lround(k * (n - 1.0) / (per_landmark - 1)))
                                               : n - per_landmark + k;
      keep[frames[i]] = 1;
    }
  }
  std::vector<const Detection*> kept;
  for (size_t i = 0; i < detections.size(); ++i) {
    if (keep[i]) kept.push_back(&detections[i]);
  }
  return kept;
}

// Sorted, merged node times; NodeIndex finds the node of a measurement time.
std::vector<double> MergeTimes(std::vector<double> times, double tolerance) {
  std::sort(times.begin(), times.end());
  std::vector<double> merged;
  for (double t : times) {
    if (merged.empty() || t - merged.back() > tolerance) merged.push_back(t);
  }
  return merged;
}

int NodeIndex(const std::vector<double>& nodes, double t, double tolerance) {
  auto it = std::lower_bound(nodes.begin(), nodes.end(), t - tolerance);
  return static_cast<int>(it - nodes.begin());
}

// Initial poses: the odometry dead-reckoning, aligned to the GNSS fixes by a rigid 2D fit over a
// sliding window around each node (the dead-reckoned heading drifts, so one fit for the whole
// passage is not enough; a window of a few hundred metres fixes rotation and position robustly,
// where headings from differences of noisy fixes can flip).
std::vector<Pose2> AlignDeadReckoning(const PassageGraph& g, const Calibration& calib, double window_s) {
  const int n = g.node_count();
  std::vector<Pose2> dead_reckoning(n);
  dead_reckoning[0] = Pose2::Zero();
  for (int k = 0; k + 1 < n; ++k) dead_reckoning[k + 1] = ComposeMotion(dead_reckoning[k], g.motions[k].delta);
  std::vector<Eigen::Vector2d> antenna(g.gnss.size());
  for (size_t j = 0; j < g.gnss.size(); ++j) {
    const Pose2& p = dead_reckoning[g.gnss[j].node];
    const double c = std::cos(p.z()), s = std::sin(p.z());
    antenna[j] = p.head<2>() + Eigen::Vector2d(c * calib.gnss_lever_arm_m.x() - s * calib.gnss_lever_arm_m.y(),
                                               s * calib.gnss_lever_arm_m.x() + c * calib.gnss_lever_arm_m.y());
  }
  std::vector<Pose2> poses(n);
  // A window wider than this holds the whole passage (finite for any valid passage, whose times
  // span a day at most: ValidatePassage; the loop below must end whatever the times).
  const double whole_s = 2.0 * (g.node_times_s.back() - g.node_times_s.front());
  // The fixes' times, in order as the fixes are: a window's fixes are then a range, found by
  // bisection, so that a long passage costs its windows, not its fixes times its nodes.
  std::vector<double> fix_s(g.gnss.size());
  for (size_t j = 0; j < g.gnss.size(); ++j) fix_s[j] = g.node_times_s[g.gnss[j].node];
  const bool fixes_in_order = std::is_sorted(fix_s.begin(), fix_s.end());
  for (int k = 0; k < n; ++k) {
    const double t = g.node_times_s[k];
    // Widen the window until the dead-reckoned track spans enough to fix a rotation.
    for (double half = 0.5 * window_s;; half *= 2.0) {
      // The fixes within `half` of t: [from, to) (all of them, tested one by one, out of order).
      size_t from = 0, to = fix_s.size();
      if (fixes_in_order) {
        const auto first = std::partition_point(fix_s.begin(), fix_s.end(), [&](double f) { return t - f > half; });
        from = static_cast<size_t>(first - fix_s.begin());
        to = static_cast<size_t>(std::partition_point(first, fix_s.end(), [&](double f) { return !(f - t > half); }) -
                                 fix_s.begin());
      }
      Eigen::Vector2d mean_dr = Eigen::Vector2d::Zero(), mean_fix = Eigen::Vector2d::Zero();
      int count = 0;
      for (size_t j = from; j < to; ++j) {
        if (std::abs(fix_s[j] - t) > half) continue;
        mean_dr += antenna[j];
        mean_fix += g.gnss[j].position_m;
        ++count;
      }
      if (count == 0) continue;
      mean_dr /= count;
      mean_fix /= count;
      double dot = 0.0, cross = 0.0, spread = 0.0;
      for (size_t j = from; j < to; ++j) {
        if (std::abs(fix_s[j] - t) > half) continue;
        const Eigen::Vector2d a = antenna[j] - mean_dr, b = g.gnss[j].position_m - mean_fix;
        dot += a.dot(b);
        cross += a.x() * b.y() - a.y() * b.x();
        spread += a.squaredNorm();
      }
      const bool whole_passage = half > whole_s || !std::isfinite(half);
      if (spread < 50.0 * 50.0 * count && !whole_passage) continue;  // RMS spread under 50 m
      const double rotation = std::atan2(cross, dot);
      const double c = std::cos(rotation), s = std::sin(rotation);
      const Eigen::Vector2d rel = dead_reckoning[k].head<2>() - mean_dr;
      poses[k] << mean_fix + Eigen::Vector2d(c * rel.x() - s * rel.y(), s * rel.x() + c * rel.y()),
          WrapAngle(dead_reckoning[k].z() + rotation);
      break;
    }
  }
  return poses;
}

absl::Status SolvePoseGraph(const Calibration& calib, int max_iterations, PassageGraph* g) {
  ceres::Problem problem;
  AddPoseGraphFactors(*g, 0, g->node_count() - 1, calib.gnss_lever_arm_m, nullptr, nullptr, &g->initial_poses, &problem,
                      /*independent_fixes=*/true);
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = max_iterations;
  options.num_threads = 1;
  ceres::Solver::Summary summary;
  FactorizeOnThisThreadOnly();
  ceres::Solve(options, &problem, &summary);
  if (!summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("pose initialisation failed: ", summary.message));
  }
  for (Pose2& p : g->initial_poses) p.z() = WrapAngle(p.z());
  return absl::OkStatus();
}

// The odometry preintegrated between consecutive node times.
std::vector<RelativeMotion> MotionsBetween(const Passage& passage, const std::vector<double>& node_times_s) {
  std::vector<RelativeMotion> motions;
  motions.reserve(node_times_s.size());
  for (size_t k = 0; k + 1 < node_times_s.size(); ++k) {
    motions.push_back(Preintegrate(passage.odometry, node_times_s[k], node_times_s[k + 1],
                                   passage.calibration.wheelbase_m, passage.noise));
  }
  return motions;
}

// GraphOptions::detect_correlated_gnss for `g`, a passage that declares white GNSS noise: the
// residuals of its fixes against its own trajectory, its fixes taken as declared, solved on a pose
// graph of its fixes' times alone (a third of the nodes on the loop: the check's solve is the
// passage's smallest); where they show correlated errors, `g` takes the process they give.
absl::Status CheckGnssCorrelation(const Passage& passage, const GraphOptions& options, PassageGraph* g) {
  PassageGraph fixes;
  for (const GnssObservation& o : g->gnss) fixes.node_times_s.push_back(o.t_s);
  fixes.node_times_s = MergeTimes(std::move(fixes.node_times_s), options.node_merge_tolerance_s);
  fixes.motions = MotionsBetween(passage, fixes.node_times_s);
  fixes.gnss = g->gnss;
  for (GnssObservation& o : fixes.gnss) o.node = NodeIndex(fixes.node_times_s, o.t_s, options.node_merge_tolerance_s);
  fixes.initial_poses = AlignDeadReckoning(fixes, passage.calibration, options.alignment_window_s);
  if (absl::Status s = SolvePoseGraph(passage.calibration, /*max_iterations=*/10, &fixes); !s.ok()) return s;
  g->gnss_residuals = MeasureGnssResiduals(fixes.gnss, fixes.initial_poses, passage.calibration.gnss_lever_arm_m);
  g->correlated_gnss = CorrelatedGnssFromResiduals(*g->gnss_residuals, *options.detect_correlated_gnss);
  if (g->correlated_gnss) {
    g->gnss_correlation_time_s = g->correlated_gnss->correlation_time_s;
    for (GnssObservation& o : g->gnss) o.cov_m2 *= g->correlated_gnss->covariance_scale;
  }
  return absl::OkStatus();
}

}  // namespace

void AddPoseGraphFactors(const PassageGraph& graph, int first, int last, const Eigen::Vector2d& gnss_lever_arm_m,
                         ceres::LossFunction* odometry_loss, ceres::LossFunction* gnss_loss,
                         std::vector<Pose2>* poses, ceres::Problem* problem,
                         bool independent_fixes, double* speed_scale) {
  auto pose = [&](int node) { return (*poses)[node - first].data(); };
  for (Pose2& p : *poses) problem->AddParameterBlock(p.data(), 3);
  for (int k = first; k < last; ++k) {
    if (speed_scale != nullptr) {
      problem->AddResidualBlock(ScaledOdometryFactor::Create(graph.motions[k]), odometry_loss, pose(k), pose(k + 1),
                                speed_scale);
    } else {
      problem->AddResidualBlock(OdometryFactor::Create(graph.motions[k]), odometry_loss, pose(k), pose(k + 1));
    }
  }
  const double tau = independent_fixes ? 0.0 : graph.gnss_correlation_time_s;
  for (size_t j = 0; j < graph.gnss.size(); ++j) {
    const GnssObservation& o = graph.gnss[j];
    if (o.node < first || o.node > last) continue;
    if (tau <= 0.0 || j == 0) {
      problem->AddResidualBlock(GnssFactor::Create(o.position_m, o.cov_m2, gnss_lever_arm_m), gnss_loss, pose(o.node));
      continue;
    }
    const GnssObservation& previous = graph.gnss[j - 1];
    if (previous.node < first) continue;
    const double dt_s = o.t_s - previous.t_s;
    if (previous.node == o.node) {
      problem->AddResidualBlock(GnssAr1Factor::CreateAtOneNode(previous.position_m, previous.cov_m2, o.position_m,
                                                               o.cov_m2, gnss_lever_arm_m, dt_s, tau),
                                gnss_loss, pose(o.node));
    } else {
      problem->AddResidualBlock(GnssAr1Factor::Create(previous.position_m, previous.cov_m2, o.position_m, o.cov_m2,
                                                      gnss_lever_arm_m, dt_s, tau),
                                gnss_loss, pose(previous.node), pose(o.node));
    }
  }
}

absl::StatusOr<PassageGraph> BuildPassageGraph(const Passage& passage, const GraphOptions& options) {
  if (passage.gnss.size() < 2) return absl::InvalidArgumentError("gnss: passage needs at least 2 GNSS fixes");
  PassageGraph g;
  g.frame = LocalFrame(options.frame_origin.value_or(LatLon{passage.gnss.front().lat_deg, passage.gnss.front().lon_deg}));

  const std::vector<const Detection*> used =
      SelectDetections(passage.detections, passage.odometry, options.detections_per_landmark,
                       options.spread_detections, options.detection_spacing_s, options.detection_spacing_m,
                       options.node_merge_tolerance_s);
  g.detections_dropped = static_cast<int>(passage.detections.size() - used.size());

  std::vector<double> times;
  times.reserve(passage.gnss.size() + used.size());
  for (const GnssFix& f : passage.gnss) times.push_back(f.t_s);
  for (const Detection* d : used) times.push_back(d->t_s);
  g.node_times_s = MergeTimes(std::move(times), options.node_merge_tolerance_s);

  g.motions = MotionsBetween(passage, g.node_times_s);

  g.gnss_correlation_time_s = passage.noise.gnss_correlation_time_s;
  const double process_sigma_m = passage.noise.gnss_process_sigma_m;
  for (const GnssFix& f : passage.gnss) {
    const LatLon p{f.lat_deg, f.lon_deg};
    const Eigen::Matrix2d r = g.frame.EnToLocal(p);
    GnssObservation o;
    o.node = NodeIndex(g.node_times_s, f.t_s, options.node_merge_tolerance_s);
    o.t_s = f.t_s;
    o.position_m = g.frame.ToLocal(p);
    const Eigen::Matrix2d cov_en = process_sigma_m > 0.0 ? Eigen::Matrix2d(Eigen::Matrix2d::Identity() * process_sigma_m * process_sigma_m)
                                                         : f.cov_en_m2;
    o.cov_m2 = r * cov_en * r.transpose();
    g.gnss.push_back(o);
  }
  for (const Detection* d : used) {
    g.detections.push_back({NodeIndex(g.node_times_s, d->t_s, options.node_merge_tolerance_s), d->landmark_id, d->u_px});
  }
  std::stable_sort(g.detections.begin(), g.detections.end(),
                   [](const CameraObservation& a, const CameraObservation& b) { return a.node < b.node; });

  g.initial_poses = AlignDeadReckoning(g, passage.calibration, options.alignment_window_s);
  if (options.detect_correlated_gnss && g.gnss_correlation_time_s <= 0.0) {
    if (absl::Status s = CheckGnssCorrelation(passage, options, &g); !s.ok()) return s;
  }
  if (options.refine_initial_poses) {
    if (absl::Status s = SolvePoseGraph(passage.calibration, options.max_init_iterations, &g); !s.ok()) return s;
  }
  return g;
}

}  // namespace crowdmap
