// Time per update of the on-vehicle localizer on a 340 s passage of the 4 km route with 500
// landmarks (one every 8 m): holding the landmarks of the 3 x 3 tiles around the vehicle (as
// OnboardLocalizer does; tile changes included in the times), or all 500 (the worst case).
// Each iteration replays the whole passage and times every input (tile changes included); the
// counters are percentiles of those times over all iterations: wall clock (p50_ms, p99_ms, max_ms)
// and this thread's CPU time (cpu_p50_ms, cpu_p99_ms).
//   build/core/streaming_localizer_benchmark --benchmark_repetitions=3
#include <algorithm>
#include <chrono>
#include <ctime>

#include <benchmark/benchmark.h>

#include "core/localization/localization_testing.h"
#include "core/localization/streaming_localizer.h"
#include "core/localization/tile_window.h"

namespace crowdmap {
namespace {

using testing_localization::Feed;
using testing_localization::MakeMap;
using testing_localization::PassageInput;
using testing_localization::PassageInputs;

// The map's landmarks in `tile`, with their joint covariance.
LocalizationMap TileOf(const LocalizationMap& map, const TileId& tile) {
  LocalizationMap out;
  std::vector<int> rows;
  for (size_t k = 0; k < map.ids.size(); ++k) {
    if (!(TileContaining(map.positions[k]) == tile)) continue;
    out.ids.push_back(map.ids[k]);
    out.positions.push_back(map.positions[k]);
    rows.push_back(static_cast<int>(2 * k));
    rows.push_back(static_cast<int>(2 * k + 1));
  }
  out.cov_en_m2 = map.cov_en_m2(rows, rows);
  return out;
}

// Keeps the landmarks of the tiles around `position` in the localizer.
void HoldTilesAround(const LatLon& position, const LocalizationMap& map, TileWindow* window,
                     StreamingLocalizer* localizer) {
  const TileWindow::Change change = window->MoveTo(position);
  for (const TileId& t : change.leave) localizer->RemoveMapLandmarks(TileOf(map, t).ids);
  for (const TileId& t : change.enter) (void)localizer->AddMapLandmarks(TileOf(map, t));
}

// CPU time of this thread (ms): the update's own cost, without the time other processes of a
// shared machine take the core.
double ThreadCpuMs() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e3 * static_cast<double>(ts.tv_sec) + 1e-6 * static_cast<double>(ts.tv_nsec);
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size())));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// range(2): 1 = hold the 3 x 3 tiles around the vehicle, 0 = every landmark.
// range(0): the map correlated (a shared 0.3 m offset: dense joint covariance) or independent.
// range(1): which inputs are timed: 0 = GNSS and camera frames (measurement updates), 1 = all
// (odometry predictions included).
void BM_StreamingLocalizerUpdate(benchmark::State& state) {
  const Scenario route = *Scenario::Create(LocalizationRouteOptions());
  const bool correlated = state.range(0) != 0;
  const LocalizationMap map = MakeMap(route, correlated ? 0.3 : 0.0, 0.5, 7, /*exact=*/false);
  const bool all_inputs = state.range(1) != 0;
  std::vector<Passage> passages;
  for (int i = 0; i < 3; ++i) passages.push_back(route.MakePassage(i));
  std::vector<double> update_ms, update_cpu_ms;
  size_t next = 0;
  int held = 0;
  for (auto _ : state) {
    state.PauseTiming();
    const Passage& passage = passages[next++ % passages.size()];
    const std::vector<PassageInput> inputs = PassageInputs(passage);
    std::unique_ptr<StreamingLocalizer> localizer = *StreamingLocalizer::Create(passage.calibration, passage.noise);
    const bool tiled = state.range(2) != 0;
    TileWindow window(1);
    if (tiled) {
      HoldTilesAround({passage.gnss.front().lat_deg, passage.gnss.front().lon_deg}, map, &window, localizer.get());
    } else if (!localizer->AddMapLandmarks(map).ok()) {
      state.SkipWithError("map");
      break;
    }
    state.ResumeTiming();
    for (const PassageInput& input : inputs) {
      const auto start = std::chrono::steady_clock::now();
      const double cpu_start = ThreadCpuMs();
      absl::StatusOr<StreamingUpdate> update = Feed(passage, input, localizer.get());
      if (tiled && update.ok() && update->tracking) HoldTilesAround(update->pose.position, map, &window, localizer.get());
      const double cpu_ms = ThreadCpuMs() - cpu_start;
      const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
      if (!update.ok()) {
        state.SkipWithError(update.status().ToString().c_str());
        break;
      }
      if (update->tracking && (all_inputs || input.kind != PassageInput::Kind::kOdometry)) {
        update_ms.push_back(ms);
        update_cpu_ms.push_back(cpu_ms);
      }
      benchmark::DoNotOptimize(update);
    }
    held = std::max(held, localizer->landmarks_held());
  }
  state.counters["updates"] = static_cast<double>(update_ms.size());
  state.counters["p50_ms"] = Percentile(update_ms, 0.50);
  state.counters["p99_ms"] = Percentile(update_ms, 0.99);
  state.counters["max_ms"] = Percentile(update_ms, 1.0);
  state.counters["cpu_p50_ms"] = Percentile(update_cpu_ms, 0.50);
  state.counters["cpu_p99_ms"] = Percentile(update_cpu_ms, 0.99);
  state.counters["max_landmarks_held"] = held;
  state.SetLabel(std::string(state.range(2) ? "3x3 tiles, " : "all landmarks, ") +
                 (correlated ? "correlated map" : "independent landmarks") +
                 (all_inputs ? ", every input" : ", GNSS and camera updates"));
}

BENCHMARK(BM_StreamingLocalizerUpdate)
    ->ArgNames({"correlated", "all_inputs", "tiles"})
    ->Args({0, 0, 1})
    ->Args({1, 0, 1})
    ->Args({1, 1, 1})
    ->Args({1, 0, 0})
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

BENCHMARK_MAIN();
