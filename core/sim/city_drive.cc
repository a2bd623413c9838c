#include "core/sim/city_drive.h"

#include <algorithm>
#include <cmath>

#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

constexpr double kLookaheadM = 6.0;  // pure pursuit; on an arc of radius R it steers exactly 1 / R
constexpr double kArcStepRad = 0.05;
constexpr double kAccelerationMps2 = 1.5;
constexpr double kDecelerationMps2 = 2.0;
constexpr double kStopBeforeKerbM = 2.0;  // a stopped vehicle waits this far before the crossing
constexpr int kDx[4] = {1, 0, -1, 0};      // east, north, west, south
constexpr int kDy[4] = {0, 1, 0, -1};

// A polyline with arc length, followed by a pure-pursuit driver.
class LanePath {
 public:
  void Add(const Eigen::Vector2d& p) {
    cumulative_m_.push_back(points_.empty() ? 0.0 : cumulative_m_.back() + (p - points_.back()).norm());
    points_.push_back(p);
  }
  double length_m() const { return cumulative_m_.back(); }
  const std::vector<Eigen::Vector2d>& points() const { return points_; }

  Eigen::Vector2d PointAt(double s_m) const {
    s_m = std::clamp(s_m, 0.0, length_m());
    const size_t k = std::min<size_t>(
        std::upper_bound(cumulative_m_.begin(), cumulative_m_.end(), s_m) - cumulative_m_.begin(), points_.size() - 1);
    const double len = cumulative_m_[k] - cumulative_m_[k - 1];
    const double t = len > 0.0 ? (s_m - cumulative_m_[k - 1]) / len : 0.0;
    return points_[k - 1] + t * (points_[k] - points_[k - 1]);
  }

  // Arc length of the point of the path nearest to p, searched a few segments ahead of the last
  // answer (never behind it).
  double Project(const Eigen::Vector2d& p, double last_s_m) {
    double best_d2 = INFINITY, best_s = last_s_m;
    const size_t end = std::min(points_.size() - 1, segment_ + 8);
    for (size_t k = segment_; k < end; ++k) {
      const Eigen::Vector2d d = points_[k + 1] - points_[k];
      const double t = std::clamp((p - points_[k]).dot(d) / std::max(d.squaredNorm(), 1e-12), 0.0, 1.0);
      const double d2 = (points_[k] + t * d - p).squaredNorm();
      if (d2 < best_d2) {
        best_d2 = d2;
        best_s = cumulative_m_[k] + t * d.norm();
        best_segment_ = k;
      }
    }
    segment_ = best_segment_;
    return std::max(best_s, last_s_m);
  }

 private:
  std::vector<Eigen::Vector2d> points_;
  std::vector<double> cumulative_m_;
  size_t segment_ = 0, best_segment_ = 0;
};

struct Route {
  LanePath lane;
  std::vector<double> turn_s_m;  // arc length at the middle of each turn's arc
  std::vector<double> stop_s_m;  // arc length where the vehicle would stop before each intersection
  double heading_rad = 0.0;
};

