#include "client/mapsim/experiment.h"
#include "server/testing/temp_dir.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <utility>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(Experiment, ErrorFallsAndCovarianceStaysConsistentOverThirtyPassages) {
  ExperimentOptions options;
  options.scenario.landmarks = 25;
  options.passages = 30;
  options.strategy = "cc-gsd";
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_EQ(result->records.size(), 30u);
  EXPECT_EQ(result->failed_passages, 0);
  EXPECT_EQ(result->records.front().metrics.landmarks_evaluated, 25);
  const double first = result->records.front().metrics.mean_dist_err_m;
  const double last = result->records.back().metrics.mean_dist_err_m;
  // One passage maps to a few metres; thirty should at least halve that.
  EXPECT_GT(first, 1.0);
  EXPECT_LT(last, 0.5 * first);
  for (const PassageRecord& r : result->records) {
    EXPECT_GT(r.metrics.nees_per_dof, 0.2) << "passage " << r.passage;
    EXPECT_LT(r.metrics.nees_per_dof, 3.0) << "passage " << r.passage;
    EXPECT_GE(r.subgraphs, 1);
  }
  // Its errors against the bound's joint covariance (chi-square with 50 degrees of freedom, per
  // degree of freedom, for an efficient estimator).
  EXPECT_GT(result->crlb_joint_nees_per_dof, 0.3);
  EXPECT_LT(result->crlb_joint_nees_per_dof, 3.0);
}

TEST(Experiment, ModellingTheGnssProcessMakesTheAr1MapConsistentDeclaredOrFound) {
  // AR(1) GNSS errors (alpha = 0.988 at 1 Hz), 30 passages, seeds 1 to 4: with the process the
  // passages declare, the joint NEES per dof averages about 1 (measured 1.00: 0.76 to 1.27); with
  // it hidden from the estimator (white noise assumed, as before it was modelled) about 11
  // (5.8 to 15.7); hidden, but found from the passages' residuals (correlated_gnss_min_lag1, on by
  // default), about 1 again (measured 0.95: 0.70 to 1.27; 21 of each run's 30 passages found, the
  // others in joint solves, whose graphs take the process too but report nothing).
  double modelled = 0.0, white = 0.0, found = 0.0;
  int correlated = 0;
  for (uint64_t seed = 1; seed <= 4; ++seed) {
    for (int mode = 0; mode < 3; ++mode) {
      ExperimentOptions options;
      options.scenario.landmarks = 25;
      options.scenario.noise = NoiseConfig::kGnssAr1;
      options.scenario.seed = seed;
      options.passages = 30;
      options.crlb = false;
      options.assume_white_gnss = mode > 0;
      if (mode == 1) {
        options.update.correlated_gnss_min_lag1 = 0.0;
        // An estimator that ignores the process keeps a map about 3 times over-confident: honest
        // passages then move its landmarks beyond 3 of its sigmas and the whole-update gate
        // refuses a quarter of them (measured: 31 of 120; 1 of 120 with the gate at 5 sigmas).
        // This test is about the consistency each estimator reaches, so that gate is off for it.
        options.update.max_update_shift_mahalanobis2 = 0.0;
      }
      absl::StatusOr<ExperimentResult> result = RunExperiment(options);
      ASSERT_TRUE(result.ok()) << result.status();
      EXPECT_EQ(result->failed_passages, 0);
      (mode == 0 ? modelled : mode == 1 ? white : found) += result->final_joint_nees_per_dof / 4.0;
      if (mode == 2) correlated += result->correlated_gnss_passages;
      if (mode != 2) EXPECT_EQ(result->correlated_gnss_passages, 0) << "declared, or the check off";
    }
  }
  EXPECT_GT(modelled, 0.6);
  EXPECT_LT(modelled, 1.6);
  EXPECT_GT(white, 3.0);
  EXPECT_GT(found, 0.6);
  EXPECT_LT(found, 1.6);
  EXPECT_GT(correlated, 4 * (30 - 12));  // all but the joint solves' (warm-up and re-solves)
}

