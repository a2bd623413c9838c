#include "core/estimation/triangulation.h"

#include <cmath>
#include <limits>

#include <Eigen/Eigenvalues>

#include "core/estimation/graph_builder.h"

namespace crowdmap {

BearingRay CameraRay(const Pose2& pose, const Calibration& calib, double u_px) {
  // Inverse of u = -fx c_y / c_x + cx: the bearing in the camera frame is (fx, cx - u).
  const double bearing_cam = std::atan2(calib.cx_px - u_px, calib.fx_px);
  const double c = std::cos(pose.z()), s = std::sin(pose.z());
  BearingRay ray;
  ray.origin = pose.head<2>() + Eigen::Vector2d(c * calib.camera_position_m.x() - s * calib.camera_position_m.y(),
                                                s * calib.camera_position_m.x() + c * calib.camera_position_m.y());
  const double angle = pose.z() + calib.camera_yaw_rad + bearing_cam;
  ray.direction = {std::cos(angle), std::sin(angle)};
  return ray;
}

void RayIntersection::Add(const BearingRay& ray) {
  const Eigen::Matrix2d projector = Eigen::Matrix2d::Identity() - ray.direction * ray.direction.transpose();
  normal += projector;
  rhs += projector * ray.origin;
  ++rays;
}

std::optional<Eigen::Vector2d> RayIntersection::Solve(double min_eigenvalue) const {
  if (rays < 2) return std::nullopt;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(normal);
  if (eig.eigenvalues()(0) < min_eigenvalue) return std::nullopt;
  return Eigen::Vector2d(normal.ldlt().solve(rhs));
}

std::optional<Eigen::Vector2d> IntersectRays(const std::vector<BearingRay>& rays) {
  RayIntersection lines;
  for (const BearingRay& r : rays) lines.Add(r);
  return lines.Solve();
}

absl::Status TriangulationMapper::AddPassage(const Passage& passage) {
  GraphOptions options;
  options.detections_per_landmark = 0;  // every projection line
  absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, options);
  if (!graph.ok()) return graph.status();
  ++passages_;
  // Rays are moved into each landmark's anchor frame through two points on the line.
  std::unordered_map<LandmarkId, bool> seen;
  for (const CameraObservation& d : graph->detections) {
    const BearingRay ray = CameraRay(graph->initial_poses[d.node], passage.calibration, d.u_px);
    const LatLon a = graph->frame.ToGeo(ray.origin);
    const LatLon b = graph->frame.ToGeo(ray.origin + 30.0 * ray.direction);
    auto [it, inserted] = accumulators_.try_emplace(d.landmark_id);
    if (inserted) it->second.anchor = a;
    const LocalFrame anchor(it->second.anchor);
    BearingRay moved;
    moved.origin = anchor.ToLocal(a);
    moved.direction = (anchor.ToLocal(b) - moved.origin).normalized();
    it->second.lines.Add(moved);
    seen[d.landmark_id] = true;
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (const auto& [id, unused] : seen) {
    const Accumulator& acc = accumulators_.at(id);
    std::optional<Eigen::Vector2d> p = acc.lines.Solve();
    if (!p) continue;
    Landmark lm;
    if (const Landmark* old = map_.FindLandmark(id)) lm = *old;
    lm.id = id;
    lm.position = LocalFrame(acc.anchor).ToGeo(*p);
    lm.cov_en_m2 = Eigen::Matrix2d::Constant(nan);
    lm.version = passages_;
    lm.passages_seen += 1;
    map_.PutLandmark(lm);
  }
  map_.set_version(passages_);
  return absl::OkStatus();
}

}  // namespace crowdmap
