#include "client/mapsim/city_experiment.h"
#include "server/testing/temp_dir.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

CityExperimentOptions SmallCity() {
  CityExperimentOptions options;
  options.city.blocks_x = 2;
  options.city.blocks_y = 2;
  options.city.block_m = 100.0;
  options.city.route_length_m = 400.0;
  options.city.vehicles = 3;
  options.passages = 6;
  options.progress_every_passages = 2;
  return options;
}

int CountLines(const std::filesystem::path& path) {
  std::ifstream in(path);
  int lines = 0;
  for (std::string line; std::getline(in, line);) ++lines;
  return lines;
}

TEST(CityExperiment, MapsTheCityAndWritesItsOutputs) {
  const CityExperimentOptions options = SmallCity();
  int reports = 0;
  absl::StatusOr<CityExperimentResult> result =
      RunCityExperiment(options, [&](const CityProgress& p) {
        ++reports;
        EXPECT_EQ(p.passages_done, 2 * reports);
      });
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(reports, 3);
  EXPECT_EQ(result->failed_passages, 0);
  EXPECT_EQ(result->passage_ms.size(), 6u);
  EXPECT_GT(result->errors.size(), result->layout_landmarks / 4);
  EXPECT_LE(result->errors.size(), result->layout_landmarks);
  // GNSS has 10 m of noise; six passages put the landmarks within a few metres.
  EXPECT_TRUE(std::isfinite(result->mean_error_m));
  EXPECT_GT(result->mean_error_m, 0.0);
  EXPECT_LT(result->mean_error_m, 5.0);
  EXPECT_LE(result->median_error_m, result->p95_error_m);
  for (const CityLandmarkError& e : result->errors) {
    EXPECT_GT(e.sigma_east_m, 0.0);
    EXPECT_GT(e.sigma_north_m, 0.0);
  }

  TempDir scratch;  // a fresh directory: no leftover of another run
  const std::filesystem::path dir = std::filesystem::path(scratch.path()) / "city_experiment_test";
  std::filesystem::remove_all(dir);
  ASSERT_TRUE(WriteCityOutputs(options, *result, dir.string()).ok());
  EXPECT_EQ(CountLines(dir / "landmarks.csv"), static_cast<int>(result->errors.size()) + 1);
  std::ifstream json(dir / "summary.json");
  const std::string summary((std::istreambuf_iterator<char>(json)), std::istreambuf_iterator<char>());
  for (const char* key : {"\"landmarks_in_layout\"", "\"landmarks_mapped\"", "\"mean_error_m\"", "\"median_error_m\"",
                          "\"p95_error_m\"", "\"passages_failed\"", "\"p50_ms_per_passage\"", "\"p95_ms_per_passage\""}) {
    EXPECT_NE(summary.find(key), std::string::npos) << key;
  }
  EXPECT_EQ(summary.find("null"), std::string::npos);
}

TEST(CityExperiment, RefusesInvalidOptionsNamingTheField) {
  CityExperimentOptions options = SmallCity();
  options.passages = 0;
  EXPECT_EQ(RunCityExperiment(options).status().message().substr(0, 9), "passages:");
  options = SmallCity();
  options.city.spacing_min_m = -1.0;
  EXPECT_EQ(RunCityExperiment(options).status().message().substr(0, 14), "spacing_min_m:");
}

}  // namespace
}  // namespace crowdmap
