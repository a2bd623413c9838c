#ifndef CROWDMAP_CORE_MAP_MAP_STATE_H_
#define CROWDMAP_CORE_MAP_MAP_STATE_H_

#include <cstdint>
#include <functional>
#include <unordered_map>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "core/geo/local_frame.h"
#include "core/model/passage.h"

namespace crowdmap {

enum class LandmarkState { kActive = 1 };

// A mapped landmark. Its covariance is in metres^2 in the East/North frame at its position.
struct Landmark {
  LandmarkId id = 0;
  LatLon position;
  Eigen::Matrix2d cov_en_m2 = Eigen::Matrix2d::Identity();
  int64_t version = 0;          // map version that last changed it
  int64_t passages_seen = 0;    // passages that detected it
  int64_t last_seen_unix_ms = 0;
  LandmarkState state = LandmarkState::kActive;
};

// Ordered key of a landmark pair (first < second).
using LandmarkPair = std::pair<LandmarkId, LandmarkId>;

struct LandmarkPairHash {
  size_t operator()(const LandmarkPair& p) const {
    return std::hash<int64_t>()(p.first) * 0x9E3779B97F4A7C15ull ^ std::hash<int64_t>()(p.second);
  }
};

// Read access to a map: landmarks and the sparse cross-covariance blocks between them.
// Cross block Sigma_ab has rows in a's East/North frame and columns in b's.
class MapReaderInterface {
 public:
  virtual ~MapReaderInterface() = default;
  virtual const Landmark* FindLandmark(LandmarkId id) const = 0;
  // Sigma_ab; false (and *cov untouched) when no block is stored, meaning zero correlation.
  virtual bool CrossCovariance(LandmarkId a, LandmarkId b, Eigen::Matrix2d* cov) const = 0;
  // Appends the ids that share a stored cross block with `id`.
  virtual void AppendNeighbors(LandmarkId id, std::vector<LandmarkId>* out) const = 0;
  virtual int64_t version() const = 0;
};

// The changes one passage makes to a map; applied atomically (in memory or in one transaction).
struct MapDelta {
  int64_t base_version = 0;  // map version the delta was computed against
  int64_t version = 0;       // map version after applying it
  std::unordered_map<LandmarkId, Landmark> landmarks;  // full new records, created or changed
  std::unordered_map<LandmarkPair, Eigen::Matrix2d, LandmarkPairHash> cross;  // key first<second

  bool empty() const { return landmarks.empty() && cross.empty(); }
};

// In-memory map: the estimation core's map type, mirrored by the persistent store.
class MapState : public MapReaderInterface {
 public:
  const Landmark* FindLandmark(LandmarkId id) const override;
  bool CrossCovariance(LandmarkId a, LandmarkId b, Eigen::Matrix2d* cov) const override;
  void AppendNeighbors(LandmarkId id, std::vector<LandmarkId>* out) const override;
  int64_t version() const override { return version_; }

  size_t landmark_count() const { return entries_.size(); }
  size_t cross_block_count() const { return cross_block_count_; }
  void ForEachLandmark(const std::function<void(const Landmark&)>& fn) const;
  // Ids in increasing order.
  std::vector<LandmarkId> LandmarkIds() const;

  // Inserts or replaces records; used by the store when loading. Sets the version when larger.
  void PutLandmark(const Landmark& landmark);
  void PutCrossCovariance(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& cov_ab);
  void set_version(int64_t v) { version_ = v; }

  // Applies a delta computed against this map's current version.
  void Apply(const MapDelta& delta);

 private:
  struct Entry {
    Landmark landmark;
    std::unordered_map<LandmarkId, Eigen::Matrix2d> cross;  // Sigma_{this, other}
  };
  std::unordered_map<LandmarkId, Entry> entries_;
  size_t cross_block_count_ = 0;
  int64_t version_ = 0;
};

// A map seen through pending changes: reads see `delta` over `base`; writes go to the delta.
class MapOverlay : public MapReaderInterface {
 public:
  explicit MapOverlay(const MapReaderInterface& base);

  const Landmark* FindLandmark(LandmarkId id) const override;
  bool CrossCovariance(LandmarkId a, LandmarkId b, Eigen::Matrix2d* cov) const override;
  void AppendNeighbors(LandmarkId id, std::vector<LandmarkId>* out) const override;
  int64_t version() const override { return delta_.version; }

  void PutLandmark(const Landmark& landmark);
  void PutCrossCovariance(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& cov_ab);
  // Starts the next map version; returns it.
  int64_t BumpVersion() { return ++delta_.version; }

  const MapDelta& delta() const { return delta_; }
  MapDelta TakeDelta() { return std::move(delta_); }

 private:
  const MapReaderInterface& base_;
  MapDelta delta_;
  std::unordered_map<LandmarkId, std::vector<LandmarkId>> added_neighbors_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_MAP_STATE_H_
