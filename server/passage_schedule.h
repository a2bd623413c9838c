#ifndef CROWDMAP_SERVER_PASSAGE_SCHEDULE_H_
#define CROWDMAP_SERVER_PASSAGE_SCHEDULE_H_

// Which claimed passage a map worker takes next when several compute updates at once. An update is
// computed again when a change committed meanwhile wrote what it read (map_worker.h), and what a
// passage reads and writes lies along its route: two passages whose routes are far apart are
// computed side by side without conflict. So among the next few queued passages a worker takes the
// one whose route lies furthest from the routes of the passages being computed, unless the oldest
// has been passed over too often.

#include <cstddef>
#include <optional>
#include <vector>

#include "core/geo/local_frame.h"
#include "core/model/passage.h"

namespace crowdmap {

// A passage's route as points at least `spacing_m` apart along its GNSS fixes (the first and last
// fix kept).
struct RouteFootprint {
  std::vector<LatLon> points;
};
RouteFootprint FootprintOf(const Passage& passage, double spacing_m = 100.0);

// The least distance (m) between the two routes' points: the routes' own to within the
// footprints' spacing (East/North distances of nearby points; +infinity when either route is
// empty).
double Separation(const RouteFootprint& a, const RouteFootprint& b);

struct ScheduleCandidate {
  // Absent: the passage has no route (it could not be decoded): taken first, it is finished at once.
  std::optional<RouteFootprint> route;
  int passed_over = 0;  // times a later candidate was taken before it
};

// The index of the candidate to take: `candidates` oldest first, `in_flight` the routes of the
// passages being computed. The oldest when nothing is being computed or when it has been passed
// over `max_passed_over` times; otherwise the one whose least separation from the passages in
// flight is largest (the oldest of equals). `candidates` must not be empty.
size_t PickNextPassage(const std::vector<ScheduleCandidate>& candidates,
                       const std::vector<const RouteFootprint*>& in_flight, int max_passed_over);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_PASSAGE_SCHEDULE_H_
