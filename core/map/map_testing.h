#ifndef CROWDMAP_CORE_MAP_MAP_TESTING_H_
#define CROWDMAP_CORE_MAP_MAP_TESTING_H_

// Records shared by the map tests.

#include <string>
#include <utility>
#include <vector>

#include "core/map/map_state.h"

namespace crowdmap {

// Landmark `id` at its anchor (48 + 0.001 id deg N, 2 deg E), covariance id * I, at `version`.
inline Landmark MakeLandmark(LandmarkId id, int64_t version) {
  Landmark l;
  l.id = id;
  l.anchor = {48.0 + 0.001 * id, 2.0};
  l.position = l.anchor;
  l.cov_en_m2 = Eigen::Matrix2d::Identity() * id;
  l.version = version;
  return l;
}

// A factor of passage ("v", `passage`) on `ids` with information (i + 1) * I + 0.1 off the
// diagonal and vector 1, 2, ...
inline MapFactor MakeFactor(int64_t id, std::vector<LandmarkId> ids, const std::string& passage = "p") {
  MapFactor f;
  f.id = id;
  f.vehicle_id = "v";
  f.passage_id = passage;
  f.landmarks = std::move(ids);
  const int n = 2 * static_cast<int>(f.landmarks.size());
  f.information = Eigen::MatrixXd::Constant(n, n, 0.1);
  for (int i = 0; i < n; ++i) f.information(i, i) = i + 1.0;
  f.information_vector = Eigen::VectorXd::LinSpaced(n, 1.0, n);
  return f;
}

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_MAP_TESTING_H_
