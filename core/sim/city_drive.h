#ifndef CROWDMAP_CORE_SIM_CITY_DRIVE_H_
#define CROWDMAP_CORE_SIM_CITY_DRIVE_H_

#include <random>
#include <vector>

#include <Eigen/Core>

#include "core/model/motion_model.h"
#include "core/model/passage.h"
#include "core/sim/city_layout.h"
#include "core/sim/city_options.h"

namespace crowdmap {

// The true motion of one passage through the city, generated with the bicycle model itself (so
// exactly consistent with the estimator's motion model): poses[j] is the rear-axle pose at
// inputs[j].t_s = j * dt_s, and poses[j + 1] = BicycleStep(poses[j], inputs[j], dt_s).
struct CityDrive {
  double dt_s = 0.04;
  double wheelbase_m = 2.7;
  std::vector<Pose2> poses;
  std::vector<OdometrySample> inputs;
  double duration_s = 0.0;  // inputs.back().t_s
  double length_m = 0.0;    // distance driven from t = 0 to duration_s
  std::vector<Eigen::Vector2d> lane_m;  // the lane the driver followed, as a polyline
  int turns = 0;                        // left and right turns at intersections
  int stops = 0;                        // times it stood still before an intersection

  // True pose at t_s, by the same bicycle steps.
  Pose2 PoseAt(double t_s) const;
};

// Radius (m) of the lane's arc through a right or left turn: 7 m and 11 m with 10 m wide roads, so
// that a right turn stays clear of the kerb's corner.
double TurnRadiusM(const CityLayout& layout, bool right_turn);

// Drives options.route_length_m along a random route: from a random point of a random street,
// keeping right (in the middle of the right half of the carriageway), choosing at each
// intersection at random among the streets ahead, left and right (no U-turn). The driver follows
// the lane (straight, then arcs through turns) by pure pursuit, so the curvature is continuous, with steering limited
// to options.max_steering_rad; cruises at `cruise_mps` and slows to options.turn_speed_mps through
// turns. With options.stop_probability it brakes to a standstill before some intersections and
// waits there (options.stop_min_s .. stop_max_s). Only the westernmost `streets_x` north-south streets (and the east-west streets between
// them) are driven; all of them when it is larger. All randomness is drawn from `rng`.
CityDrive DriveRandomRoute(const CityLayout& layout, const CityScenarioOptions& options, double dt_s,
                           double cruise_mps, std::mt19937_64* rng, int streets_x);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_CITY_DRIVE_H_
