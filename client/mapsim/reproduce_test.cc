#include "client/mapsim/reproduce.h"
#include "server/testing/temp_dir.h"

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "absl/strings/str_split.h"

namespace crowdmap {
namespace {

std::string ReadAll(const std::filesystem::path& path) {
  std::ifstream in(path);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// A reproduction of 2 passages per experiment into `scratch`, a fresh directory (no leftover of
// another run).
ReproduceOptions SmallReproduction(const TempDir& scratch) {
  ReproduceOptions options;
  options.out_dir = (std::filesystem::path(scratch.path()) / "reproduce").string();
  options.passages = 2;
  return options;
}

TEST(Reproduce, RunsEveryExperimentForEachSeedAndReportsTheMeans) {
  TempDir scratch;
  ReproduceOptions options = SmallReproduction(scratch);
  options.seed = 4;
  options.seeds = 2;
  options.nees_sd_target = 0.0;  // no further seeds
  ASSERT_TRUE(RunReproduction(options).ok());
  for (const char* name : {"n4_cc_white_s4", "n100_cc-gsd_white_s5", "n50_cc-gsd_ar1+yaw_s5", "n50_cc-gsd_ar1+yaw_yaw_s5",
                           "n50_cc-gsd_white_v20_yaw_s4"}) {
    EXPECT_TRUE(std::filesystem::exists(std::filesystem::path(options.out_dir) / name / "summary.json")) << name;
  }
  const std::string md = ReadAll(std::filesystem::path(options.out_dir) / "reproduction.md");
  EXPECT_NE(md.find("seeds 4 to 5"), std::string::npos) << md;
  // Each white-noise row: the mean error with its range over the seeds, the NEES with the spread a
  // consistent map would give it ("±"), for every N.
  for (const char* row : {"| 4 | ", "| 25 | ", "| 50 | ", "| 75 | ", "| 100 | "}) {
    const size_t at = md.find(row);
    ASSERT_NE(at, std::string::npos) << row;
    const std::string line = md.substr(at, md.find('\n', at) - at);
    EXPECT_NE(line.find(" ± "), std::string::npos) << line;
    EXPECT_NE(line.find(") |"), std::string::npos) << line;
    EXPECT_EQ(line.find("failed"), std::string::npos) << line;
  }
  for (const char* noise : {"| white |", "| yaw-bias |", "| gnss-ar1 |", "| ar1+yaw |"}) {
    EXPECT_NE(md.find(noise), std::string::npos) << noise;
  }
  // The camera yaw table: the fleet row reports how well each vehicle's yaw is known.
  const size_t yaw_table = md.find("camera yaw estimated");
  ASSERT_NE(yaw_table, std::string::npos) << md;
  const size_t fleet = md.find("| white, 20 vehicles with their own yaw |", yaw_table);
  ASSERT_NE(fleet, std::string::npos) << md;
  const std::string line = md.substr(fleet, md.find('\n', fleet) - fleet);
  EXPECT_EQ(line.find("failed"), std::string::npos) << line;
  // The vehicle yaw columns: within 2 sigma, NEES, and the shared error beside the records' sigma.
  const std::vector<std::string> cells = absl::StrSplit(line, " | ");
  ASSERT_GE(cells.size(), 4u) << line;
  for (size_t i = cells.size() - 3; i < cells.size(); ++i) EXPECT_EQ(cells[i].find("n/a"), std::string::npos) << line;
  EXPECT_NE(cells.back().find(" / "), std::string::npos) << line;
}

TEST(Reproduce, ConsistencyCellsTakeSeedsUntilTheirMeanNeesIsPreciseEnough) {
  TempDir scratch;
  ReproduceOptions options = SmallReproduction(scratch);
  options.seeds = 1;
  options.max_seeds = 3;
  options.nees_sd_target = 1e-6;  // never reached: every CC and CC+GSD cell takes max_seeds
  ASSERT_TRUE(RunReproduction(options).ok());
  const std::filesystem::path out(options.out_dir);
  for (const char* name : {"n4_cc_white_s3", "n100_cc-gsd_white_s3", "n50_cc-gsd_gnss-ar1_s3"}) {
    EXPECT_TRUE(std::filesystem::exists(out / name / "summary.json")) << name;
  }
  for (const char* name : {"n4_cc_white_s4", "n4_dc_white_s2", "n50_cc-gsd_ar1+yaw_s2", "n50_cc-gsd_yaw-bias_s2"}) {
    EXPECT_FALSE(std::filesystem::exists(out / name)) << name;
  }
  const std::string md = ReadAll(out / "reproduction.md");
  const size_t at = md.find("| 4 | ");
  ASSERT_NE(at, std::string::npos);
  EXPECT_NE(md.substr(at, md.find('\n', at) - at).find(" (3) |"), std::string::npos) << md;
}

TEST(Reproduce, EveryExperimentUsesTheDetectionsAskedFor) {
  TempDir scratch;
  ReproduceOptions options = SmallReproduction(scratch);
  options.seeds = 1;
  options.nees_sd_target = 0.0;
  options.detections_per_landmark = 0;
  ASSERT_TRUE(RunReproduction(options).ok());
  const std::filesystem::path out(options.out_dir);
  for (const char* name : {"n4_dc_white_s1", "n100_cc-gsd_white_s1", "n50_cc-gsd_white_v20_yaw_s1"}) {
    EXPECT_NE(ReadAll(out / name / "summary.json").find("\"detections_per_landmark\": 0"), std::string::npos) << name;
  }
  EXPECT_NE(ReadAll(out / "reproduction.md").find("Detections per landmark and passage: all."), std::string::npos);
}

TEST(Reproduce, RefusesBadOptionsNamingTheField) {
  TempDir scratch;
  ReproduceOptions options = SmallReproduction(scratch);
  options.seeds = 0;
  const absl::Status s = RunReproduction(options);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("seeds"), std::string::npos) << s;
  options.seeds = 3;
  options.max_seeds = 2;
  EXPECT_NE(RunReproduction(options).message().find("max_seeds"), std::string::npos);
  options.max_seeds = 20;
  options.nees_sd_target = -1.0;
  EXPECT_NE(RunReproduction(options).message().find("nees_sd_target"), std::string::npos);
  options.nees_sd_target = 0.2;
  options.detections_per_landmark = 1;  // no landmark could be created
  EXPECT_NE(RunReproduction(options).message().find("detections_per_landmark"), std::string::npos);
  options.detections_per_landmark = 5;
  options.jobs = 0;
  EXPECT_NE(RunReproduction(options).message().find("jobs"), std::string::npos);
  options.jobs = 2;
  options.passages = 0;
  EXPECT_NE(RunReproduction(options).message().find("passages"), std::string::npos);
}

}  // namespace
}  // namespace crowdmap