Route RandomRoute(const CityLayout& layout, double lane_offset_m, double length_needed_m, int streets_x,
                  std::mt19937_64* rng) {
  const std::vector<double>& xs = layout.street_x_m();
  const std::vector<double>& ys = layout.street_y_m();
  const int nx = std::min(static_cast<int>(xs.size()), streets_x), ny = static_cast<int>(ys.size());
  auto valid = [&](int i, int j, int d) {
    const int ni = i + kDx[d], nj = j + kDy[d];
    return ni >= 0 && ni < nx && nj >= 0 && nj < ny;
  };
  auto node = [&](int i, int j) { return Eigen::Vector2d(xs[i], ys[j]); };
  auto right = [](int d) { return Eigen::Vector2d(kDy[d], -kDx[d]); };

  std::uniform_int_distribution<int> pick_i(0, nx - 1), pick_j(0, ny - 1), pick_d(0, 3);
  std::uniform_real_distribution<double> pick_fraction(0.2, 0.8);
  int i = 0, j = 0, d = 0;
  do {
    i = pick_i(*rng);
    j = pick_j(*rng);
    d = pick_d(*rng);
  } while (!valid(i, j, d));
  Route route;
  route.heading_rad = std::atan2(kDy[d], kDx[d]);
  const double fraction = pick_fraction(*rng);
  route.lane.Add(node(i, j) + fraction * (node(i + kDx[d], j + kDy[d]) - node(i, j)) + lane_offset_m * right(d));
  i += kDx[d];
  j += kDy[d];
  while (true) {
    const Eigen::Vector2d end = node(i, j) + lane_offset_m * right(d);
    if (route.lane.length_m() + (end - route.lane.points().back()).norm() >= length_needed_m) {
      route.lane.Add(end);
      return route;
    }
    int choices[3], count = 0;
    for (int next : {d, (d + 1) % 4, (d + 3) % 4}) {
      if (valid(i, j, next)) choices[count++] = next;
    }
    const int next = choices[std::uniform_int_distribution<int>(0, count - 1)(*rng)];
    // Where the incoming and outgoing lane lines cross (on the incoming lane when going straight).
    const Eigen::Vector2d turn_shift = next != d ? Eigen::Vector2d(lane_offset_m * right(next)) : Eigen::Vector2d::Zero();
    const Eigen::Vector2d corner = node(i, j) + lane_offset_m * right(d) + turn_shift;
    if (next == d) {
      route.lane.Add(corner);
      route.stop_s_m.push_back(route.lane.length_m() - layout.road_half_width_m() - kStopBeforeKerbM);
    } else {
      // A circular arc tangent to both lane lines; a right turn is tighter than a left one.
      const bool right_turn = next == (d + 3) % 4;
      const double radius_m = TurnRadiusM(layout, right_turn);
      const Eigen::Vector2d d_in(kDx[d], kDy[d]), d_out(kDx[next], kDy[next]);
      const Eigen::Vector2d center = corner - radius_m * d_in + radius_m * d_out;
      const double from = std::atan2(-d_out.y(), -d_out.x()), sweep = right_turn ? -M_PI / 2 : M_PI / 2;
      const int steps = static_cast<int>(std::ceil(std::abs(sweep) / kArcStepRad));
      for (int k = 0; k <= steps; ++k) {
        const double a = from + sweep * k / steps;
        route.lane.Add(center + radius_m * Eigen::Vector2d(std::cos(a), std::sin(a)));
        if (k == 0) route.stop_s_m.push_back(route.lane.length_m() - kStopBeforeKerbM);
        if (k == steps / 2) route.turn_s_m.push_back(route.lane.length_m());
      }
    }
    d = next;
    i += kDx[d];
    j += kDy[d];
  }
}

// Highest speed at arc length s_m that still lets the vehicle slow to turn_mps for each turn
// (from one lookahead before the middle of its arc to one after).
double AllowedSpeed(const std::vector<double>& turn_s_m, double s_m, double cruise_mps, double turn_mps) {
  double v = cruise_mps;
  for (double turn : turn_s_m) {
    const double before_m = turn - kLookaheadM - s_m;
    if (before_m < -2.0 * kLookaheadM) continue;
    if (before_m > cruise_mps * cruise_mps / (2.0 * kDecelerationMps2)) break;
    v = std::min(v, std::sqrt(turn_mps * turn_mps + 2.0 * kDecelerationMps2 * std::max(0.0, before_m)));
  }
  return v;
}

}  // namespace

double TurnRadiusM(const CityLayout& layout, bool right_turn) {
  return (right_turn ? 1.4 : 2.2) * layout.road_half_width_m();
}

Pose2 CityDrive::PoseAt(double t_s) const { return PoseAlongInputs(poses, inputs, dt_s, wheelbase_m, t_s); }

