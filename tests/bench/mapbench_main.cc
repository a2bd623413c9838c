// mapbench: measures the map service on loopback with an in-process server and a temporary
// database (see server/README.md).
//   mapbench upload [--clients 8] [--passages 2000] [--apply] [--no-worker-yield]
//       durable-acknowledgement upload throughput of thesis-sized passages (165 s, 25 Hz odometry)
//   mapbench query [--readers 16] [--seconds 10] [--cross] [--no-writes] [--apply-rate R] [--preload P]
//                  [--worker-nice N] [--no-worker-yield]
//       QueryRegion latency over a 1 km^2 box (about 100 landmarks) while passages are applied
//       back to back (--apply-rate R: about R per second; --no-writes: none, the readers alone).
//       The map first takes P passages (default: up to its last joint re-solve, 128), so that the
//       measured updates are the sequential ones of a mature map.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <google/protobuf/arena.h>
#include <spdlog/spdlog.h>

#include "core/estimation/map_updater.h"
#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

using Clock = std::chrono::steady_clock;

double Ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(p * (v.size() - 1) + 0.5))];
}

int IntFlag(int argc, char** argv, const char* name, int fallback) {
  for (int i = 2; i + 1 < argc; ++i) {
    if (std::strcmp(argv[i], name) == 0) return std::atoi(argv[i + 1]);
  }
  return fallback;
}

bool BoolFlag(int argc, char** argv, const char* name) {
  for (int i = 2; i < argc; ++i) {
    if (std::strcmp(argv[i], name) == 0) return true;
  }
  return false;
}

int Upload(int argc, char** argv) {
  const int clients = IntFlag(argc, argv, "--clients", 8);
  const int total = IntFlag(argc, argv, "--passages", 2000);
  const bool apply = BoolFlag(argc, argv, "--apply");
  ScenarioOptions options;  // thesis scenario: 165 s, 25 landmarks
  auto scenario = Scenario::Create(options);
  if (!scenario.ok()) return 1;
  constexpr int kDistinct = 50;
  std::vector<pb::Passage> templates(kDistinct);
  for (int i = 0; i < kDistinct; ++i) PassageToProto(scenario->MakePassage(i), &templates[i]);

  TempDir dir;
  MapServerOptions server_options = TestServerOptions(dir.File("map.db"), apply);
  if (BoolFlag(argc, argv, "--no-worker-yield")) server_options.worker.yield = false;
  server_options.max_queue = 0;
  // 50 vehicles send 2000 passages as fast as they can: the per-vehicle quota would refuse most.
  server_options.limits.vehicle_uploads_per_s = 0;
  auto server = MapServer::Start(server_options);
  if (!server.ok()) return 1;
  std::atomic<int> next{0}, failures{0};
  std::vector<std::vector<double>> latencies(clients);
  const auto start = Clock::now();
  std::vector<std::thread> threads;
  for (int c = 0; c < clients; ++c) {
    threads.emplace_back([&, c] {
      MockVehicle vehicle((*server)->address());
      for (int i = next++; i < total; i = next++) {
        pb::Passage wire = templates[i % kDistinct];
        wire.set_passage_id("bench-" + std::to_string(i));
        wire.set_start_time_unix_ms(wire.start_time_unix_ms() + i);  // each its own drive, taken once
        const auto t0 = Clock::now();
        auto r = vehicle.UploadOnce(wire);
        latencies[c].push_back(Ms(Clock::now() - t0));
        if (!r.ok() || r->duplicate()) ++failures;
      }
    });
  }
  for (auto& t : threads) t.join();
  const double seconds = Ms(Clock::now() - start) / 1000.0;
  std::vector<double> all;
  for (const auto& l : latencies) all.insert(all.end(), l.begin(), l.end());
  std::printf("upload clients=%d passages=%d bytes_per_passage=%zu apply=%s failures=%d seconds=%.2f "
              "uploads_per_s=%.1f ack_p50_ms=%.2f ack_p99_ms=%.2f\n",
              clients, total, templates[0].ByteSizeLong(), apply ? "true" : "false", failures.load(), seconds,
              total / seconds, Percentile(all, 0.5), Percentile(all, 0.99));
  (*server)->Shutdown();
  return failures.load() == 0 ? 0 : 1;
}

