#include "tests/support/map_compare.h"

#include <vector>

#include "core/geo/local_frame.h"

namespace crowdmap {

::testing::AssertionResult MapsMatch(const MapState& expected, const MapState& actual, double position_tol_m,
                                     double cov_tol_m2) {
  const std::vector<LandmarkId> ids = expected.LandmarkIds();
  if (ids != actual.LandmarkIds()) {
    return ::testing::AssertionFailure() << "landmark ids differ: expected " << ids.size() << ", got "
                                         << actual.landmark_count();
  }
  if (expected.cross_block_count() != actual.cross_block_count()) {
    return ::testing::AssertionFailure() << "cross blocks: expected " << expected.cross_block_count() << ", got "
                                         << actual.cross_block_count();
  }
  for (LandmarkId id : ids) {
    const Landmark& e = *expected.FindLandmark(id);
    const Landmark& a = *actual.FindLandmark(id);
    const double dist = EastNorthOffset(e.position, a.position).norm();
    if (dist > position_tol_m) {
      return ::testing::AssertionFailure() << "landmark " << id << " is " << dist << " m from the expected position";
    }
    const double cov_err = (e.cov_en_m2 - a.cov_en_m2).cwiseAbs().maxCoeff();
    if (cov_err > cov_tol_m2) {
      return ::testing::AssertionFailure() << "landmark " << id << " covariance differs by " << cov_err << " m^2";
    }
    if (e.passages_seen != a.passages_seen) {
      return ::testing::AssertionFailure() << "landmark " << id << " seen by " << a.passages_seen
                                           << " passages, expected " << e.passages_seen;
    }
    std::vector<LandmarkId> neighbors;
    expected.AppendNeighbors(id, &neighbors);
    for (LandmarkId other : neighbors) {
      Eigen::Matrix2d eb, ab;
      expected.CrossCovariance(id, other, &eb);
      if (!actual.CrossCovariance(id, other, &ab)) {
        return ::testing::AssertionFailure() << "missing cross block (" << id << ", " << other << ")";
      }
      const double err = (eb - ab).cwiseAbs().maxCoeff();
      if (err > cov_tol_m2) {
        return ::testing::AssertionFailure() << "cross block (" << id << ", " << other << ") differs by " << err;
      }
    }
  }
  return ::testing::AssertionSuccess();
}

MapState MapFromPassages(const Scenario& scenario, int passages, const MapUpdateOptions& options) {
  MapState map;
  MapUpdater updater(options);
  for (int i = 0; i < passages; ++i) {
    const Passage passage = scenario.MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok()) continue;
    map.Apply(update->delta);
    updater.Applied(passage);
  }
  return map;
}

}  // namespace crowdmap
