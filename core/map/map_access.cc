#include "core/map/map_access.h"

namespace crowdmap {
namespace {

template <typename Set>
bool Intersect(const Set& a, const Set& b) {
  const Set& small = a.size() <= b.size() ? a : b;
  const Set& large = a.size() <= b.size() ? b : a;
  for (const auto& x : small) {
    if (large.count(x) > 0) return true;
  }
  return false;
}

}  // namespace

bool Overlaps(const MapReadSet& read, const MapWriteSet& written) {
  return Intersect(read.landmarks, written.landmarks) || Intersect(read.factor_lists, written.factor_lists) ||
         Intersect(read.factors, written.factors) || Intersect(read.passage_factor_lists, written.passages) ||
         Intersect(read.vehicles, written.vehicles) || (read.all_vehicles && !written.vehicles.empty());
}

MapWriteSet WriteSetOf(const MapDelta& delta, const MapReaderInterface& map) {
  MapWriteSet out;
  // A factor added or removed changes its landmarks' information and factor lists.
  auto factor_changes = [&](const MapFactor& f) {
    for (LandmarkId l : f.landmarks) {
      out.factor_lists.insert(l);
      out.landmarks.insert(l);
    }
    out.passages.insert({f.vehicle_id, f.passage_id});
  };
  for (const auto& [id, landmark] : delta.landmarks) out.landmarks.insert(id);
  out.landmarks.insert(delta.removed_landmarks.begin(), delta.removed_landmarks.end());
  for (const auto& [id, factor] : delta.added_factors) {
    out.factors.insert(id);  // a computation that looked the id up found nothing there
    factor_changes(factor);
  }
  for (int64_t id : delta.removed_factors) {
    out.factors.insert(id);
    if (const MapFactor* f = map.FindFactor(id); f != nullptr) factor_changes(*f);
  }
  // A folded factor's information stays in the map: only the factor itself goes.
  for (int64_t id : delta.folded_factors) {
    out.factors.insert(id);
    if (const MapFactor* f = map.FindFactor(id); f != nullptr) out.passages.insert({f->vehicle_id, f->passage_id});
  }
  for (const auto& [id, vehicle] : delta.vehicles) out.vehicles.insert(id);
  return out;
}

void RebaseDelta(int64_t from_last_factor_id, int64_t version, int64_t last_factor_id, MapDelta* delta) {
  const int64_t from_version = delta->base_version;
  const int64_t shift = version - from_version;
  auto moved = [&](int64_t v) { return v > from_version ? v + shift : v; };
  delta->base_version = version;
  delta->version = moved(delta->version);
  for (auto& [id, landmark] : delta->landmarks) landmark.version = moved(landmark.version);
  for (auto& [id, vehicle] : delta->vehicles) vehicle.version = moved(vehicle.version);
  std::map<int64_t, MapFactor> factors;
  for (auto& [id, factor] : delta->added_factors) {
    factor.id = id > from_last_factor_id ? id - from_last_factor_id + last_factor_id : id;
    factors.emplace(factor.id, std::move(factor));
  }
  delta->added_factors = std::move(factors);
}

MapReadRecorder::MapReadRecorder(MapAccess access) : access_(std::move(access)) {
  access_([this](const MapReaderInterface& map) {
    last_factor_id_ = map.last_factor_id();
    version_ = map.version();
  });
}

MapReadRecorder::MapReadRecorder(MapAccess access, int64_t version, int64_t last_factor_id)
    : access_(std::move(access)), last_factor_id_(last_factor_id), version_(version) {}

MapReadRecorder::MapReadRecorder(const MapReaderInterface& map)
    : MapReadRecorder([&map](const std::function<void(const MapReaderInterface&)>& read) { read(map); }) {}

namespace {

// The copy in `cache` of what `find` returns, made through `access` on the first call.
template <typename Key, typename Record, typename Find>
const Record* Cached(const MapAccess& access, const Key& key, std::unordered_map<Key, std::optional<Record>>* cache,
                     const Find& find) {
  auto it = cache->find(key);
  if (it == cache->end()) {
    std::optional<Record> copy;
    access([&](const MapReaderInterface& map) {
      if (const Record* r = find(map); r != nullptr) copy = *r;
    });
    it = cache->emplace(key, std::move(copy)).first;
  }
  return it->second ? &*it->second : nullptr;
}

}  // namespace

const Landmark* MapReadRecorder::FindLandmark(LandmarkId id) const {
  read_.landmarks.insert(id);
  return Cached(access_, id, &landmarks_, [id](const MapReaderInterface& map) { return map.FindLandmark(id); });
}

InformationBlock MapReadRecorder::Information(LandmarkId a, LandmarkId b) const {
  read_.landmarks.insert(a);
  read_.landmarks.insert(b);
  InformationBlock out;
  access_([&](const MapReaderInterface& map) { out = map.Information(a, b); });
  return out;
}

Eigen::Vector2d MapReadRecorder::InformationVector(LandmarkId id) const {
  read_.landmarks.insert(id);
  Eigen::Vector2d out;
  access_([&](const MapReaderInterface& map) { out = map.InformationVector(id); });
  return out;
}

const InformationRow& MapReadRecorder::CachedRow(LandmarkId id) const {
  // A block (id, b) changes only with a factor on both: one on id, which records id's row.
  read_.landmarks.insert(id);
  auto it = rows_.find(id);
  if (it == rows_.end()) {
    // Gathered in a buffer that keeps its capacity, then copied at its size: one allocation.
    row_buffer_.clear();
    access_([&](const MapReaderInterface& map) {
      if (const InformationRow* row = map.InformationRowOf(id); row != nullptr) {
        row_buffer_.assign(row->begin(), row->end());
        return;
      }
      const InformationBlock diagonal = map.Information(id, id);
      bool placed = false;
      map.ForEachLink(id, [&](LandmarkId b, const InformationBlock& block) {
        if (!placed && b > id) {
          row_buffer_.push_back({id, diagonal});
          placed = true;
        }
        row_buffer_.push_back({b, block});
      });
      if (!placed) row_buffer_.push_back({id, diagonal});
    });
    it = rows_.emplace(id, row_buffer_).first;
  }
  return it->second;
}

void MapReadRecorder::ForEachLink(LandmarkId id,
                                  const std::function<void(LandmarkId, const InformationBlock&)>& fn) const {
  for (const LinkedBlock& e : CachedRow(id)) {  // outside the access: fn may read again
    if (e.id != id) fn(e.id, e.block);
  }
}

const InformationRow* MapReadRecorder::InformationRowOf(LandmarkId id) const { return &CachedRow(id); }

const MapFactor* MapReadRecorder::FindFactor(int64_t id) const {
  read_.factors.insert(id);
  return Cached(access_, id, &factors_, [id](const MapReaderInterface& map) { return map.FindFactor(id); });
}

bool MapReadRecorder::AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const {
  // Read like FindFactor (the same entry in the read set), but its information is not copied.
  read_.factors.insert(id);
  const std::vector<LandmarkId>* landmarks = nullptr;
  if (auto f = factors_.find(id); f != factors_.end()) {
    if (f->second) landmarks = &f->second->landmarks;
  } else {
    auto it = factor_landmarks_.find(id);
    if (it == factor_landmarks_.end()) {
      std::optional<std::vector<LandmarkId>> copy;
      access_([&](const MapReaderInterface& map) {
        std::vector<LandmarkId> read;
        if (map.AppendFactorLandmarks(id, &read)) copy = std::move(read);
      });
      it = factor_landmarks_.emplace(id, std::move(copy)).first;
    }
    if (it->second) landmarks = &*it->second;
  }
  if (landmarks == nullptr) return false;
  out->insert(out->end(), landmarks->begin(), landmarks->end());
  return true;
}

void MapReadRecorder::AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const {
  read_.factor_lists.insert(id);
  const size_t from = out->size();
  access_([&](const MapReaderInterface& map) { map.AppendFactorIds(id, out); });
  read_.factors.insert(out->begin() + static_cast<std::ptrdiff_t>(from), out->end());
}

void MapReadRecorder::AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                                             std::vector<int64_t>* out) const {
  read_.passage_factor_lists.insert({vehicle_id, passage_id});
  access_([&](const MapReaderInterface& map) { map.AppendPassageFactorIds(vehicle_id, passage_id, out); });
}

const VehicleCalibration* MapReadRecorder::FindVehicle(const std::string& vehicle_id) const {
  read_.vehicles.insert(vehicle_id);
  return Cached(access_, vehicle_id, &vehicles_,
                [&vehicle_id](const MapReaderInterface& map) { return map.FindVehicle(vehicle_id); });
}

void MapReadRecorder::ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const {
  read_.all_vehicles = true;
  std::vector<VehicleCalibration> vehicles;  // copied under the lock, handed out after it
  access_([&](const MapReaderInterface& map) {
    map.ForEachVehicle([&](const VehicleCalibration& v) { vehicles.push_back(v); });
  });
  for (const VehicleCalibration& v : vehicles) fn(v);
}

}  // namespace crowdmap
