// Time to localise a 3-minute passage of the 4 km route against its 500-landmark map. Each
// repetition is one call, so the median row is the p50 over the calls:
//   build/core/passage_localizer_benchmark --benchmark_report_aggregates_only=true
#include <benchmark/benchmark.h>

#include "core/localization/passage_localizer.h"
#include "core/sim/scenario.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

constexpr double kPassageS = 180.0;

// The route's landmarks as a map: 0.5 m independent errors, plus (correlated) a 0.3 m offset they
// share, which makes the joint covariance of the landmarks a passage sees dense.
LocalizationMap RouteMap(const Scenario& scenario, bool correlated) {
  NoiseSource noise(7);
  const int n = static_cast<int>(scenario.landmarks().size());
  LocalizationMap map;
  map.cov_en_m2 = 0.25 * Eigen::MatrixXd::Identity(2 * n, 2 * n);
  for (int k = 0; k < n; ++k) {
    const TruthLandmark& lm = scenario.landmarks()[k];
    map.ids.push_back(lm.id);
    map.positions.push_back(scenario.frame().ToGeo(lm.position_m + 0.5 * Eigen::Vector2d(noise.Normal(), noise.Normal())));
    if (!correlated) continue;
    for (int l = 0; l < n; ++l) map.cov_en_m2.block<2, 2>(2 * k, 2 * l) += 0.09 * Eigen::Matrix2d::Identity();
  }
  return map;
}

// The route, both maps and four 3-minute passages, made once.
struct Setup {
  Setup() {
    const Scenario route = *Scenario::Create(LocalizationRouteOptions());
    maps = {RouteMap(route, false), RouteMap(route, true)};
    for (int i = 0; i < 4; ++i) passages.push_back(PassageBetween(route.MakePassage(i), 0.0, kPassageS));
  }

  std::vector<LocalizationMap> maps;
  std::vector<Passage> passages;
};

void BM_LocalizePassage(benchmark::State& state) {
  static const Setup* setup = new Setup();
  static size_t next = 0;
  const LocalizationMap& map = setup->maps[state.range(0)];
  int landmarks = 0;
  for (auto _ : state) {
    absl::StatusOr<PassageLocalization> result = LocalizePassage(setup->passages[next++ % setup->passages.size()], map);
    if (!result.ok()) {
      state.SkipWithError(result.status().ToString().c_str());
      break;
    }
    landmarks = static_cast<int>(result->landmarks_used.size());
    benchmark::DoNotOptimize(result);
  }
  state.counters["landmarks_used"] = landmarks;
  state.SetLabel(state.range(0) ? "correlated map" : "independent landmarks");
}

BENCHMARK(BM_LocalizePassage)
    ->ArgNames({"correlated"})
    ->Arg(0)
    ->Arg(1)
    ->Iterations(1)
    ->Repetitions(21)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

BENCHMARK_MAIN();
