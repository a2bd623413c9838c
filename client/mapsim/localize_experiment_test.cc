#include "client/mapsim/localize_experiment.h"

#include <cmath>

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

// The own maps' rows carry the Cramer-Rao bound of their passages, which more passages lower.
TEST(LocalizeExperiment, OwnMapsCarryTheBoundOfTheirPassages) {
  LocalizeExperimentOptions options;
  options.landmark_counts = {44};
  options.duration_s = 60.0;
  options.runs = 1;
  options.gnss_fixes = 0;
  options.own_map_passages = {2, 6};
  absl::StatusOr<std::vector<LocalizeRow>> rows = RunLocalizeExperiment(options);
  ASSERT_TRUE(rows.ok()) << rows.status();
  ASSERT_EQ(rows->size(), 7u);
  const LocalizeCell& two = (*rows)[5].cells[0];
  const LocalizeCell& six = (*rows)[6].cells[0];
  EXPECT_TRUE(std::isnan((*rows)[0].cells[0].map_crlb_m));
  EXPECT_GT(six.map_crlb_m, 0.0);
  EXPECT_LT(six.map_crlb_m, two.map_crlb_m);
  EXPECT_NE(LocalizeMarkdown(options, *rows).find("Cramer-Rao bound of its passages"), std::string::npos);
}

TEST(LocalizeExperiment, RejectsBadOptions) {
  LocalizeExperimentOptions options;
  options.runs = 0;
  EXPECT_FALSE(RunLocalizeExperiment(options).ok());
}

}  // namespace
}  // namespace crowdmap
