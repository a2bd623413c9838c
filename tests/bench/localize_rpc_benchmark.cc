// LocalizePassage through gRPC against an in-process server (SQLite file in a temporary
// directory) whose map the service built from passages of the 4 km, 500-landmark route: the
// response time of a 3-minute passage (region read with cross-covariances, the localisation, the
// wire), and the same passage localised in-process against that map read back (the core figure).
// Each repetition is one call, so the median row is the p50 over the calls:
//   build/tests/localize_rpc_benchmark --benchmark_report_aggregates_only=true
#include <cstdio>
#include <cstdlib>

#include <benchmark/benchmark.h>

#include "core/estimation/map_update_options.h"
#include "core/estimation/vehicle_calibration.h"
#include "core/localization/passage_localizer.h"
#include "core/sim/scenario.h"
#include "server/map_server.h"
#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/mock_vehicle.h"

namespace crowdmap {
namespace {

constexpr int kMapPassages = 3;
constexpr double kPassageS = 180.0;
constexpr int kPassages = 4;

void Die(const std::string& what, const absl::Status& status) {
  std::fprintf(stderr, "%s: %s\n", what.c_str(), status.ToString().c_str());
  std::exit(1);
}

// The server with its map, the passages to localise, and the map read back, made once.
struct Setup {
  Setup() {
    const Scenario route = *Scenario::Create(LocalizationRouteOptions());
    MapServerOptions server_options;
    server_options.listen = "127.0.0.1:0";
    server_options.db_path = dir.File("map.db");
    server_options.worker.idle_poll = std::chrono::milliseconds(20);
    absl::StatusOr<std::unique_ptr<MapServer>> started = MapServer::Start(server_options);
    if (!started.ok()) Die("server", started.status());
    server = *std::move(started);
    client = std::make_unique<MockVehicle>(server->address());
    for (int i = 0; i < kMapPassages; ++i) {
      if (auto uploaded = client->Upload(route.MakePassage(i)); !uploaded.ok()) Die("upload", uploaded.status());
    }
    absl::StatusOr<pb::MapInfo> info = client->WaitUntilIdle(std::chrono::minutes(30));
    if (!info.ok()) Die("map", info.status());
    absl::StatusOr<MapState> map = client->DownloadMap(MockVehicle::World());
    if (!map.ok()) Die("download", map.status());
    for (int i = 0; i < kPassages; ++i) {
      passages.push_back(PassageBetween(route.MakePassage(100 + i), 0.0, kPassageS));
      PassageToProto(passages.back(), &wire.emplace_back());
      absl::StatusOr<LocalizationMap> local = ReadLocalizationMap(*map, passages.back());
      if (!local.ok()) Die("map read", local.status());
      maps.push_back(*std::move(local));
    }
  }

  TempDir dir;
  std::unique_ptr<MapServer> server;
  std::unique_ptr<MockVehicle> client;
  std::vector<Passage> passages;
  std::vector<pb::Passage> wire;
  std::vector<LocalizationMap> maps;  // per passage, read in-process from the downloaded map
};

const Setup& TheSetup() {
  static const Setup* setup = new Setup();
  return *setup;
}

void BM_LocalizePassageRpc(benchmark::State& state) {
  const Setup& setup = TheSetup();
  static size_t next = 0;
  int landmarks = 0;
  for (auto _ : state) {
    absl::StatusOr<pb::LocalizePassageResponse> response =
        setup.client->client()->LocalizePassage(setup.wire[next++ % setup.wire.size()]);
    if (!response.ok()) {
      state.SkipWithError(response.status().ToString().c_str());
      break;
    }
    landmarks = response->landmarks_used_size();
  }
  state.counters["landmarks_used"] = landmarks;
}

// Argument 1: the camera's yaw offset estimated, as the RPC does for these vehicles (no record:
// the map update's prior); 0: the calibration taken as exact.
void BM_LocalizePassageInProcess(benchmark::State& state) {
  const Setup& setup = TheSetup();
  static size_t next = 0;
  int landmarks = 0;
  PassageLocalizerOptions options;
  if (state.range(0) == 1) {
    options.camera_yaw_sigma_rad = MapUpdateOptions().camera_yaw_prior_sigma_rad;
  }
  for (auto _ : state) {
    const size_t k = next++ % setup.passages.size();
    absl::StatusOr<PassageLocalization> result = LocalizePassage(setup.passages[k], setup.maps[k], options);
    if (!result.ok()) {
      state.SkipWithError(result.status().ToString().c_str());
      break;
    }
    landmarks = static_cast<int>(result->landmarks_used.size());
    benchmark::DoNotOptimize(result);
  }
  state.counters["landmarks_used"] = landmarks;
}

BENCHMARK(BM_LocalizePassageRpc)->Iterations(1)->Repetitions(21)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_LocalizePassageInProcess)->Arg(1)->Arg(0)->Iterations(1)->Repetitions(21)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

BENCHMARK_MAIN();
