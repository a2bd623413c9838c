// Covariance reads of a city map: the joint covariance (cross-covariances included) of the
// landmarks in a 500 m box, as QueryRegion serves it, from the whole map's factorisation.
//   build/core/map_covariance_benchmark [--blocks N] [--passages P] [--retain-passages R]
//                                       [benchmark flags]
// builds an N x N block city map (mapsim city's layout, default 10 x 10, about 2,500 landmarks)
// from P passages (default 100) in process first (printing its size), the factors of all but the
// last R passages folded into the map's base (default 256, as mapd), then times:
//   BM_Factorise              the whole map's factorisation (once per map version)
//   BM_BoxCovariance/forward  the box's block of the inverse by forward solves from the box
//                             (MapWindow::Covariance)
//   BM_BoxCovariance/columns  the same block from full columns of the inverse (both triangular
//                             solves over the whole map), for comparison
//   BM_BoxCovarianceBounded/H a bounded window (H links) around the box: conservative, not exact
//                             (mapd --window-hops H; build_ms: the window's factorisation,
//                             inverse_ms: the box's block of its inverse; sigma_vs_exact, _min
//                             and _max: its marginal sigmas over the exact ones; may_be_narrower:
//                             the share of the boxes whose window says so, and
//                             sigma_vs_exact_min_others the smallest ratio over the other boxes,
//                             at least 1 when the windows are right about it)
#include <benchmark/benchmark.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "core/estimation/map_updater.h"
#include "core/map/map_window.h"
#include "core/sim/city_scenario.h"

