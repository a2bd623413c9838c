#include "client/mapsim/localize_experiment.h"

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(LocalizeExperiment, DenseMapHelpsOnAShortRoute) {
  LocalizeExperimentOptions options;
  options.landmark_counts = {500};
  options.duration_s = 60.0;
  options.runs = 1;
  absl::StatusOr<std::vector<LocalizeRow>> rows = RunLocalizeExperiment(options);
  ASSERT_TRUE(rows.ok()) << rows.status();
  ASSERT_EQ(rows->size(), 5u);
  for (const LocalizeRow& row : *rows) {
    ASSERT_EQ(row.cells.size(), 1u);
    EXPECT_LT(row.cells[0].with_map_m, row.cells[0].without_map_m) << row.config.name;
  }
  EXPECT_DOUBLE_EQ((*rows)[0].cells[0].thesis_with_m, 0.72);
  const std::string table = LocalizeMarkdown(options, *rows);
  EXPECT_NE(table.find("| white | 2.76 / "), std::string::npos) << table;
}

TEST(LocalizeExperiment, RejectsBadOptions) {
  LocalizeExperimentOptions options;
  options.runs = 0;
  EXPECT_FALSE(RunLocalizeExperiment(options).ok());
}

}  // namespace
}  // namespace crowdmap
