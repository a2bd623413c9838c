#ifndef CROWDMAP_CLIENT_MAPSIM_FLEET_H_
#define CROWDMAP_CLIENT_MAPSIM_FLEET_H_

#include <chrono>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client/api/map_client.h"
#include "client/mapsim/experiment.h"
#include "core/sim/city_scenario.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// A simulated fleet against a running mapd: passages 0..P-1 of the scenario uploaded by V
// concurrent vehicles (vehicle v uploads passages v, v+V, ... in order), then read back.
struct FleetOptions {
  std::string server = "127.0.0.1:50051";
  ScenarioOptions scenario;
  int passages = 40;
  int vehicles = 4;
  std::string strategy;  // expected server strategy (cc | dc | cc-gsd); empty = whatever it runs
  std::chrono::milliseconds sample_interval{250};  // map read back and evaluated this often while applying
  std::chrono::seconds apply_timeout{1800};
  MapClientOptions client;  // `server` above overrides client.server
  // After the run, apply the passages in-process in the server's arrival order and compare the
  // maps (needs a server whose map started empty; the loop's passages only).
  bool replay = true;
  // City passages (CityScenario, `city_scenario`) instead of the loop's (`scenario`).
  bool city = false;
  CityScenarioOptions city_scenario;

  absl::Status Validate() const;
};

// Where the run is, for progress output.
struct FleetProgress {
  int uploaded = 0;
  int applied = 0;  // passages the server finished (applied, rejected or failed) since the start
  int total = 0;
  double mean_dist_err_m = -1.0;  // of the last sampled map; < 0 before the first sample
  // The passage count of the joint solve the server is running (the young map's warm-up or a
  // re-solve of all its passages, which takes seconds while the count stands still); 0 = none.
  int64_t joint_solve_of = 0;
};

// The passage count of the joint solve the server's next passage takes (from the estimator
// settings GetMapInfo reports), or 0 when it is a sequential update.
int64_t JointSolveUnderWay(const pb::MapInfo& info);

// The fleet's passages applied in-process in the order the server received them: the server must
// give exactly this map; the experiment in passage order may differ (the estimator is nonlinear,
// so the order of the first passages matters).
struct FleetReplay {
  double final_mean_dist_err_m = 0.0;
  double max_position_diff_m = 0.0;  // over landmarks, server map vs replay
  double max_cov_diff_m2 = 0.0;      // largest covariance entry difference
  int missing_landmarks = 0;         // in one map and not the other
};

struct FleetResult {
  // Records are sampled maps (passage = passages finished when the map was read), not one per
  // passage: the server applies passages faster than a client can read every intermediate map.
  // The last record is the final map; final_nees_per_dof and final_joint_nees_per_dof are those
  // of the final map; solve_ms of a record is the median server time of the passages finished since the previous one.
  ExperimentResult experiment;
  std::vector<pb::Landmark> landmarks;  // the final map, as returned by QueryRegion
  int64_t map_version = 0;
  std::string server_strategy;
  MapUpdateOptions server_update;  // the server's other estimator settings (GetMapInfo)
  int duplicates = 0;       // uploads the server already had (an earlier run on the same database)
  double upload_s = 0.0;    // first upload to last acknowledgement
  double apply_s = 0.0;     // first upload to the queue drained
  std::vector<int> arrival_order;     // scenario passage indices in server id (= apply) order
  std::optional<FleetReplay> replay;  // when options.replay and the run allowed it

  std::string Brief() const;
};

absl::StatusOr<FleetResult> RunFleet(const FleetOptions& options,
                                     const std::function<void(const FleetProgress&)>& progress = nullptr);

// Writes DIR/passages.csv, DIR/summary.json, DIR/errors.svg (as `mapsim experiment`) and
// DIR/map.geojson (with the 95% error ellipses).
absl::Status WriteFleetOutputs(const FleetOptions& options, const FleetResult& result, const std::string& dir);

// Writes passages 0..P-1 of the scenario to DIR/passage-NNNNN.json (or .pb), files that
// `mapctl upload` accepts.
absl::Status ExportPassages(const ScenarioOptions& scenario, int passages, bool binary, const std::string& dir);
// The same for passages make_passage(0..P-1) of any source (e.g. CityScenario::MakePassage).
absl::Status ExportPassages(const std::function<Passage(int)>& make_passage, int passages, bool binary,
                            const std::string& dir);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_FLEET_H_
