#include "server/passage_schedule.h"

#include <cmath>
#include <limits>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

const LatLon kOrigin{48.137, 11.575};

// A straight route from `from` to `to` (East/North metres about kOrigin), a fix every 10 m.
Passage StraightRoute(const Eigen::Vector2d& from, const Eigen::Vector2d& to) {
  const LocalFrame frame(kOrigin);
  Passage p;
  const int steps = static_cast<int>(std::ceil((to - from).norm() / 10.0));
  for (int i = 0; i <= steps; ++i) {
    const LatLon ll = frame.ToGeo(from + (to - from) * (static_cast<double>(i) / steps));
    GnssFix fix;
    fix.t_s = i;
    fix.lat_deg = ll.lat_deg;
    fix.lon_deg = ll.lon_deg;
    p.gnss.push_back(fix);
  }
  return p;
}

TEST(PassageSchedule, AFootprintKeepsTheRouteEndsAndPointsAboutTheSpacingApart) {
  const Passage route = StraightRoute({0.0, 0.0}, {0.0, 1005.0});
  const RouteFootprint footprint = FootprintOf(route, 100.0);
  ASSERT_GE(footprint.points.size(), 10u);
  EXPECT_LE(footprint.points.size(), 12u);
  EXPECT_DOUBLE_EQ(footprint.points.front().lat_deg, route.gnss.front().lat_deg);
  EXPECT_DOUBLE_EQ(footprint.points.back().lat_deg, route.gnss.back().lat_deg);
  const LocalFrame frame(kOrigin);
  for (size_t i = 1; i + 1 < footprint.points.size(); ++i) {
    const double step = (frame.ToLocal(footprint.points[i]) - frame.ToLocal(footprint.points[i - 1])).norm();
    EXPECT_GE(step, 99.9);
    EXPECT_LE(step, 110.1);
  }
  EXPECT_TRUE(FootprintOf(Passage()).points.empty());
}

TEST(PassageSchedule, SeparationIsTheLeastDistanceBetweenTwoRoutes) {
  const RouteFootprint a = FootprintOf(StraightRoute({0.0, 0.0}, {0.0, 2000.0}));
  const RouteFootprint b = FootprintOf(StraightRoute({300.0, 500.0}, {1500.0, 500.0}));
  EXPECT_NEAR(Separation(a, b), 300.0, 3.0);
  EXPECT_NEAR(Separation(b, a), Separation(a, b), 1e-9);
  const RouteFootprint crossing = FootprintOf(StraightRoute({-500.0, 1000.0}, {500.0, 1000.0}));
  EXPECT_LT(Separation(a, crossing), 100.0);  // to within the footprints' spacing
  EXPECT_EQ(Separation(a, RouteFootprint()), std::numeric_limits<double>::infinity());
}

TEST(PassageSchedule, TakesTheCandidateFurthestFromThePassagesInFlight) {
  const RouteFootprint in_flight = FootprintOf(StraightRoute({0.0, 0.0}, {0.0, 2000.0}));
  ScheduleCandidate near;  // 200 m off
  near.route = FootprintOf(StraightRoute({200.0, 0.0}, {200.0, 2000.0}));
  ScheduleCandidate far;  // 3 km off
  far.route = FootprintOf(StraightRoute({3000.0, 0.0}, {3000.0, 2000.0}));
  ScheduleCandidate middle;  // 1 km off
  middle.route = FootprintOf(StraightRoute({1000.0, 0.0}, {1000.0, 2000.0}));

  // Nothing in flight: arrival order.
  EXPECT_EQ(PickNextPassage({near, far, middle}, {}, 8), 0u);
  EXPECT_EQ(PickNextPassage({near, far, middle}, {&in_flight}, 8), 1u);
  EXPECT_EQ(PickNextPassage({near, middle}, {&in_flight}, 8), 1u);
  // Against two in flight, the least separation counts: `far` is 200 m from the second.
  const RouteFootprint beside_far = FootprintOf(StraightRoute({2800.0, 0.0}, {2800.0, 2000.0}));
  EXPECT_EQ(PickNextPassage({near, far, middle}, {&in_flight, &beside_far}, 8), 2u);
  // The oldest, passed over often enough, is taken whatever its route.
  near.passed_over = 8;
  EXPECT_EQ(PickNextPassage({near, far, middle}, {&in_flight}, 8), 0u);
  // A passage without a route (not decodable) is taken at once: it is finished without a computation.
  near.passed_over = 0;
  ScheduleCandidate undecodable;
  EXPECT_EQ(PickNextPassage({near, undecodable, far}, {&in_flight}, 8), 1u);
}

}  // namespace
}  // namespace crowdmap