namespace crowdmap {
namespace {

int g_blocks = 10;
int g_passages = 100;
int g_retain_passages = MapUpdateOptions().retain_passages;
constexpr double kBoxHalfWidthM = 250.0;
constexpr int kBoxes = 40;

struct CityMap {
  MapState map;
  std::vector<std::vector<LandmarkId>> boxes;  // the mapped landmarks of kBoxes 500 m boxes
};

const CityMap& TheMap() {
  static const CityMap* city_map = [] {
    auto* out = new CityMap;
    CityScenarioOptions options;
    options.blocks_x = options.blocks_y = g_blocks;
    const CityScenario city = *CityScenario::Create(options);
    MapUpdateOptions update;
    update.warmup_passages = 0;
    update.relinearize_until_passages = 0;
    update.window_hops = 2;  // building the map is not what is measured
    update.retain_passages = g_retain_passages;
    MapUpdater updater(update);
    for (int i = 0; i < g_passages; ++i) {
      const Passage passage = city.MakePassage(i);
      absl::StatusOr<PassageUpdate> u = updater.Compute(passage, out->map);
      if (!u.ok()) continue;
      out->map.Apply(u->delta);
      updater.Applied(passage, u->delta);
      if ((i + 1) % 20 == 0) std::fprintf(stderr, "built %d of %d passages\n", i + 1, g_passages);
    }
    std::vector<const Landmark*> all;
    out->map.ForEachLandmark([&](const Landmark& l) { all.push_back(&l); });
    std::mt19937_64 rng(1);
    std::uniform_int_distribution<size_t> pick(0, all.size() - 1);
    size_t total = 0;
    for (int b = 0; b < kBoxes; ++b) {
      const LatLon centre = all[pick(rng)]->position;
      std::vector<LandmarkId> ids;
      for (const Landmark* l : all) {
        const Eigen::Vector2d d = EastNorthOffset(centre, l->position);
        if (std::abs(d.x()) <= kBoxHalfWidthM && std::abs(d.y()) <= kBoxHalfWidthM) ids.push_back(l->id);
      }
      std::sort(ids.begin(), ids.end());
      total += ids.size();
      out->boxes.push_back(std::move(ids));
    }
    const std::string kept = g_retain_passages == 0
                                 ? std::string("every passage's")
                                 : "the last " + std::to_string(g_retain_passages) + " passages' at most";
    std::fprintf(stderr,
                 "map: %zu landmarks, %zu factors kept (%s), version %lld; %d boxes of 500 m, %.1f landmarks each\n",
                 out->map.landmark_count(), out->map.factor_count(), kept.c_str(),
                 static_cast<long long>(out->map.version()), kBoxes, static_cast<double>(total) / kBoxes);
    return out;
  }();
  return *city_map;
}

std::shared_ptr<const MapWindow> WholeWindow() {
  static std::shared_ptr<const MapWindow> window = [] {
    const MapState& map = TheMap().map;
    return std::make_shared<const MapWindow>(*MapWindow::Build(map, map.LandmarkIds(), MapWindowOptions{}));
  }();
  return window;
}

void BM_Factorise(benchmark::State& state) {
  const MapState& map = TheMap().map;
  for (auto _ : state) {
    absl::StatusOr<MapWindow> w = MapWindow::Build(map, map.LandmarkIds(), MapWindowOptions{});
    if (!w.ok()) state.SkipWithError(w.status().ToString().c_str());
    benchmark::DoNotOptimize(w);
  }
  state.counters["landmarks"] = static_cast<double>(map.landmark_count());
}

void BM_BoxCovariance(benchmark::State& state) {
  const CityMap& city = TheMap();
  const std::shared_ptr<const MapWindow> window = WholeWindow();
  const bool forward = state.range(0) == 0;
  size_t next = 0;
  for (auto _ : state) {
    const std::vector<LandmarkId>& ids = city.boxes[next++ % city.boxes.size()];
    if (forward) {
      absl::StatusOr<Eigen::MatrixXd> cov = window->Covariance(ids);
      if (!cov.ok()) state.SkipWithError(cov.status().ToString().c_str());
      benchmark::DoNotOptimize(cov);
    } else {
      absl::StatusOr<Eigen::MatrixXd> columns = window->CovarianceColumns(ids);
      if (!columns.ok()) state.SkipWithError(columns.status().ToString().c_str());
      Eigen::MatrixXd cov(2 * ids.size(), 2 * ids.size());
      for (size_t k = 0; k < ids.size(); ++k) cov.middleRows<2>(2 * k) = columns->middleRows<2>(2 * window->index(ids[k]));
      benchmark::DoNotOptimize(cov);
    }
  }
  state.SetLabel(forward ? "forward" : "columns");
}

// Each box's marginal standard deviations (East and North of every landmark) from the whole map's
// factorisation: the exact ones.
const std::vector<Eigen::VectorXd>& ExactSigmas() {
  static const std::vector<Eigen::VectorXd> sigmas = [] {
    std::vector<Eigen::VectorXd> out;
    for (const std::vector<LandmarkId>& ids : TheMap().boxes) {
      out.push_back(WholeWindow()->Covariance(ids)->diagonal().cwiseSqrt());
    }
    return out;
  }();
  return sigmas;
}

void BM_BoxCovarianceBounded(benchmark::State& state) {
  const CityMap& city = TheMap();
  MapWindowOptions options;
  options.hops = static_cast<int>(state.range(0));
  options.estimate = false;  // as JointCovariance
  size_t next = 0;
  double build_ms = 0.0, inverse_ms = 0.0, window_landmarks = 0.0;
  // How much wider the bounded window's marginal sigmas are than the exact ones (1 = exact), over
  // every coordinate of the boxes read: the mean, the smallest (at least 1: conservative) and the
  // largest ratio.
  const std::vector<Eigen::VectorXd>& exact = ExactSigmas();
  double ratio_sum = 0.0, ratio_min = 1e300, ratio_max = 0.0, ratio_count = 0.0;
  double narrower_boxes = 0.0, boxes = 0.0, ratio_min_others = 1e300;
  for (auto _ : state) {
    // JointCovariance in its two steps, each timed: the window's factorisation, the box's inverse.
    const std::vector<LandmarkId>& ids = city.boxes[next++ % city.boxes.size()];
    const auto start = std::chrono::steady_clock::now();
    absl::StatusOr<MapWindow> window = MapWindow::Build(city.map, ids, options);
    const auto built = std::chrono::steady_clock::now();
    if (!window.ok()) {
      state.SkipWithError(window.status().ToString().c_str());
      break;
    }
    absl::StatusOr<Eigen::MatrixXd> cov = window->Covariance(ids);
    const auto done = std::chrono::steady_clock::now();
    if (!cov.ok()) {
      state.SkipWithError(cov.status().ToString().c_str());
      break;
    }
    benchmark::DoNotOptimize(cov);
    build_ms += std::chrono::duration<double, std::milli>(built - start).count();
    inverse_ms += std::chrono::duration<double, std::milli>(done - built).count();
    window_landmarks += static_cast<double>(window->landmarks().size());
    const Eigen::VectorXd ratio = cov->diagonal().cwiseSqrt().cwiseQuotient(exact[(next - 1) % city.boxes.size()]);
    ratio_sum += ratio.sum();
    ratio_count += static_cast<double>(ratio.size());
    ratio_min = std::min(ratio_min, ratio.minCoeff());
    ratio_max = std::max(ratio_max, ratio.maxCoeff());
    boxes += 1.0;
    if (window->covariance_bound() == CovarianceBound::kMayBeNarrower) {
      narrower_boxes += 1.0;
    } else {
      ratio_min_others = std::min(ratio_min_others, ratio.minCoeff());
    }
  }
  state.counters["sigma_vs_exact"] = ratio_count > 0 ? ratio_sum / ratio_count : 0.0;
  state.counters["sigma_vs_exact_min"] = ratio_count > 0 ? ratio_min : 0.0;
  state.counters["sigma_vs_exact_max"] = ratio_max;
  state.counters["may_be_narrower"] = boxes > 0 ? narrower_boxes / boxes : 0.0;
  if (narrower_boxes < boxes) state.counters["sigma_vs_exact_min_others"] = ratio_min_others;
  state.counters["build_ms"] = benchmark::Counter(build_ms, benchmark::Counter::kAvgIterations);
  state.counters["inverse_ms"] = benchmark::Counter(inverse_ms, benchmark::Counter::kAvgIterations);
  state.counters["window_landmarks"] = benchmark::Counter(window_landmarks, benchmark::Counter::kAvgIterations);
}

BENCHMARK(BM_Factorise)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_BoxCovariance)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_BoxCovarianceBounded)->ArgName("hops")->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace crowdmap

