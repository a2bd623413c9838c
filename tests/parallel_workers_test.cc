// mapd with two workers: passages are computed concurrently, and the map it commits is exactly
// the one the same passages give applied one at a time in the order of their commits (to rounding).
#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <utility>
#include <vector>

#include <csignal>

#include "absl/strings/str_cat.h"
#include "core/map/map_window.h"
#include "core/sim/city_scenario.h"
#include "server/mapd_config.h"
#include "server/storage/sqlite_map_store.h"
#include "server/testing/temp_dir.h"
#include "tests/support/mapd_process.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// The passages in the order the service committed them (their results' map versions).
std::vector<Passage> InCommitOrder(MockVehicle* vehicle, const std::vector<Passage>& passages) {
  std::vector<std::pair<int64_t, const Passage*>> by_version;
  for (const Passage& p : passages) {
    absl::StatusOr<pb::PassageStatus> status = vehicle->GetPassage(p.vehicle_id, p.passage_id);
    EXPECT_TRUE(status.ok()) << status.status();
    if (!status.ok()) continue;
    EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED) << p.passage_id << ": " << status->error();
    by_version.emplace_back(status->result().map_version(), &p);
  }
  std::sort(by_version.begin(), by_version.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  std::vector<Passage> out;
  for (const auto& [version, p] : by_version) out.push_back(*p);
  return out;
}

// With options.relinearize_sigmas, each passage is followed by its re-linearisations, as the
// service's worker does them when each passage finds it idle; or, with `after_backlog`, they all
// follow the last passage (as many as were owed), as after a backlog. `relinearized` counts them.
MapState ApplyInOrder(const std::vector<Passage>& passages, MapUpdateOptions options, int* relinearized = nullptr,
                      bool after_backlog = false) {
  const int per_passage = options.relinearizations_per_passage;
  if (after_backlog) options.relinearizations_per_passage = per_passage * static_cast<int>(passages.size());
  MapState map;
  MapUpdater updater(options);
  const auto passage_of = [&](const MapUpdater::PassageKey& key) -> absl::StatusOr<Passage> {
    for (const Passage& p : passages) {
      if (p.vehicle_id == key.first && p.passage_id == key.second) return p;
    }
    return absl::NotFoundError(key.second);
  };
  for (const Passage& passage : passages) {
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << passage.passage_id << ": " << update.status();
    if (!update.ok()) continue;
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
    if (after_backlog && &passage != &passages.back()) continue;
    const int count = RelinearizeStaleInMemory(passage_of, &updater, &map);
    if (relinearized != nullptr) *relinearized += count;
  }
  return map;
}

// Relative difference of two matrices or vectors.
template <typename A, typename B>
double Relative(const A& a, const B& b) {
  return (a - b).norm() / (1.0 + b.norm());
}

// Same landmarks, versions and factors (ids, landmarks, provenance), and the same numbers to
// rounding: a map computed twice from the same passages in the same order need not be equal to
// the bit (the dense kernels under CHOLMOD split their work by the threads free at the moment).
void ExpectSameMap(const MapState& expected, const MapState& actual) {
  constexpr double kRounding = 1e-9;
  EXPECT_EQ(actual.version(), expected.version());
  EXPECT_EQ(actual.last_factor_id(), expected.last_factor_id());
  ASSERT_EQ(actual.landmark_count(), expected.landmark_count());
  ASSERT_EQ(actual.factor_count(), expected.factor_count());
  double worst_position_m = 0.0;
  double worst_covariance = 0.0;
  double worst_information = 0.0;
  expected.ForEachLandmark([&](const Landmark& l) {
    const Landmark* a = actual.FindLandmark(l.id);
    ASSERT_NE(a, nullptr) << l.id;
    EXPECT_EQ(a->version, l.version) << l.id;
    EXPECT_EQ(a->passages_seen, l.passages_seen) << l.id;
    worst_position_m = std::max(worst_position_m, (a->Offset() - l.Offset()).norm());
    worst_covariance = std::max(worst_covariance, Relative(a->cov_en_m2, l.cov_en_m2));
    worst_information =
        std::max(worst_information, Relative(actual.InformationVector(l.id), expected.InformationVector(l.id)));
  });
  expected.ForEachFactor([&](const MapFactor& f) {
    const MapFactor* a = actual.FindFactor(f.id);
    ASSERT_NE(a, nullptr) << "factor " << f.id;
    EXPECT_EQ(a->landmarks, f.landmarks) << f.id;
    EXPECT_EQ(a->passage_id, f.passage_id) << f.id;
    worst_information = std::max(worst_information, Relative(a->information, f.information));
    worst_information = std::max(worst_information, Relative(a->information_vector, f.information_vector));
  });
  EXPECT_LE(worst_position_m, kRounding);
  EXPECT_LE(worst_covariance, kRounding);
  EXPECT_LE(worst_information, kRounding);
}

