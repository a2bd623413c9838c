#include "server/passage_schedule.h"

#include <cmath>
#include <limits>

namespace crowdmap {
namespace {

constexpr double kMetresPerRadian = 6371008.8;  // mean Earth radius
constexpr double kRadiansPerDegree = M_PI / 180.0;

// East/North distance of two points a few kilometres apart at most (equirectangular about their
// mean latitude; well under 1% off there, which is all a schedule needs).
double Distance(const LatLon& a, const LatLon& b) {
  const double mean_lat = 0.5 * (a.lat_deg + b.lat_deg) * kRadiansPerDegree;
  const double north = (b.lat_deg - a.lat_deg) * kRadiansPerDegree;
  const double east = (b.lon_deg - a.lon_deg) * kRadiansPerDegree * std::cos(mean_lat);
  return kMetresPerRadian * std::hypot(east, north);
}

}  // namespace

RouteFootprint FootprintOf(const Passage& passage, double spacing_m) {
  RouteFootprint out;
  for (const GnssFix& fix : passage.gnss) {
    const LatLon p{fix.lat_deg, fix.lon_deg};
    if (out.points.empty() || Distance(out.points.back(), p) >= spacing_m) out.points.push_back(p);
  }
  if (!passage.gnss.empty()) {
    const LatLon last{passage.gnss.back().lat_deg, passage.gnss.back().lon_deg};
    if (Distance(out.points.back(), last) > 0.0) out.points.push_back(last);
  }
  return out;
}

double Separation(const RouteFootprint& a, const RouteFootprint& b) {
  double least = std::numeric_limits<double>::infinity();
  for (const LatLon& p : a.points) {
    for (const LatLon& q : b.points) least = std::min(least, Distance(p, q));
  }
  return least;
}

size_t PickNextPassage(const std::vector<ScheduleCandidate>& candidates,
                       const std::vector<const RouteFootprint*>& in_flight, int max_passed_over) {
  if (in_flight.empty() || candidates.front().passed_over >= max_passed_over) return 0;
  size_t best = 0;
  double best_separation = -1.0;
  for (size_t i = 0; i < candidates.size(); ++i) {
    if (!candidates[i].route) return i;
    double separation = std::numeric_limits<double>::infinity();
    for (const RouteFootprint* other : in_flight) separation = std::min(separation, Separation(*candidates[i].route, *other));
    if (separation > best_separation) {
      best = i;
      best_separation = separation;
    }
  }
  return best;
}

}  // namespace crowdmap
