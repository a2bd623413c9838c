#ifndef CROWDMAP_CLIENT_MAPSIM_BENCH_H_
#define CROWDMAP_CLIENT_MAPSIM_BENCH_H_

#include <string>

#include "absl/status/statusor.h"
#include "client/api/client_security.h"
#include "core/sim/city_scenario.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Load test of a running mapd (use a scratch database: the passages are applied to its map).
// K clients upload P simulated passages as fast as acknowledgements come back; then R readers
// issue QueryRegion (the route's bounding box) and GetTile (the tiles of the route's landmarks)
// while the worker applies the queue: until it is drained or `read_seconds` pass, whichever comes
// first, so every measured read competes with map updates.
struct BenchOptions {
  std::string server = "127.0.0.1:50051";
  ClientSecurityOptions security;  // TLS and token of every client
  ScenarioOptions scenario;
  // City passages (CityScenario) instead of the loop's; the read box is then the whole city.
  bool city = false;
  CityScenarioOptions city_scenario;
  // Uploads per second over all clients, 0 = as fast as acknowledgements come back. A paced run
  // spreads the uploads over the worker's commits, so that acknowledgements are measured while
  // the map is being updated.
  double upload_rate_per_s = 0.0;
  int clients = 8;
  int passages = 400;
  int readers = 8;
  double read_seconds = 10.0;

  absl::Status Validate() const;
};

struct LatencyStats {
  int64_t calls = 0;
  double p50_ms = 0.0;
  double p99_ms = 0.0;
  double max_ms = 0.0;
};

struct BenchResult {
  int passages = 0;
  double upload_s = 0.0;
  double uploads_per_s = 0.0;  // durable acknowledgements per second, K concurrent clients
  LatencyStats ack;            // one upload's acknowledgement
  double apply_s = 0.0;        // first upload to the queue drained
  double applied_per_s = 0.0;  // passages finished by the worker per second over apply_s
  double read_s = 0.0;         // length of the read phase
  LatencyStats query_region;
  LatencyStats get_tile;
  int64_t landmarks_in_box = 0;

  std::string Brief() const;
};

absl::StatusOr<BenchResult> RunBench(const BenchOptions& options);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_BENCH_H_
