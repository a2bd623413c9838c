#ifndef CROWDMAP_CORE_MAP_MAP_ACCESS_H_
#define CROWDMAP_CORE_MAP_MAP_ACCESS_H_

#include <cstdint>
#include <functional>
#include <optional>
#include <unordered_map>
#include <set>
#include <string>
#include <unordered_set>
#include <utility>

#include "core/map/map_state.h"

namespace crowdmap {

// Map updates computed concurrently against one version of the map (the service's workers). An
// update reads a neighbourhood of the map; another update committed meanwhile changed another
// part. When the part it changed holds nothing the first one read, the first one's computation
// would have read exactly the same against the map with the other's change, and so produced the
// same change: it is committed after the other once its version numbers and new factor ids are
// moved past the other's (RebaseDelta). Otherwise it is computed again.

// The passage factors came from: vehicle_id, passage_id.
using FactorSource = std::pair<std::string, std::string>;

// What a computation read from a map (MapReadRecorder).
struct MapReadSet {
  // Landmarks whose record, information blocks or information vector were read (a block (a, b)
  // counts for both a and b, a row of ForEachLink for its landmark).
  std::unordered_set<LandmarkId> landmarks;
  // Landmarks whose list of factors was read (AppendFactorIds).
  std::unordered_set<LandmarkId> factor_lists;
  // Factors read by id (FindFactor, AppendFactorLandmarks; a miss counts) and those a list of
  // factors handed out: their removal or folding changes what was read.
  std::unordered_set<int64_t> factors;
  std::set<FactorSource> passage_factor_lists;  // AppendPassageFactorIds
  std::set<std::string> vehicles;             // FindVehicle
  bool all_vehicles = false;                  // ForEachVehicle
};

// What committing a delta changes in a map (WriteSetOf).
struct MapWriteSet {
  // Landmarks whose record, information blocks or information vector change: the landmark
  // records written or removed, and the landmarks of every factor added or removed.
  std::unordered_set<LandmarkId> landmarks;
  // Landmarks whose list of factors gains or loses a factor by an addition or a removal, and the
  // passages whose factors change (added, removed or folded).
  std::unordered_set<LandmarkId> factor_lists;
  std::set<FactorSource> passages;
  // Factors added, removed or folded. A fold changes no information and no list but those that held
  // the factor, which a computation that read one of them recorded in MapReadSet::factors: it needs
  // no landmarks here, and a computation that read other factors of its landmarks stays valid.
  std::unordered_set<int64_t> factors;
  std::set<std::string> vehicles;
};

// Whether a computation that read `read` could have read differently after `written` was committed.
bool Overlaps(const MapReadSet& read, const MapWriteSet& written);

// What committing `delta` to `map` (the map it was computed against, or a later one that still
// holds the factors it removes and folds) changes.
MapWriteSet WriteSetOf(const MapDelta& delta, const MapReaderInterface& map);

// Moves a delta computed against a map whose last factor id was `from_last_factor_id` onto a map
// at `version` whose last factor id is `last_factor_id`: its versions (the delta's and its
// records') shift by version - delta.base_version, its new factors' ids by last_factor_id -
// from_last_factor_id. Meant for a delta that Overlaps none of the changes committed in between.
void RebaseDelta(int64_t from_last_factor_id, int64_t version, int64_t last_factor_id, MapDelta* delta);

// Runs a function with a map under whatever lock keeps it from changing during the call.
using MapAccess = std::function<void(const std::function<void(const MapReaderInterface&)>&)>;

// A MapReaderInterface over a map that may change between its calls (other workers' commits), that
// records what was read. Each call reads through `access` (one short lock per call) and copies
// what it returns, so that the pointers it hands out stay valid; a record or a row of links read
// once is read again from that copy. Reads of one computation can thus come from several versions
// of the map, but only where a commit changed what it read, which Overlaps tells: such a
// computation is discarded. Not thread-safe: one per computation.
class MapReadRecorder : public MapReaderInterface {
 public:
  explicit MapReadRecorder(MapAccess access);
  // A computation that counts as made against the map at `version` (whose last factor id was
  // `last_factor_id`) although `access` may already show a later one: a commit under way when it
  // starts. Sound when it is checked, as any computation is, against every change committed since
  // `version`: what it read of a later version is what those changes wrote.
  MapReadRecorder(MapAccess access, int64_t version, int64_t last_factor_id);
  // Over a map that does not change meanwhile.
  explicit MapReadRecorder(const MapReaderInterface& map);

  const Landmark* FindLandmark(LandmarkId id) const override;
  InformationBlock Information(LandmarkId a, LandmarkId b) const override;
  Eigen::Vector2d InformationVector(LandmarkId id) const override;
  void ForEachLink(LandmarkId id, const std::function<void(LandmarkId, const InformationBlock&)>& fn) const override;
  const InformationRow* InformationRowOf(LandmarkId id) const override;
  const MapFactor* FindFactor(int64_t id) const override;
  bool AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const override;
  void AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const override;
  void AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                              std::vector<int64_t>* out) const override;
  // Of the map the computation counts as made against (as when the recorder was made, unless given).
  int64_t last_factor_id() const override { return last_factor_id_; }
  int64_t version() const override { return version_; }
  const VehicleCalibration* FindVehicle(const std::string& vehicle_id) const override;
  void ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const override;

  const MapReadSet& read() const { return read_; }
  MapReadSet TakeRead() { return std::move(read_); }

 private:
  MapAccess access_;
  int64_t last_factor_id_ = 0;
  int64_t version_ = 0;
  mutable MapReadSet read_;
  // Copies of what was read (nullopt: absent), node-based so that pointers into them stay valid.
  mutable std::unordered_map<LandmarkId, std::optional<Landmark>> landmarks_;
  mutable std::unordered_map<int64_t, std::optional<MapFactor>> factors_;
  // The landmarks of factors whose landmarks alone were read (AppendFactorLandmarks).
  mutable std::unordered_map<int64_t, std::optional<std::vector<LandmarkId>>> factor_landmarks_;
  mutable std::unordered_map<std::string, std::optional<VehicleCalibration>> vehicles_;
  // The rows read, the diagonal included (a window reads most of them twice: to find its
  // landmarks, then to assemble their information), and the buffer one is gathered in.
  mutable std::unordered_map<LandmarkId, InformationRow> rows_;
  mutable InformationRow row_buffer_;
  // Row `id`, read once (recorded as a read of the landmark).
  const InformationRow& CachedRow(LandmarkId id) const;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_MAP_ACCESS_H_
