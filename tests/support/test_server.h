#ifndef CROWDMAP_TESTS_SUPPORT_TEST_SERVER_H_
#define CROWDMAP_TESTS_SUPPORT_TEST_SERVER_H_

#include <memory>
#include <string>

#include "core/sim/scenario.h"
#include "gtest/gtest.h"
#include "server/map_server.h"

namespace crowdmap {

// Server options for an in-process test: loopback, ephemeral port, the given database file.
inline MapServerOptions TestServerOptions(const std::string& db_path, bool start_worker = true) {
  MapServerOptions options;
  options.listen = "127.0.0.1:0";
  options.db_path = db_path;
  options.start_worker = start_worker;
  options.worker.idle_poll = std::chrono::milliseconds(20);
  return options;
}

inline std::unique_ptr<MapServer> StartTestServer(const MapServerOptions& options) {
  auto server = MapServer::Start(options);
  EXPECT_TRUE(server.ok()) << server.status();
  return server.ok() ? std::move(*server) : nullptr;
}

// A short version of the thesis scenario so that a passage applies in milliseconds.
inline Scenario ShortScenario(int landmarks = 6, double duration_s = 40.0) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.duration_s = duration_s;
  auto scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  return *std::move(scenario);
}

// `passage` with its detections of landmark `from` reported as `to`: a landmark it alone sees,
// which excluding it removes from the map.
inline Passage WithLandmarkRenamed(Passage passage, LandmarkId from, LandmarkId to) {
  int renamed = 0;
  for (Detection& d : passage.detections) {
    if (d.landmark_id == from) {
      d.landmark_id = to;
      ++renamed;
    }
  }
  EXPECT_GT(renamed, 0) << "the passage does not see landmark " << from;
  return passage;
}

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_SUPPORT_TEST_SERVER_H_
