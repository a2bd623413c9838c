#ifndef CROWDMAP_TESTS_SUPPORT_MAP_COMPARE_H_
#define CROWDMAP_TESTS_SUPPORT_MAP_COMPARE_H_

#include "core/estimation/map_updater.h"
#include "core/map/map_state.h"
#include "core/sim/scenario.h"
#include "gtest/gtest.h"

namespace crowdmap {

// Same landmarks, positions within `position_tol_m` (metres, East/North), every covariance and
// cross-covariance entry within `cov_tol_m2`, and the same cross-block pattern.
::testing::AssertionResult MapsMatch(const MapState& expected, const MapState& actual, double position_tol_m,
                                     double cov_tol_m2);

// The map the service builds with `options` from the scenario's first `passages` passages
// applied in order (all but `skip`, if given), computed in-process.
MapState MapFromPassages(const Scenario& scenario, int passages, const MapUpdateOptions& options = MapUpdateOptions(),
                         int skip = -1);

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_SUPPORT_MAP_COMPARE_H_