// `one_at_a_time`: each upload waits until the service is idle (queue empty, no re-linearisation
// due), so that each passage's re-linearisations follow it.
void RunWithWorkers(int workers, const std::vector<Passage>& passages, const MapUpdateOptions& update,
                    int* relinearized = nullptr, bool one_at_a_time = false) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.worker.workers = workers;
  options.worker.update = update;
  options.limits.vehicle_uploads_per_s = 0;  // the test's uploads come as fast as they can
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  for (const Passage& p : passages) {
    auto r = vehicle.Upload(p);
    ASSERT_TRUE(r.ok()) << r.status();
    if (one_at_a_time) {
      ASSERT_TRUE(vehicle.WaitUntilIdle().ok());
    }
  }
  auto info = vehicle.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  ASSERT_EQ(info->passages_applied(), static_cast<int64_t>(passages.size()));
  const MapState expected = ApplyInOrder(InCommitOrder(&vehicle, passages), update, relinearized);
  {
    SCOPED_TRACE("served map");
    ASSERT_TRUE(server->store()->ReadCommittedMap([&](const MapState& map) { ExpectSameMap(expected, map); }));
  }
  server->Shutdown(std::chrono::milliseconds(0));
  server.reset();
  auto store = CreateSqliteMapStore(dir.File("map.db"));
  ASSERT_TRUE(store.ok()) << store.status();
  MapState stored;
  ASSERT_TRUE((*store)->LoadMap(&stored).ok());
  SCOPED_TRACE("stored map");
  ExpectSameMap(expected, stored);
}

// Short partial routes on a street grid.
std::vector<Passage> CityPassages(int count) {
  CityScenarioOptions city;
  city.blocks_x = 10;
  city.blocks_y = 10;
  city.route_length_m = 600.0;
  auto scenario = CityScenario::Create(city);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  std::vector<Passage> passages;
  if (scenario.ok()) {
    for (int i = 0; i < count; ++i) passages.push_back(scenario->MakePassage(i));
  }
  return passages;
}

// `update` with two links of window, a retention of 6 passages so that commits also fold factors
// while the other worker computes, and no joint solves.
MapUpdateOptions CityUpdateOptions(MapUpdateOptions update = MapUpdateOptions()) {
  update.warmup_passages = 0;
  update.relinearize_until_passages = 0;
  update.window_hops = 2;
  update.retain_passages = 6;
  return update;
}

TEST(ParallelWorkers, CityPassagesGiveTheMapOfTheirCommitOrder) {
  RunWithWorkers(2, CityPassages(24), CityUpdateOptions());
}

// A young map's joint solves (the warm-up), computed by one worker while the other commits: a
// landmark or factor the solve has read may be gone, or new, by its next read. Such a computation
// is made again, and the map is the one of the commit order. (mapd --workers 2 crashed on a fresh
// map here: a window named a landmark the overlay no longer found.)
TEST(ParallelWorkers, AYoungMapsJointSolvesUnderAnotherWorkersCommits) {
  MapUpdateOptions update = CityUpdateOptions();
  update.warmup_passages = 8;
  update.retain_passages = 0;
  RunWithWorkers(2, CityPassages(12), update);
}

