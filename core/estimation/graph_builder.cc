#include "core/estimation/graph_builder.h"

#include <algorithm>
#include <cmath>
#include <map>

#include <ceres/ceres.h>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"

namespace crowdmap {
namespace {

// The last K detections of every landmark, in time order.
std::vector<const Detection*> SelectDetections(const std::vector<Detection>& detections, int per_landmark) {
  std::map<LandmarkId, int> remaining;
  std::vector<const Detection*> kept;
  for (auto it = detections.rbegin(); it != detections.rend(); ++it) {
    int& left = remaining.try_emplace(it->landmark_id, per_landmark).first->second;
    if (per_landmark > 0 && left == 0) continue;
    --left;
    kept.push_back(&*it);
  }
  std::reverse(kept.begin(), kept.end());
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

// Antenna track interpolated at time t (clamped at the ends).
Eigen::Vector2d TrackAt(const std::vector<double>& times, const std::vector<Eigen::Vector2d>& track, double t) {
  if (t <= times.front()) return track.front();
  if (t >= times.back()) return track.back();
  const size_t j = static_cast<size_t>(std::upper_bound(times.begin(), times.end(), t) - times.begin());
  const double w = (t - times[j - 1]) / (times[j] - times[j - 1]);
  return (1.0 - w) * track[j - 1] + w * track[j];
}

// Initial poses: heading from the GNSS track over a +-2 s window, position from the track minus
// the lever arm. Good to a few metres and a few tenths of a radian: enough for the pose graph.
std::vector<Pose2> PosesFromTrack(const PassageGraph& g, const std::vector<double>& fix_times,
                                  const std::vector<Eigen::Vector2d>& track, const Calibration& calib) {
  std::vector<Pose2> poses(g.node_times_s.size());
  double heading = 0.0;
  bool have_heading = false;
  for (size_t k = 0; k < poses.size(); ++k) {
    const double t = g.node_times_s[k];
    const Eigen::Vector2d ahead = TrackAt(fix_times, track, t + 2.0), behind = TrackAt(fix_times, track, t - 2.0);
    if ((ahead - behind).norm() > 1.0) {
      heading = std::atan2(ahead.y() - behind.y(), ahead.x() - behind.x());
      have_heading = true;
    } else if (have_heading && k > 0) {
      heading = WrapAngle(poses[k - 1].z() + g.motions[k - 1].delta.z());
    }
    const double c = std::cos(heading), s = std::sin(heading);
    const Eigen::Vector2d antenna = TrackAt(fix_times, track, t);
    const Eigen::Vector2d arm(c * calib.gnss_lever_arm_m.x() - s * calib.gnss_lever_arm_m.y(),
                              s * calib.gnss_lever_arm_m.x() + c * calib.gnss_lever_arm_m.y());
    poses[k] = Pose2(antenna.x() - arm.x(), antenna.y() - arm.y(), heading);
  }
  return poses;
}

absl::Status SolvePoseGraph(const Calibration& calib, int max_iterations, PassageGraph* g) {
  ceres::Problem problem;
  for (Pose2& p : g->initial_poses) problem.AddParameterBlock(p.data(), 3);
  for (int k = 0; k + 1 < g->node_count(); ++k) {
    problem.AddResidualBlock(OdometryFactor::Create(g->motions[k]), nullptr, g->initial_poses[k].data(),
                             g->initial_poses[k + 1].data());
  }
  for (const GnssObservation& o : g->gnss) {
    problem.AddResidualBlock(GnssFactor::Create(o.position_m, o.cov_m2, calib.gnss_lever_arm_m), nullptr,
                             g->initial_poses[o.node].data());
  }
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = max_iterations;
  options.num_threads = 1;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  if (!summary.IsSolutionUsable()) {
    return absl::InternalError(absl::StrCat("pose initialisation failed: ", summary.message));
  }
  for (Pose2& p : g->initial_poses) p.z() = WrapAngle(p.z());
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<PassageGraph> BuildPassageGraph(const Passage& passage, const GraphOptions& options) {
  if (passage.gnss.size() < 2) return absl::InvalidArgumentError("gnss: passage needs at least 2 GNSS fixes");
  PassageGraph g;
  g.frame = LocalFrame(LatLon{passage.gnss.front().lat_deg, passage.gnss.front().lon_deg});

  const std::vector<const Detection*> used = SelectDetections(passage.detections, options.detections_per_landmark);
  g.detections_dropped = static_cast<int>(passage.detections.size() - used.size());

  std::vector<double> times;
  times.reserve(passage.gnss.size() + used.size());
  for (const GnssFix& f : passage.gnss) times.push_back(f.t_s);
  for (const Detection* d : used) times.push_back(d->t_s);
  g.node_times_s = MergeTimes(std::move(times), options.node_merge_tolerance_s);

  const double wheelbase = passage.calibration.wheelbase_m;
  g.motions.reserve(g.node_times_s.size());
  for (size_t k = 0; k + 1 < g.node_times_s.size(); ++k) {
    g.motions.push_back(Preintegrate(passage.odometry, g.node_times_s[k], g.node_times_s[k + 1], wheelbase, passage.noise));
  }

  std::vector<double> fix_times;
  std::vector<Eigen::Vector2d> track;
  for (const GnssFix& f : passage.gnss) {
    const LatLon p{f.lat_deg, f.lon_deg};
    const Eigen::Matrix2d r = g.frame.EnToLocal(p);
    GnssObservation o;
    o.node = NodeIndex(g.node_times_s, f.t_s, options.node_merge_tolerance_s);
    o.position_m = g.frame.ToLocal(p);
    o.cov_m2 = r * f.cov_en_m2 * r.transpose();
    g.gnss.push_back(o);
    fix_times.push_back(f.t_s);
    track.push_back(o.position_m);
  }
  for (const Detection* d : used) {
    g.detections.push_back({NodeIndex(g.node_times_s, d->t_s, options.node_merge_tolerance_s), d->landmark_id, d->u_px});
  }
  std::stable_sort(g.detections.begin(), g.detections.end(),
                   [](const CameraObservation& a, const CameraObservation& b) { return a.node < b.node; });

  g.initial_poses = PosesFromTrack(g, fix_times, track, passage.calibration);
  if (absl::Status s = SolvePoseGraph(passage.calibration, options.max_init_iterations, &g); !s.ok()) return s;
  return g;
}

}  // namespace crowdmap
