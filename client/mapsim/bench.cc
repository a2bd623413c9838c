#include "client/mapsim/bench.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <limits>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/time/clock.h"
#include "client/api/map_client.h"
#include "client/mapsim/simulated_passages.h"
#include "core/geo/tiles.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

using Clock = std::chrono::steady_clock;

double Ms(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double, std::milli>(b - a).count(); }

LatencyStats Stats(std::vector<double> ms) {
  LatencyStats s;
  s.calls = static_cast<int64_t>(ms.size());
  if (ms.empty()) return s;
  std::sort(ms.begin(), ms.end());
  auto at = [&](double q) { return ms[std::min(ms.size() - 1, static_cast<size_t>(q * (ms.size() - 1) + 0.5))]; };
  s.p50_ms = at(0.50);
  s.p99_ms = at(0.99);
  s.max_ms = ms.back();
  return s;
}

pb::BoundingBox RouteBox(const std::vector<TruthLandmark>& landmarks) {
  double min_lat = std::numeric_limits<double>::infinity(), min_lon = min_lat, max_lat = -min_lat, max_lon = -min_lat;
  for (const TruthLandmark& l : landmarks) {
    min_lat = std::min(min_lat, l.position.lat_deg);
    max_lat = std::max(max_lat, l.position.lat_deg);
    min_lon = std::min(min_lon, l.position.lon_deg);
    max_lon = std::max(max_lon, l.position.lon_deg);
  }
  constexpr double kMarginDeg = 0.001;  // about 100 m
  pb::BoundingBox box;
  box.set_min_lat_deg(min_lat - kMarginDeg);
  box.set_max_lat_deg(max_lat + kMarginDeg);
  box.set_min_lon_deg(min_lon - kMarginDeg);
  box.set_max_lon_deg(max_lon + kMarginDeg);
  return box;
}

absl::StatusOr<std::unique_ptr<MapClient>> Connect(const std::string& server, const ClientSecurityOptions& security) {
  MapClientOptions options;
  options.server = server;
  options.security = security;
  options.max_attempts = 5;
  return MapClient::Create(options);
}

}  // namespace

absl::Status BenchOptions::Validate() const {
  if (absl::Status s = scenario.Validate(); !s.ok()) return s;
  if (clients < 1 || readers < 0 || passages < 1) {
    return absl::InvalidArgumentError("need clients >= 1, readers >= 0, passages >= 1");
  }
  if (!(read_seconds > 0)) return absl::InvalidArgumentError("read_seconds: must be > 0");
  if (!(upload_rate_per_s >= 0)) return absl::InvalidArgumentError("upload_rate_per_s: must be >= 0 (0 = unpaced)");
  if (city) {
    if (absl::Status s = city_scenario.Validate(); !s.ok()) return s;
  }
  return absl::OkStatus();
}

std::string BenchResult::Brief() const {
  return absl::StrFormat(
      "passages=%d uploads_per_s=%.1f ack_p50_ms=%.2f ack_p99_ms=%.2f ack_max_ms=%.2f applied_per_s=%.1f read_s=%.2f query_region_p50_ms=%.2f query_region_p99_ms=%.2f "
      "query_region_calls=%d get_tile_p50_ms=%.2f get_tile_p99_ms=%.2f get_tile_calls=%d landmarks_in_box=%d",
      passages, uploads_per_s, ack.p50_ms, ack.p99_ms, ack.max_ms, applied_per_s, read_s, query_region.p50_ms, query_region.p99_ms, query_region.calls,
      get_tile.p50_ms, get_tile.p99_ms, get_tile.calls, landmarks_in_box);
}