// Local re-linearisation in the service (mapd --relinearize-sigmas): once the queue is empty, the
// worker takes the stalest retained passage again for each passage applied, and commits it as a
// change of its own; the map served and stored is the in-process updater's with the same
// re-linearisations.
TEST(ServiceRelinearization, TheWorkerRelinearizesStalePassagesAsTheInProcessUpdaterDoes) {
  MapUpdateOptions update = CityUpdateOptions();
  update.relinearize_sigmas = 0.5;
  int relinearized = 0;
  RunWithWorkers(1, CityPassages(20), update, &relinearized, /*one_at_a_time=*/true);
  EXPECT_GE(relinearized, 3) << "the scenario must make passages stale";
}

// A backlog is applied first, one passage after the other, and the re-linearisations it earned
// follow once the queue is empty: the map is the one of applying every passage, then
// re-linearising the stalest passage up to once per passage (re-linearisations in between would
// give another map and other versions).
TEST(ServiceRelinearization, ABacklogIsAppliedFirstAndItsRelinearisationsFollow) {
  const std::vector<Passage> passages = CityPassages(16);
  MapUpdateOptions update = CityUpdateOptions();
  update.relinearize_sigmas = 0.5;
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"), /*start_worker=*/false);
  options.worker.update = update;
  options.limits.vehicle_uploads_per_s = 0;
  {
    auto queuing = StartTestServer(options);
    ASSERT_NE(queuing, nullptr);
    MockVehicle vehicle(queuing->address());
    for (const Passage& p : passages) ASSERT_TRUE(vehicle.Upload(p).ok());
    queuing->Shutdown(std::chrono::milliseconds(0));
  }
  options.start_worker = true;
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  auto info = vehicle.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  ASSERT_EQ(info->passages_applied(), static_cast<int64_t>(passages.size()));
  EXPECT_EQ(info->relinearizations_due(), 0);
  EXPECT_DOUBLE_EQ(info->relinearize_sigmas(), 0.5);
  int64_t last_applied_version = 0;
  for (const Passage& p : passages) {
    auto status = vehicle.GetPassage(p.vehicle_id, p.passage_id);
    ASSERT_TRUE(status.ok()) << status.status();
    last_applied_version = std::max(last_applied_version, status->result().map_version());
  }

  int relinearized = 0;
  const MapState expected = ApplyInOrder(passages, update, &relinearized, /*after_backlog=*/true);
  EXPECT_GE(relinearized, 1) << "the scenario must make passages stale";
  EXPECT_GT(info->map_version(), last_applied_version) << "re-linearisations after the last passage";
  ASSERT_TRUE(server->store()->ReadCommittedMap([&](const MapState& map) { ExpectSameMap(expected, map); }));
  server->Shutdown(std::chrono::milliseconds(0));
}

