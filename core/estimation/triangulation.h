#ifndef CROWDMAP_CORE_ESTIMATION_TRIANGULATION_H_
#define CROWDMAP_CORE_ESTIMATION_TRIANGULATION_H_

#include <optional>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "core/geo/local_frame.h"
#include "core/map/map_state.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

// A projection line: through the camera centre, along the detection's bearing.
struct BearingRay {
  Eigen::Vector2d origin;
  Eigen::Vector2d direction;  // unit
};

// The projection line of a detection at pixel u seen from a vehicle pose.
BearingRay CameraRay(const Pose2& pose, const Calibration& calib, double u_px);

// Normal equations of the point minimising the sum of squared orthogonal distances to lines.
struct RayIntersection {
  Eigen::Matrix2d normal = Eigen::Matrix2d::Zero();  // sum of (I - d d^T)
  Eigen::Vector2d rhs = Eigen::Vector2d::Zero();     // sum of (I - d d^T) o
  int rays = 0;

  void Add(const BearingRay& ray);
  // The least-squares point, or nullopt with fewer than two rays or nearly parallel ones
  // (smallest eigenvalue of `normal` below min_eigenvalue).
  std::optional<Eigen::Vector2d> Solve(double min_eigenvalue = 1e-4) const;
};

// Least-squares intersection of rays (thesis section 4.2, eq. 4.1).
std::optional<Eigen::Vector2d> IntersectRays(const std::vector<BearingRay>& rays);

// The thesis's triangulation baseline: every landmark estimated from all projection lines of all
// passages, independently of the others, with no covariance. Vehicle poses come from GNSS and
// odometry only (the passage's pose graph without landmarks). For comparison, not for service.
class TriangulationMapper {
 public:
  // Adds the passage's projection lines and re-solves the landmarks it saw.
  absl::Status AddPassage(const Passage& passage);
  // The current estimates as a map (covariance set to NaN: the method provides none).
  const MapState& map() const { return map_; }

 private:
  struct Accumulator {
    LatLon anchor;  // the normal equations are kept in the East/North frame at this point
    RayIntersection lines;
  };
  std::unordered_map<LandmarkId, Accumulator> accumulators_;
  MapState map_;
  int64_t passages_ = 0;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_TRIANGULATION_H_
