#include "core/sim/city_layout.h"

#include <algorithm>
#include <cmath>

#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

// Side of a grid-index cell: a detection query (50 m range) then reads about 5 x 5 cells.
constexpr double kIndexCellM = 25.0;

}  // namespace

bool SegmentCrossesRect(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Rect2& rect) {
  // Liang-Barsky clipping of the segment a + t (b - a), t in [0, 1], against the open rectangle.
  double t0 = 0.0, t1 = 1.0;
  const Eigen::Vector2d d = b - a;
  for (int axis = 0; axis < 2; ++axis) {
    if (std::abs(d[axis]) < 1e-12) {
      if (a[axis] <= rect.min_m[axis] || a[axis] >= rect.max_m[axis]) return false;
      continue;
    }
    double ta = (rect.min_m[axis] - a[axis]) / d[axis];
    double tb = (rect.max_m[axis] - a[axis]) / d[axis];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
    if (t0 >= t1) return false;
  }
  return true;
}

CityLayout::CityLayout(const CityScenarioOptions& options)
    : options_(options), frame_(options.origin), road_half_width_m_(0.5 * options.road_width_m) {
  std::mt19937_64 rng(SplitMix64(options.layout_seed ^ 0x5EEDC17Eull));
  std::uniform_real_distribution<double> jitter(-options.street_jitter_m, options.street_jitter_m);
  for (int i = 0; i <= options.blocks_x; ++i) street_x_m_.push_back(i * options.block_m + jitter(rng));
  for (int j = 0; j <= options.blocks_y; ++j) street_y_m_.push_back(j * options.block_m + jitter(rng));

  const double inset = road_half_width_m_ + options.building_setback_m;
  for (int j = 0; j < options.blocks_y; ++j) {
    for (int i = 0; i < options.blocks_x; ++i) {
      buildings_.push_back({{street_x_m_[i] + inset, street_y_m_[j] + inset},
                            {street_x_m_[i + 1] - inset, street_y_m_[j + 1] - inset}});
    }
  }

  const double clearance = road_half_width_m_ + options.corner_clearance_m;
  for (int j = 0; j <= options.blocks_y; ++j) {
    for (int i = 0; i < options.blocks_x; ++i) {
      for (double side : {-1.0, 1.0}) {
        PlaceLandmarksAlong(true, street_y_m_[j], street_x_m_[i] + clearance, street_x_m_[i + 1] - clearance, side,
                            &rng);
      }
    }
  }
  for (int i = 0; i <= options.blocks_x; ++i) {
    for (int j = 0; j < options.blocks_y; ++j) {
      for (double side : {-1.0, 1.0}) {
        PlaceLandmarksAlong(false, street_x_m_[i], street_y_m_[j] + clearance, street_y_m_[j + 1] - clearance, side,
                            &rng);
      }
    }
  }
  BuildIndex();
}

void CityLayout::PlaceLandmarksAlong(bool east_west, double street_m, double from_m, double to_m, double side,
                                     std::mt19937_64* rng) {
  std::uniform_real_distribution<double> spacing(options_.spacing_min_m, options_.spacing_max_m);
  std::uniform_real_distribution<double> offset(options_.landmark_kerb_offset_min_m,
                                                options_.landmark_kerb_offset_max_m);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  // The first landmark of a stretch is placed at a random phase of the spacing, so that stretches
  // do not all start with a landmark at the corner.
  for (double along = from_m + unit(*rng) * options_.spacing_min_m; along <= to_m; along += spacing(*rng)) {
    const double across = street_m + side * (road_half_width_m_ + offset(*rng));
    TruthLandmark lm;
    lm.id = static_cast<LandmarkId>(landmarks_.size()) + 1;
    lm.position_m = east_west ? Eigen::Vector2d(along, across) : Eigen::Vector2d(across, along);
    lm.position = frame_.ToGeo(lm.position_m);
    landmarks_.push_back(lm);
  }
}