// mapd --read-window-hops: a read's covariances come from a window of that many links, whatever
// the updates use. A 300 m box of a city map of 24 short passages read with 1 link gives the 1-link
// window's joint covariance (the map's own, computed in process), wider than with 2 links.
TEST(ServiceReads, TheReadWindowSetsTheLinksOfARegionsCovariance) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.worker.update = CityUpdateOptions();
  options.read_window_hops = 1;
  std::unique_ptr<MapServer> server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle client(absl::StrCat("127.0.0.1:", server->port()));
  for (const Passage& p : CityPassages(24)) ASSERT_TRUE(client.Upload(p).ok());
  ASSERT_TRUE(client.WaitUntilIdle().ok());
  MapState map;
  ASSERT_TRUE(server->store()->ReadCommittedMap([&](const MapState& m) { map = m; }));
  // A box around the landmark nearest the middle of the mapped ones.
  Eigen::Vector2d sum = Eigen::Vector2d::Zero();
  std::vector<const Landmark*> all;
  map.ForEachLandmark([&](const Landmark& l) { all.push_back(&l); });
  for (const Landmark* l : all) sum += Eigen::Vector2d(l->position.lat_deg, l->position.lon_deg);
  const Eigen::Vector2d mean = sum / static_cast<double>(all.size());
  const Landmark* centre = *std::min_element(all.begin(), all.end(), [&](const Landmark* a, const Landmark* b) {
    return (Eigen::Vector2d(a->position.lat_deg, a->position.lon_deg) - mean).norm() <
           (Eigen::Vector2d(b->position.lat_deg, b->position.lon_deg) - mean).norm();
  });
  const double dlat = 150.0 / 111320.0;
  const double dlon = dlat / std::cos(centre->position.lat_deg * M_PI / 180.0);
  grpc::ClientContext ctx;
  pb::QueryRegionRequest request;
  request.mutable_box()->set_min_lat_deg(centre->position.lat_deg - dlat);
  request.mutable_box()->set_max_lat_deg(centre->position.lat_deg + dlat);
  request.mutable_box()->set_min_lon_deg(centre->position.lon_deg - dlon);
  request.mutable_box()->set_max_lon_deg(centre->position.lon_deg + dlon);
  request.set_page_size(2000);  // the most a page with covariances holds
  request.set_include_cross_covariance(true);
  pb::QueryRegionResponse response;
  ASSERT_TRUE(client.stub()->QueryRegion(&ctx, request, &response).ok());
  std::vector<LandmarkId> ids;
  for (const pb::Landmark& l : response.landmarks()) ids.push_back(l.id());
  ASSERT_GE(ids.size(), 10u);
  ASSERT_LT(ids.size(), all.size() / 2) << "the box must leave most of the map outside";
  absl::StatusOr<Eigen::MatrixXd> one_link = JointCovariance(map, ids, MapWindowOptions{1});
  absl::StatusOr<Eigen::MatrixXd> two_links = JointCovariance(map, ids, MapWindowOptions{2});
  ASSERT_TRUE(one_link.ok()) << one_link.status();
  ASSERT_TRUE(two_links.ok()) << two_links.status();
  double wider = 0.0;
  for (int k = 0; k < response.landmarks_size(); ++k) {
    const pb::Landmark& l = response.landmarks(k);
    EXPECT_NEAR(l.cov_en_m2().ee(), (*one_link)(2 * k, 2 * k), 1e-9);
    EXPECT_NEAR(l.cov_en_m2().nn(), (*one_link)(2 * k + 1, 2 * k + 1), 1e-9);
    for (int c = 0; c < 2; ++c) {
      wider = std::max(wider, (*one_link)(2 * k + c, 2 * k + c) / (*two_links)(2 * k + c, 2 * k + c));
    }
  }
  std::unordered_map<LandmarkId, int> at;
  for (size_t k = 0; k < ids.size(); ++k) at[ids[k]] = static_cast<int>(k);
  ASSERT_GT(response.cross_covariances_size(), 0);
  for (const pb::CrossCovariance& c : response.cross_covariances()) {
    EXPECT_NEAR(c.cov_m2().en(), (*one_link)(2 * at[c.first_id()], 2 * at[c.second_id()] + 1), 1e-9);
  }
  EXPECT_GT(wider, 1.001) << "1 link must read wider covariances than 2 on this map";
  // With 18 of the 24 passages folded into the base (retention 6), the base reaches outside the
  // 1-link window, which the response says.
  CovarianceBound bound = CovarianceBound::kExact;
  ASSERT_TRUE(JointCovariance(map, ids, MapWindowOptions{1}, &bound).ok());
  EXPECT_EQ(bound, CovarianceBound::kMayBeNarrower);
  EXPECT_EQ(response.covariance_bound(), pb::COVARIANCE_BOUND_MAY_BE_NARROWER);
  server->Shutdown(std::chrono::milliseconds(0));
}

