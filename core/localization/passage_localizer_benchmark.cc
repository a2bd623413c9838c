// Time to localise a 3-minute passage of the 4 km route against its 500-landmark map.
//   build/core/passage_localizer_benchmark --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
#include <algorithm>

#include <benchmark/benchmark.h>

#include "core/localization/passage_localizer.h"
#include "core/sim/scenario.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

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

void BM_LocalizePassage(benchmark::State& state) {
  ScenarioOptions options;
  options.landmarks = 500;
  options.duration_s = 340.0;
  options.repeat_route = true;
  const Scenario route = *Scenario::Create(options);
  const LocalizationMap map = RouteMap(route, state.range(0) != 0);
  // The passages: the first 3 minutes of the route.
  constexpr double kPassageS = 180.0;
  std::vector<Passage> passages;
  for (int i = 0; i < 4; ++i) {
    Passage p = route.MakePassage(i);
    auto after = [](double t) { return t > kPassageS; };
    p.odometry.erase(std::remove_if(p.odometry.begin(), p.odometry.end(), [&](const auto& o) { return after(o.t_s); }),
                     p.odometry.end());
    p.gnss.erase(std::remove_if(p.gnss.begin(), p.gnss.end(), [&](const auto& g) { return after(g.t_s); }), p.gnss.end());
    p.detections.erase(
        std::remove_if(p.detections.begin(), p.detections.end(), [&](const auto& d) { return after(d.t_s); }),
        p.detections.end());
    passages.push_back(std::move(p));
  }
  size_t next = 0;
  int landmarks = 0;
  for (auto _ : state) {
    absl::StatusOr<PassageLocalization> result = LocalizePassage(passages[next++ % passages.size()], map);
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

BENCHMARK(BM_LocalizePassage)->ArgNames({"correlated"})->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

BENCHMARK_MAIN();