CityDrive DriveRandomRoute(const CityLayout& layout, const CityScenarioOptions& options, double dt_s,
                           double cruise_mps, std::mt19937_64* rng, int streets_x) {
  const double lane_offset_m = 0.5 * layout.road_half_width_m();
  Route route =
      RandomRoute(layout, lane_offset_m, options.route_length_m + 2.0 * kLookaheadM + 20.0, streets_x, rng);
  CityDrive drive;
  drive.dt_s = dt_s;
  drive.wheelbase_m = options.calibration.wheelbase_m;
  drive.lane_m = route.lane.points();
  drive.turns = static_cast<int>(route.turn_s_m.size());

  const double max_curvature_wheelbase = std::sin(options.max_steering_rad);
  const double turn_mps = std::min(options.turn_speed_mps, cruise_mps);
  const Eigen::Vector2d start = route.lane.points().front();
  Pose2 pose(start.x(), start.y(), route.heading_rad);

  // Stops before intersections, drawn after the route (which then does not depend on them) and
  // only when they are asked for (so that the passages of a seed stay what they were).
  struct Stop {
    double s_m, standing_s;
  };
  std::vector<Stop> stops;
  double standing_total_s = 0.0;
  if (options.stop_probability > 0.0) {
    std::uniform_real_distribution<double> unit(0.0, 1.0), standing(options.stop_min_s, options.stop_max_s);
    for (double stop_s_m : route.stop_s_m) {
      if (unit(*rng) >= options.stop_probability) continue;
      stops.push_back({stop_s_m, standing(*rng)});
      standing_total_s += stops.back().standing_s;
    }
  }
  size_t next_stop = 0;
  double stand_until_s = -1.0;  // while standing, the time the vehicle drives on

  double s_m = 0.0, v = 0.0;
  const int max_steps =
      static_cast<int>((options.route_length_m / (0.5 * turn_mps) + standing_total_s) / dt_s) + 10 + 2 * stops.size();
  for (int j = 0; j < max_steps; ++j) {
    const double t_s = j * dt_s;
    s_m = route.lane.Project(pose.head<2>(), s_m);
    double allowed = AllowedSpeed(route.turn_s_m, s_m, cruise_mps, turn_mps);
    while (next_stop < stops.size() && stand_until_s < 0.0 && stops[next_stop].s_m < s_m - 1.0) ++next_stop;
    if (next_stop < stops.size()) {
      const double gap_m = stops[next_stop].s_m - s_m;
      // Standing once the next step would reach the stop line; braking at kDecelerationMps2 before.
      if (stand_until_s < 0.0 && gap_m <= v * dt_s + 1e-3) {
        stand_until_s = t_s + stops[next_stop].standing_s;
        ++drive.stops;
      }
      if (stand_until_s >= 0.0 && t_s >= stand_until_s) {
        ++next_stop;
        stand_until_s = -1.0;
      } else if (stand_until_s >= 0.0) {
        allowed = 0.0;
      } else {
        // The speed from which steps of dt_s, each losing kDecelerationMps2 * dt_s, cover gap_m:
        // gap = v^2 / (2 a) + v dt / 2.
        const double half_step = 0.5 * kDecelerationMps2 * dt_s;
        allowed = std::min(allowed, std::sqrt(half_step * half_step + 2.0 * kDecelerationMps2 * std::max(0.0, gap_m)) -
                                        half_step);
      }
    }
    v = j == 0 ? allowed : std::min(allowed, v + kAccelerationMps2 * dt_s);
    const Eigen::Vector2d ahead = route.lane.PointAt(s_m + kLookaheadM) - pose.head<2>();
    const double c = std::cos(pose.z()), s = std::sin(pose.z());
    const Eigen::Vector2d local(c * ahead.x() + s * ahead.y(), -s * ahead.x() + c * ahead.y());
    // Pure pursuit: the arc through the lookahead point has curvature 2 y / |p|^2; the bicycle
    // model turns with curvature sin(steering) / wheelbase.
    const double curvature = 2.0 * local.y() / std::max(local.squaredNorm(), 1e-6);
    const double steering =
        std::asin(std::clamp(curvature * drive.wheelbase_m, -max_curvature_wheelbase, max_curvature_wheelbase));
    drive.poses.push_back(pose);
    drive.inputs.push_back({t_s, v, steering});
    if (drive.length_m >= options.route_length_m) break;
    pose = BicycleStep(pose, v, steering, dt_s, drive.wheelbase_m);
    drive.length_m += v * dt_s;
  }
  drive.duration_s = drive.inputs.back().t_s;
  return drive;
}

}  // namespace crowdmap
