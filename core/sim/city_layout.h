#ifndef CROWDMAP_CORE_SIM_CITY_LAYOUT_H_
#define CROWDMAP_CORE_SIM_CITY_LAYOUT_H_

#include <functional>
#include <random>
#include <vector>

#include <Eigen/Core>

#include "core/geo/local_frame.h"
#include "core/sim/city_options.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// An axis-aligned rectangle in the city frame (m).
struct Rect2 {
  Eigen::Vector2d min_m;
  Eigen::Vector2d max_m;
};

// Whether the segment a-b passes through the interior of `rect` (touching its border does not count).
bool SegmentCrossesRect(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Rect2& rect);

// The static city: street centrelines, buildings, landmarks and a grid index over them. Built in
// time linear in the number of landmarks; depends only on the layout options and layout_seed.
// Frame: East/North (m) at options.origin, the nominal south-west intersection.
class CityLayout {
 public:
  // `options` must have passed Validate().
  explicit CityLayout(const CityScenarioOptions& options);

  const LocalFrame& frame() const { return frame_; }
  // Centreline positions of the north-south streets (x, west to east) and of the east-west
  // streets (y, south to north): blocks_x + 1 and blocks_y + 1 of them.
  const std::vector<double>& street_x_m() const { return street_x_m_; }
  const std::vector<double>& street_y_m() const { return street_y_m_; }
  double road_half_width_m() const { return road_half_width_m_; }
  // One building per block, block (i, j) at index j * blocks_x + i.
  const std::vector<Rect2>& buildings() const { return buildings_; }
  // Landmark id k + 1 at index k.
  const std::vector<TruthLandmark>& landmarks() const { return landmarks_; }

  // Calls fn(landmark) for every landmark within radius_m of center (and a few beyond it), from the
  // grid index; never scans the whole layout.
  void ForEachLandmarkNear(const Eigen::Vector2d& center_m, double radius_m,
                           const std::function<void(const TruthLandmark&)>& fn) const;
  // Whether no building stands between a and b.
  bool LineOfSightClear(const Eigen::Vector2d& a_m, const Eigen::Vector2d& b_m) const;

 private:
  void PlaceLandmarksAlong(bool east_west, double street_m, double from_m, double to_m, double side,
                           std::mt19937_64* rng);
  void BuildIndex();
  // Index of the block interval [streets[k], streets[k + 1]] holding v, clamped to the grid.
  static int BlockOf(const std::vector<double>& streets, double v);

  CityScenarioOptions options_;
  LocalFrame frame_;
  double road_half_width_m_ = 0.0;
  std::vector<double> street_x_m_, street_y_m_;
  std::vector<Rect2> buildings_;
  std::vector<TruthLandmark> landmarks_;
  // Grid index: landmark indices of cell c at cell_items_[cell_start_[c] .. cell_start_[c + 1]).
  Eigen::Vector2d index_origin_m_ = Eigen::Vector2d::Zero();
  int index_cols_ = 0, index_rows_ = 0;
  std::vector<int> cell_start_, cell_items_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_CITY_LAYOUT_H_