void CityLayout::BuildIndex() {
  const double margin = road_half_width_m_ + options_.landmark_kerb_offset_max_m + kIndexCellM;
  index_origin_m_ = Eigen::Vector2d(street_x_m_.front() - margin, street_y_m_.front() - margin);
  index_cols_ = static_cast<int>(std::ceil((street_x_m_.back() + margin - index_origin_m_.x()) / kIndexCellM));
  index_rows_ = static_cast<int>(std::ceil((street_y_m_.back() + margin - index_origin_m_.y()) / kIndexCellM));
  auto cell_of = [&](const Eigen::Vector2d& p) {
    const int c = std::clamp(static_cast<int>((p.x() - index_origin_m_.x()) / kIndexCellM), 0, index_cols_ - 1);
    const int r = std::clamp(static_cast<int>((p.y() - index_origin_m_.y()) / kIndexCellM), 0, index_rows_ - 1);
    return r * index_cols_ + c;
  };
  // Counting sort by cell: linear in the landmarks.
  cell_start_.assign(static_cast<size_t>(index_cols_) * index_rows_ + 1, 0);
  for (const TruthLandmark& lm : landmarks_) ++cell_start_[cell_of(lm.position_m) + 1];
  for (size_t c = 1; c < cell_start_.size(); ++c) cell_start_[c] += cell_start_[c - 1];
  std::vector<int> next(cell_start_.begin(), cell_start_.end() - 1);
  cell_items_.resize(landmarks_.size());
  for (size_t k = 0; k < landmarks_.size(); ++k) cell_items_[next[cell_of(landmarks_[k].position_m)]++] = k;
}

void CityLayout::ForEachLandmarkNear(const Eigen::Vector2d& center_m, double radius_m,
                                     const std::function<void(const TruthLandmark&)>& fn) const {
  const Eigen::Vector2d lo = (center_m - index_origin_m_).array() - radius_m;
  const Eigen::Vector2d hi = (center_m - index_origin_m_).array() + radius_m;
  const int c0 = std::max(0, static_cast<int>(std::floor(lo.x() / kIndexCellM)));
  const int c1 = std::min(index_cols_ - 1, static_cast<int>(std::floor(hi.x() / kIndexCellM)));
  const int r0 = std::max(0, static_cast<int>(std::floor(lo.y() / kIndexCellM)));
  const int r1 = std::min(index_rows_ - 1, static_cast<int>(std::floor(hi.y() / kIndexCellM)));
  for (int r = r0; r <= r1; ++r) {
    for (int c = c0; c <= c1; ++c) {
      const int cell = r * index_cols_ + c;
      for (int k = cell_start_[cell]; k < cell_start_[cell + 1]; ++k) fn(landmarks_[cell_items_[k]]);
    }
  }
}

int CityLayout::BlockOf(const std::vector<double>& streets, double v) {
  const int k = static_cast<int>(std::upper_bound(streets.begin(), streets.end(), v) - streets.begin()) - 1;
  return std::clamp(k, 0, static_cast<int>(streets.size()) - 2);
}

bool CityLayout::LineOfSightClear(const Eigen::Vector2d& a_m, const Eigen::Vector2d& b_m) const {
  const int i0 = BlockOf(street_x_m_, std::min(a_m.x(), b_m.x())), i1 = BlockOf(street_x_m_, std::max(a_m.x(), b_m.x()));
  const int j0 = BlockOf(street_y_m_, std::min(a_m.y(), b_m.y())), j1 = BlockOf(street_y_m_, std::max(a_m.y(), b_m.y()));
  for (int j = j0; j <= j1; ++j) {
    for (int i = i0; i <= i1; ++i) {
      if (SegmentCrossesRect(a_m, b_m, buildings_[j * options_.blocks_x + i])) return false;
    }
  }
  return true;
}

}  // namespace crowdmap