int main(int argc, char** argv) {
  std::vector<char*> rest = {argv[0]};
  for (int i = 1; i < argc; ++i) {
    const bool has_value = i + 1 < argc;
    if (std::strcmp(argv[i], "--blocks") == 0 && has_value) {
      crowdmap::g_blocks = std::atoi(argv[++i]);
    } else if (std::strcmp(argv[i], "--passages") == 0 && has_value) {
      crowdmap::g_passages = std::atoi(argv[++i]);
    } else if (std::strcmp(argv[i], "--retain-passages") == 0 && has_value) {
      crowdmap::g_retain_passages = std::atoi(argv[++i]);
    } else {
      rest.push_back(argv[i]);
    }
  }
  if (crowdmap::g_blocks < 1 || crowdmap::g_passages < 1) {
    std::fprintf(stderr, "--blocks and --passages must be positive\n");
    return 2;
  }
  if (crowdmap::g_retain_passages < 0) {
    std::fprintf(stderr, "--retain-passages must be >= 0 (0 = keep every passage's factors)\n");
    return 2;
  }
  int rest_argc = static_cast<int>(rest.size());
  benchmark::Initialize(&rest_argc, rest.data());
  if (benchmark::ReportUnrecognizedArguments(rest_argc, rest.data())) return 2;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