int Query(int argc, char** argv) {
  const int readers = IntFlag(argc, argv, "--readers", 16);
  const int seconds = IntFlag(argc, argv, "--seconds", 10);
  ScenarioOptions options;
  options.landmarks = 100;
  auto scenario = Scenario::Create(options);
  if (!scenario.ok()) return 1;
  TempDir dir;
  MapServerOptions server_options = TestServerOptions(dir.File("map.db"), true);
  server_options.worker.nice = IntFlag(argc, argv, "--worker-nice", server_options.worker.nice);
  // --no-worker-yield: the worker computes and commits without yielding the CPU (the ablation of
  // MapWorkerOptions::yield).
  if (BoolFlag(argc, argv, "--no-worker-yield")) server_options.worker.yield = false;
  auto server = MapServer::Start(server_options);
  if (!server.ok()) return 1;
  MockVehicle writer((*server)->address());
  // By default the measured updates are the sequential ones of a map past its joint solves (the
  // warm-up and the re-solves at each doubling of its passage count), which take seconds each
  // and happen once in a map's life.
  const int preload =
      IntFlag(argc, argv, "--preload", std::max(5, JointSolvePassages(server_options.worker.update) + 1));
  std::fprintf(stderr, "preloading %d passages...\n", preload);
  for (int i = 0; i < preload; ++i) {
    if (!writer.Upload(scenario->MakePassage(i)).ok()) return 1;
  }
  if (!writer.WaitUntilIdle().ok()) return 1;

  // 1 km x 1 km around the landmarks' centroid.
  Eigen::Vector2d centroid = Eigen::Vector2d::Zero();
  for (const TruthLandmark& l : scenario->landmarks()) centroid += l.position_m;
  centroid /= scenario->landmarks().size();
  const LatLon sw = scenario->frame().ToGeo(centroid - Eigen::Vector2d(500, 500));
  const LatLon ne = scenario->frame().ToGeo(centroid + Eigen::Vector2d(500, 500));
  pb::QueryRegionRequest request;
  request.mutable_box()->set_min_lat_deg(sw.lat_deg);
  request.mutable_box()->set_min_lon_deg(sw.lon_deg);
  request.mutable_box()->set_max_lat_deg(ne.lat_deg);
  request.mutable_box()->set_max_lon_deg(ne.lon_deg);
  request.set_include_cross_covariance(BoolFlag(argc, argv, "--cross"));

  std::atomic<bool> stop{false};
  std::atomic<int> applied_during{0};
  // --no-writes: readers only, the baseline that shows what the concurrent map updates cost.
  // --apply-rate R: about R passages per second instead of as many as the worker can apply.
  const bool writes = !BoolFlag(argc, argv, "--no-writes");
  const int apply_rate = IntFlag(argc, argv, "--apply-rate", 0);
  std::thread uploader([&] {
    auto next = Clock::now();
    for (int i = preload; writes && !stop; ++i) {
      if (apply_rate > 0) {
        next += std::chrono::microseconds(1000000 / apply_rate);
        std::this_thread::sleep_until(next);
      }
      if (writer.Upload(scenario->MakePassage(i)).ok()) ++applied_during;
      // Three queued passages keep the worker busy for over 100 ms: polling every 20 ms keeps the
      // queue from running dry without adding a stream of calls of its own to the measured load.
      while (!stop && writer.GetMapInfo()->queue_depth() > 2) std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  });
  std::vector<std::vector<double>> latencies(readers);
  std::atomic<int64_t> landmarks_seen{0};
  std::vector<std::thread> threads;
  const auto end = Clock::now() + std::chrono::seconds(seconds);
  for (int r = 0; r < readers; ++r) {
    threads.emplace_back([&, r] {
      MockVehicle reader((*server)->address());
      // The response's landmark messages go on a per-call arena whose first block is reused.
      std::vector<char> block(64 << 10);
      google::protobuf::ArenaOptions arena_options;
      arena_options.initial_block = block.data();
      arena_options.initial_block_size = block.size();
      while (Clock::now() < end) {
        google::protobuf::Arena arena(arena_options);
        auto* response = google::protobuf::Arena::CreateMessage<pb::QueryRegionResponse>(&arena);
        grpc::ClientContext ctx;
        ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
        const auto t0 = Clock::now();
        grpc::Status s = reader.stub()->QueryRegion(&ctx, request, response);
        latencies[r].push_back(Ms(Clock::now() - t0));
        if (s.ok()) landmarks_seen += response->landmarks_size();
      }
    });
  }
  for (auto& t : threads) t.join();
  stop = true;
  uploader.join();
  auto info = writer.GetMapInfo();
  std::vector<double> all;
  for (const auto& l : latencies) all.insert(all.end(), l.begin(), l.end());
  std::printf("query readers=%d seconds=%d queries=%zu queries_per_s=%.0f landmarks_per_query=%.1f "
              "passages_uploaded_during=%d map_version=%lld p50_ms=%.3f p99_ms=%.3f\n",
              readers, seconds, all.size(), all.size() / static_cast<double>(seconds),
              all.empty() ? 0.0 : landmarks_seen.load() / static_cast<double>(all.size()), applied_during.load(),
              static_cast<long long>(info.ok() ? info->map_version() : -1), Percentile(all, 0.5),
              Percentile(all, 0.99));
  (*server)->Shutdown();
  return 0;
}

}  // namespace
}  // namespace crowdmap

int main(int argc, char** argv) {
  spdlog::set_level(spdlog::level::warn);
  crowdmap::TuneProcessForServing();  // as mapd does
  if (argc >= 2 && std::strcmp(argv[1], "upload") == 0) return crowdmap::Upload(argc, argv);
  if (argc >= 2 && std::strcmp(argv[1], "query") == 0) return crowdmap::Query(argc, argv);
  std::fprintf(stderr, "usage: mapbench upload [--clients 8] [--passages 2000] [--apply] [--no-worker-yield]\n"
                       "       mapbench query [--readers 16] [--seconds 10] [--cross] [--no-writes] [--apply-rate R]"
                       " [--preload P]\n"
                       "                      [--worker-nice N] [--no-worker-yield]\n");
  return 2;
}