TEST(Experiment, ACameraNoisierThanDeclaredIsFoundAndTheMapStaysConsistent) {
  // Pixel noise twice what the passages declare, 50 landmarks, 60 passages, seeds 1 to 4: the
  // whole graph's chi-square test inflates some subgraphs, but the camera holds few of the degrees
  // of freedom and the map keeps a joint NEES per dof of about 1.5 (measured 1.54: 1.09 to 1.99);
  // with each sensor tested on its own about 1.0 (1.03: 0.80 to 1.25), the camera found in most
  // passages with a factor near 4, and the map no less accurate (0.377 against 0.391 m).
  double tested = 0.0, untested = 0.0, tested_error = 0.0, untested_error = 0.0;
  int camera_found = 0;
  for (uint64_t seed = 1; seed <= 4; ++seed) {
    for (const bool test : {false, true}) {
      ExperimentOptions options;
      options.scenario.landmarks = 50;
      options.scenario.seed = seed;
      options.scenario.undeclared_noise.pixel = 2.0;
      options.passages = 60;
      options.crlb = false;
      if (!test) options.update.sensor_test_sigmas = 0.0;
      absl::StatusOr<ExperimentResult> result = RunExperiment(options);
      ASSERT_TRUE(result.ok()) << result.status();
      EXPECT_EQ(result->failed_passages, 0);
      (test ? tested : untested) += result->final_joint_nees_per_dof / 4.0;
      (test ? tested_error : untested_error) += result->final_mean_dist_err_m / 4.0;
      const SensorInflations& found = result->sensor_inflations;
      if (!test) EXPECT_EQ(found.passages[0] + found.passages[1] + found.passages[2], 0) << "the test off";
      if (test) {
        EXPECT_EQ(found.passages[0], 0) << "odometry as declared";
        EXPECT_EQ(found.passages[1], 0) << "GNSS as declared";
        camera_found += found.passages[2];
      }
    }
  }
  EXPECT_GT(untested, 1.3);
  EXPECT_LT(tested, 1.25);
  EXPECT_GT(tested, 0.75);
  EXPECT_LT(tested_error, 1.02 * untested_error);
  EXPECT_GT(camera_found, 4 * 60 / 2);
}

TEST(Experiment, DecorrelatedMapKeepsNoCrossCovariances) {
  ExperimentOptions options;
  options.scenario.landmarks = 10;
  options.passages = 3;
  options.strategy = "dc";
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_TRUE(result.ok()) << result.status();
  result->final_map.ForEachFactor([](const MapFactor& f) { EXPECT_EQ(f.landmarks.size(), 1u); });
  EXPECT_EQ(result->final_map.landmark_count(), 10u);
}

TEST(Experiment, TriangulationBaselineHasNoCovariance) {
  ExperimentOptions options;
  options.scenario.landmarks = 4;
  options.passages = 5;
  options.strategy = "triangulation";
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_LT(result->final_mean_dist_err_m, 10.0);
  EXPECT_TRUE(std::isnan(result->final_nees_per_dof));
}

TEST(Experiment, RejectsAnUnknownStrategy) {
  ExperimentOptions options;
  options.strategy = "kalman";
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_FALSE(result.ok());
  EXPECT_NE(result.status().message().find("strategy"), std::string::npos);
}

TEST(Experiment, AppliesPassagesInTheGivenOrder) {
  ExperimentOptions options;
  options.scenario.landmarks = 4;
  options.passages = 3;
  options.strategy = "dc";
  options.order = {2, 0, 1};
  absl::StatusOr<ExperimentResult> reordered = RunExperiment(options);
  ASSERT_TRUE(reordered.ok()) << reordered.status();
  options.order.clear();
  absl::StatusOr<ExperimentResult> in_order = RunExperiment(options);
  ASSERT_TRUE(in_order.ok()) << in_order.status();
  // The first passage alone decides the first map: passage 2 first gives another first record.
  EXPECT_NE(reordered->records.front().metrics.mean_dist_err_m, in_order->records.front().metrics.mean_dist_err_m);
  EXPECT_EQ(reordered->records.size(), 3u);
}

// With white noise the noise model is right, so the consistency test fires only as a rare false
// alarm (about one passage in a thousand, variance factor near 1.35); a passage inflated far more
// was solved into a wrong minimum. In this order (seed 1) passage 162, applied 165th,
// needs more than 20 iterations to localise its second subgraph against the map; a localisation
// stopped short of the basin left the full solve at chi2 = 33 per degree of freedom.
TEST(Experiment, WhiteNoisePassagesAreNeverInflatedInAReorderedRun) {
  ExperimentOptions options;
  options.scenario.landmarks = 25;
  options.passages = 168;
  options.strategy = "cc-gsd";
  options.order = ShuffledOrder(168, 8, 40, 8);
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->failed_passages, 0);
  EXPECT_EQ(result->inflated_passages, 0);
}