absl::StatusOr<BenchResult> RunBench(const BenchOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<SimulatedPassages> scenario =
      MakeSimulatedPassages(options.scenario, options.city ? &options.city_scenario : nullptr, options.passages);
  if (!scenario.ok()) return scenario.status();
  absl::StatusOr<std::unique_ptr<MapClient>> control = Connect(options.server, options.security);
  if (!control.ok()) return control.status();
  absl::StatusOr<pb::MapInfo> start = (*control)->GetMapInfo();
  if (!start.ok()) return start.status();
  const int64_t finished_at_start = start->passages_applied() + start->passages_rejected() + start->passages_failed();

  // Passages are generated before timing. On a reused database the run's time keeps them new:
  // in their ids, and in their start times (the server takes one drive once, whatever its ids).
  const int64_t run_ms = absl::ToUnixMillis(absl::Now());
  const std::string tag = absl::StrCat("bench-", run_ms);
  std::vector<pb::Passage> wire(options.passages);
  for (int i = 0; i < options.passages; ++i) {
    PassageToProto(scenario->passages[i], &wire[i]);
    wire[i].set_passage_id(absl::StrCat(tag, "-", i));
    wire[i].set_start_time_unix_ms(run_ms + i);
  }
  scenario->passages.clear();

  BenchResult result;
  result.passages = options.passages;
  std::atomic<int> next{0};
  std::mutex mu;
  absl::Status error;
  std::vector<double> ack_ms;
  const Clock::time_point t0 = Clock::now();
  std::vector<std::thread> uploaders;
  for (int k = 0; k < options.clients; ++k) {
    uploaders.emplace_back([&] {
      absl::StatusOr<std::unique_ptr<MapClient>> client = Connect(options.server, options.security);
      std::vector<double> mine;
      for (int i = next++; client.ok() && i < options.passages; i = next++) {
        if (options.upload_rate_per_s > 0.0) {
          std::this_thread::sleep_until(t0 + std::chrono::microseconds(
                                                 static_cast<int64_t>(1e6 * i / options.upload_rate_per_s)));
        }
        const Clock::time_point sent = Clock::now();
        absl::StatusOr<pb::UploadPassageResponse> r = (*client)->Upload(wire[i]);
        if (!r.ok()) {
          std::lock_guard<std::mutex> lock(mu);
          if (error.ok()) error = r.status();
          return;
        }
        mine.push_back(Ms(sent, Clock::now()));
      }
      {
        std::lock_guard<std::mutex> lock(mu);
        ack_ms.insert(ack_ms.end(), mine.begin(), mine.end());
      }
      if (!client.ok()) {
        std::lock_guard<std::mutex> lock(mu);
        error = client.status();
      }
    });
  }
  for (std::thread& t : uploaders) t.join();
  const Clock::time_point t_uploaded = Clock::now();
  if (!error.ok()) return error;
  result.upload_s = Ms(t0, t_uploaded) / 1000.0;
  result.uploads_per_s = options.passages / result.upload_s;
  result.ack = Stats(ack_ms);

  const pb::BoundingBox box = RouteBox(scenario->landmarks);
  std::vector<TileId> tiles;
  for (const TruthLandmark& l : scenario->landmarks) tiles.push_back(TileContaining(l.position));
  std::vector<double> region_ms, tile_ms;
  std::atomic<bool> stop{false};
  std::vector<std::thread> readers;
  for (int r = 0; r < options.readers; ++r) {
    readers.emplace_back([&, r] {
      absl::StatusOr<std::unique_ptr<MapClient>> client = Connect(options.server, options.security);
      std::vector<double> my_region, my_tile;
      for (size_t n = r; client.ok() && !stop.load(); ++n) {
        const Clock::time_point a = Clock::now();
        if (n % 2 == 0) {
          absl::StatusOr<RegionMap> region = (*client)->QueryRegion(box);
          if (region.ok()) my_region.push_back(Ms(a, Clock::now()));
        } else {
          const TileId& t = tiles[(n / 2) % tiles.size()];
          if ((*client)->GetTile(t.z, t.x, t.y).ok()) my_tile.push_back(Ms(a, Clock::now()));
        }
      }
      std::lock_guard<std::mutex> lock(mu);
      region_ms.insert(region_ms.end(), my_region.begin(), my_region.end());
      tile_ms.insert(tile_ms.end(), my_tile.begin(), my_tile.end());
    });
  }
  const Clock::time_point read_end = t_uploaded + std::chrono::milliseconds(static_cast<int64_t>(options.read_seconds * 1000));
  Clock::time_point drained{};
  while (true) {
    absl::StatusOr<pb::MapInfo> info = (*control)->GetMapInfo();
    if (!info.ok()) {
      error = info.status();
      break;
    }
    const int64_t finished = info->passages_applied() + info->passages_rejected() + info->passages_failed();
    if (drained == Clock::time_point{} && info->queue_depth() == 0 && finished - finished_at_start >= options.passages) {
      drained = Clock::now();
    }
    if (!stop && (Clock::now() >= read_end || drained != Clock::time_point{})) {
      stop = true;
      result.read_s = Ms(t_uploaded, Clock::now()) / 1000.0;
    }
    if (stop && drained != Clock::time_point{}) break;
    if (Clock::now() > read_end + std::chrono::minutes(30)) {
      error = absl::DeadlineExceededError("the queue did not drain within 30 minutes");
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  stop = true;
  for (std::thread& t : readers) t.join();
  if (!error.ok()) return error;
  result.apply_s = Ms(t0, drained) / 1000.0;
  result.applied_per_s = options.passages / result.apply_s;
  result.query_region = Stats(region_ms);
  result.get_tile = Stats(tile_ms);
  absl::StatusOr<RegionMap> region = (*control)->QueryRegion(box);
  if (region.ok()) result.landmarks_in_box = static_cast<int64_t>(region->landmarks.size());
  return result;
}

}  // namespace crowdmap