// mapd with two workers killed (SIGKILL) while they apply, restarted on the same file, every
// passage sent again: each ends applied once, and the map is the one of the commit order.
TEST(ParallelWorkers, AKillWhileTwoWorkersApplyLosesNothingAndAppliesNothingTwice) {
  const std::vector<Passage> passages = CityPassages(20);
  // The flags of CityUpdateOptions.
  std::vector<std::string> flags = {"--workers", "2", "--window-hops", "2", "--warmup-passages", "0",
                                    "--relinearize-until-passages", "0", "--retain-passages", "6",
                                    "--vehicle-upload-rate", "0"};
  for (const std::string& f : ReplayableMapdFlags()) flags.push_back(f);
  TempDir dir;
  const std::string db = dir.File("map.db");
  int applied_before_kill = 0;
  {
    MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, flags);
    ASSERT_TRUE(mapd.WaitReady());
    MockVehicle client(mapd.address());
    for (const Passage& p : passages) ASSERT_TRUE(client.Upload(p).ok());
    for (int i = 0; i < 20000 && applied_before_kill < 4; ++i) {
      auto info = client.GetMapInfo();
      if (info.ok()) applied_before_kill = static_cast<int>(info->passages_applied());
    }
    const int status = mapd.Kill(SIGKILL);
    ASSERT_TRUE(WIFSIGNALED(status));
  }
  MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, flags);
  ASSERT_TRUE(mapd.WaitReady());
  MockVehicle client(mapd.address());
  for (const Passage& p : passages) ASSERT_TRUE(client.Upload(p).ok());  // acknowledgements lost
  auto info = client.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), static_cast<int64_t>(passages.size()));
  EXPECT_EQ(info->passages_failed() + info->passages_rejected() + info->passages_quarantined(), 0);
  // mapd's own defaults (e.g. the camera yaw estimated) with the flags above.
  const MapState expected =
      ApplyInOrder(InCommitOrder(&client, passages), CityUpdateOptions(ReplayableMapdUpdateOptions()));
  EXPECT_EQ(mapd.Kill(SIGTERM), 0);
  auto store = CreateSqliteMapStore(db);
  ASSERT_TRUE(store.ok()) << store.status();
  MapState stored;
  ASSERT_TRUE((*store)->LoadMap(&stored).ok());
  ExpectSameMap(expected, stored);
  std::printf("applied before the kill: %d of %zu\n", applied_before_kill, passages.size());
}

// Two workers claim passages ahead of their computations (to take one far from the other's): a stop
// puts those back on the queue, not started and not counted, instead of leaving them processing
// for the next start to count as interrupted. The passages are then all applied by the next start.
TEST(ParallelWorkers, AStopPutsThePassagesClaimedAheadBackUncounted) {
  const std::vector<Passage> passages = CityPassages(16);
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.worker.workers = 2;
  options.worker.update = CityUpdateOptions();
  options.limits.vehicle_uploads_per_s = 0;
  {
    auto server = StartTestServer(options);
    ASSERT_NE(server, nullptr);
    MockVehicle vehicle(server->address());
    for (const Passage& p : passages) ASSERT_TRUE(vehicle.Upload(p).ok());
    for (int i = 0; i < 20000; ++i) {
      auto info = vehicle.GetMapInfo();
      if (info.ok() && info->passages_applied() >= 2) break;
    }
    server->Shutdown(std::chrono::milliseconds(0));
  }
  {
    auto store = CreateSqliteMapStore(dir.File("map.db"));
    ASSERT_TRUE(store.ok()) << store.status();
    PassageQuery query;
    query.limit = 100;
    auto records = (*store)->ListPassages(query);
    ASSERT_TRUE(records.ok()) << records.status();
    ASSERT_EQ(records->size(), passages.size());
    int queued = 0;
    for (const StoredPassage& r : *records) {
      EXPECT_NE(r.state, PassageState::kProcessing) << r.passage_id;
      if (r.state != PassageState::kQueued) continue;
      ++queued;
      EXPECT_EQ(r.attempts, 0) << r.passage_id << ": a stop says nothing about the passage";
    }
    std::printf("queued after the stop: %d of %zu\n", queued, passages.size());
    EXPECT_GT(queued, 0) << "the stop came too late to test anything";
  }
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  auto info = vehicle.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), static_cast<int64_t>(passages.size()));
}

// The loop with the defaults: the young map's joint solves take all passages before them, so a
// worker's joint solve is computed again whenever the other committed first.
TEST(ParallelWorkers, JointSolvesOfTheYoungMapGiveTheMapOfTheirCommitOrder) {
  const Scenario scenario = ShortScenario(8, 60.0);
  std::vector<Passage> passages;
  for (int i = 0; i < 20; ++i) passages.push_back(scenario.MakePassage(i));
  RunWithWorkers(2, passages, MapUpdateOptions());
}

}  // namespace
}  // namespace crowdmap