TEST(Experiment, ShuffledOrderPermutesOnlyWithinWindowsAfterTheStart) {
  const std::vector<int> order = ShuffledOrder(23, 4, 3, 9);
  ASSERT_EQ(order.size(), 23u);
  for (int i = 0; i < 3; ++i) EXPECT_EQ(order[i], i);
  for (int i = 3; i < 23; ++i) EXPECT_EQ((order[i] - 3) / 4, (i - 3) / 4) << i;  // stays in its window
  std::vector<int> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (int i = 0; i < 23; ++i) EXPECT_EQ(sorted[i], i);
  EXPECT_NE(order, ShuffledOrder(23, 1, 0, 9));  // something moved
  EXPECT_EQ(order, ShuffledOrder(23, 4, 3, 9));  // deterministic
}

TEST(Experiment, RejectsAnOrderThatIsNotAPermutation) {
  ExperimentOptions options;
  options.passages = 3;
  for (const std::vector<int>& order : {std::vector<int>{0, 1}, {0, 1, 1}, {0, 1, 3}, {-1, 0, 1}}) {
    options.order = order;
    absl::StatusOr<ExperimentResult> result = RunExperiment(options);
    ASSERT_FALSE(result.ok());
    EXPECT_EQ(result.status().message().substr(0, 5), "order") << result.status();
  }
}

TEST(Experiment, OrderFileRoundTripsAndNamesTheBadLine) {
  TempDir scratch;  // a fresh directory: no leftover of another run
  const std::filesystem::path dir = std::filesystem::path(scratch.path()) / "order_files";
  std::filesystem::create_directories(dir);
  const std::vector<int> order = {2, 0, 3, 1};
  ASSERT_TRUE(WriteOrderFile(order, (dir / "order.txt").string()).ok());
  absl::StatusOr<std::vector<int>> read = ReadOrderFile((dir / "order.txt").string());
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, order);

  std::ofstream((dir / "bad.txt").string()) << "2\n0\n3x\n1\n";
  read = ReadOrderFile((dir / "bad.txt").string());
  ASSERT_FALSE(read.ok());
  EXPECT_EQ(read.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(read.status().message().find("bad.txt:3:"), std::string::npos) << read.status();
  EXPECT_EQ(ReadOrderFile((dir / "missing.txt").string()).status().code(), absl::StatusCode::kNotFound);
}

// The header line of a CSV file and the number of rows after it.
std::pair<std::string, int> ReadCsv(const std::filesystem::path& path) {
  std::ifstream csv(path);
  std::string header;
  std::getline(csv, header);
  int rows = 0;
  for (std::string line; std::getline(csv, line);) ++rows;
  return {header, rows};
}

TEST(Experiment, WritesCsvSummaryAndPlot) {
  ExperimentOptions options;
  options.scenario.landmarks = 4;
  options.passages = 3;
  absl::StatusOr<ExperimentResult> result = RunExperiment(options);
  ASSERT_TRUE(result.ok()) << result.status();
  TempDir scratch;  // a fresh directory: no leftover of another run
  const std::filesystem::path dir = std::filesystem::path(scratch.path()) / "experiment_outputs";
  ASSERT_TRUE(WriteExperimentOutputs(options, *result, dir.string()).ok());
  const auto [header, rows] = ReadCsv(dir / "passages.csv");
  EXPECT_EQ(header.rfind("passage,mean_dist_err_m,mean_east_err_m,mean_north_err_m,east_3sigma_m,north_3sigma_m,"
                         "nees_per_dof,solve_ms,subgraphs", 0),
            0u);
  EXPECT_EQ(rows, 3);
  std::ifstream json(dir / "summary.json");
  const std::string summary((std::istreambuf_iterator<char>(json)), std::istreambuf_iterator<char>());
  for (const char* key : {"final_mean_dist_err_m", "final_nees_per_dof", "median_passage_ms", "\"passages\": 3",
                          "\"landmarks\": 4", "\"strategy\": \"cc-gsd\"", "\"noise\": \"white\"", "\"seed\": 1"}) {
    EXPECT_NE(summary.find(key), std::string::npos) << key;
  }
  EXPECT_NE(summary.find("nees_per_dof_sd_if_consistent"), std::string::npos);
  EXPECT_GT(std::filesystem::file_size(dir / "errors.svg"), 1000u);

  // One row per mapped landmark, with its error and covariance; one row per pair of them.
  EXPECT_EQ(ReadCsv(dir / "landmarks.csv"),
            std::make_pair(std::string("landmark,true_east_m,true_north_m,east_err_m,north_err_m,cov_ee_m2,"
                                       "cov_en_m2,cov_nn_m2"),
                           4));
  EXPECT_EQ(ReadCsv(dir / "cross_covariances.csv"),
            std::make_pair(std::string("landmark_a,landmark_b,cov_ee_m2,cov_en_m2,cov_ne_m2,cov_nn_m2"), 6));
}

}  // namespace
}  // namespace crowdmap
