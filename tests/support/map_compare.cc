#include "tests/support/map_compare.h"

#include <vector>

#include "core/geo/local_frame.h"
#include "core/map/map_window.h"

namespace crowdmap {

::testing::AssertionResult MapsMatch(const MapState& expected, const MapState& actual, double position_tol_m,
                                     double cov_tol_m2) {
  const std::vector<LandmarkId> ids = expected.LandmarkIds();
  if (ids != actual.LandmarkIds()) {
    return ::testing::AssertionFailure() << "landmark ids differ: expected " << ids.size() << ", got "
                                         << actual.landmark_count();
  }
  for (LandmarkId id : ids) {
    const Landmark& e = *expected.FindLandmark(id);
    const Landmark& a = *actual.FindLandmark(id);
    const double dist = EastNorthOffset(e.position, a.position).norm();
    if (dist > position_tol_m) {
      return ::testing::AssertionFailure() << "landmark " << id << " is " << dist << " m from the expected position";
    }
    if (e.passages_seen != a.passages_seen) {
      return ::testing::AssertionFailure() << "landmark " << id << " seen by " << a.passages_seen
                                           << " passages, expected " << e.passages_seen;
    }
  }
  // The joint covariances, recovered from each map's information (a stored marginal may be older
  // than the information: see MarginalRefresh).
  absl::StatusOr<Eigen::MatrixXd> e = JointCovariance(expected, ids), a = JointCovariance(actual, ids);
  if (!e.ok() || !a.ok()) {
    return ::testing::AssertionFailure() << "joint covariance: " << e.status() << " / " << a.status();
  }
  const double err = (*e - *a).cwiseAbs().maxCoeff();
  if (err > cov_tol_m2) {
    return ::testing::AssertionFailure() << "joint covariances differ by " << err << " m^2";
  }
  return ::testing::AssertionSuccess();
}

MapState MapFromPassages(const Scenario& scenario, int passages, const MapUpdateOptions& options, int skip) {
  MapState map;
  MapUpdater updater(options);
  for (int i = 0; i < passages; ++i) {
    if (i == skip) continue;
    const Passage passage = scenario.MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok()) continue;
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
  }
  return map;
}

}  // namespace crowdmap
