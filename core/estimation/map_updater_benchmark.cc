// Time to apply one passage to a map that already holds its landmarks: a thesis-sized loop
// passage, and a ~2 km route through the default city (6 x 6 blocks, 1009 landmarks).
//   build/core/map_updater_benchmark --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
#include <benchmark/benchmark.h>

#include <functional>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/estimation/map_updater.h"
#include "core/sim/city_scenario.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

constexpr int kTimedPassages = 20;

// Applies passages 0..mature-1 of `make` to an empty map, then times applying each of the next
// kTimedPassages in turn to that same map (it is never changed), with where the time goes per
// passage: the solve, the covariance recovery and the bias correction; and the solver's iterations.
void TimeApplyingPassages(const std::function<Passage(int)>& make, int mature, const MapUpdateOptions& options,
                          benchmark::State& state) {
  MapState map;
  MapUpdater updater(options);
  for (int i = 0; i < mature; ++i) {
    const Passage passage = make(i);
    absl::StatusOr<PassageUpdate> u = updater.Compute(passage, map);
    if (!u.ok()) continue;
    map.Apply(u->delta);
    updater.Applied(passage, u->delta);
  }
  std::vector<Passage> passages;
  for (int i = 0; i < kTimedPassages; ++i) passages.push_back(make(mature + i));
  size_t next = 0;
  double solve_ms = 0.0, covariance_ms = 0.0, bias_ms = 0.0, subgraphs = 0.0, iterations = 0.0;
  for (auto _ : state) {
    absl::StatusOr<PassageUpdate> u = updater.Compute(passages[next++ % passages.size()], map);
    if (!u.ok()) {
      state.SkipWithError(u.status().ToString().c_str());
      break;
    }
    solve_ms += u->summary.solve_ms;
    covariance_ms += u->summary.covariance_ms;
    bias_ms += u->summary.bias_correction_ms;
    subgraphs += u->summary.subgraphs;
    iterations += u->summary.solver_iterations;
    benchmark::DoNotOptimize(u);
  }
  state.counters["solve_ms"] = benchmark::Counter(solve_ms, benchmark::Counter::kAvgIterations);
  state.counters["covariance_ms"] = benchmark::Counter(covariance_ms, benchmark::Counter::kAvgIterations);
  state.counters["bias_correction_ms"] = benchmark::Counter(bias_ms, benchmark::Counter::kAvgIterations);
  state.counters["subgraphs"] = benchmark::Counter(subgraphs, benchmark::Counter::kAvgIterations);
  state.counters["solver_iterations"] = benchmark::Counter(iterations, benchmark::Counter::kAvgIterations);
  state.counters["landmarks"] = static_cast<double>(map.landmark_count());
}

// A loop passage on a map of 50 passages (the map prior is then dense and tight, as in a mature
// map), the service's defaults but the strategy and the camera yaw.
void BM_ApplyPassage(benchmark::State& state) {
  ScenarioOptions scenario_options;
  scenario_options.landmarks = static_cast<int>(state.range(0));
  const Scenario scenario = *Scenario::Create(scenario_options);
  MapUpdateOptions options;
  options.strategy = static_cast<UpdateStrategy>(state.range(1));
  options.estimate_camera_yaw = state.range(2) != 0;
  TimeApplyingPassages([&](int i) { return scenario.MakePassage(i); }, 50, options, state);
  state.SetLabel(absl::StrCat(UpdateStrategyName(options.strategy), options.estimate_camera_yaw ? " +yaw" : ""));
}

BENCHMARK(BM_ApplyPassage)
    ->ArgNames({"landmarks", "strategy", "yaw"})
    ->Args({100, static_cast<int>(UpdateStrategy::kCorrelatedSubdivided), 0})
    ->Args({100, static_cast<int>(UpdateStrategy::kCorrelatedSubdivided), 1})  // camera yaw estimated
    ->Args({100, static_cast<int>(UpdateStrategy::kCorrelated), 0})
    ->Args({100, static_cast<int>(UpdateStrategy::kDecorrelated), 0})
    ->Args({25, static_cast<int>(UpdateStrategy::kCorrelatedSubdivided), 0})
    ->Unit(benchmark::kMillisecond);

// A city passage (~2 km), on a map built from the first `mature_passages` routes with
// sequential updates only (no joint solves), the service's other defaults but the window
// (`window_hops`, 0 = the whole connected map).
void BM_ApplyCityPassage(benchmark::State& state) {
  const CityScenario city = *CityScenario::Create(CityScenarioOptions{});
  MapUpdateOptions options;
  options.warmup_passages = 0;
  options.relinearize_until_passages = 0;
  options.window_hops = static_cast<int>(state.range(1));
  TimeApplyingPassages([&](int i) { return city.MakePassage(i); }, static_cast<int>(state.range(0)), options, state);
}

BENCHMARK(BM_ApplyCityPassage)
    ->ArgNames({"mature_passages", "window_hops"})
    ->Args({60, 0})
    ->Args({60, 2})
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

BENCHMARK_MAIN();
