#include "core/map/map_state.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"

namespace crowdmap {

namespace {

// The block (row's landmark, b), inserted (zero, no factor) when absent.
InformationBlock& BlockIn(InformationRow& row, LandmarkId b) {
  auto it = std::lower_bound(row.begin(), row.end(), b, [](const LinkedBlock& e, LandmarkId id) { return e.id < id; });
  if (it == row.end() || it->id != b) it = row.insert(it, LinkedBlock{b, InformationBlock{}});
  return it->block;
}

const InformationBlock* FindIn(const InformationRow& row, LandmarkId b) {
  auto it = std::lower_bound(row.begin(), row.end(), b, [](const LinkedBlock& e, LandmarkId id) { return e.id < id; });
  return it == row.end() || it->id != b ? nullptr : &it->block;
}

}  // namespace

void AssembledInformation::Add(const MapFactor& factor, int sign) {
  const int k = static_cast<int>(factor.landmarks.size());
  // The factor's landmarks in increasing id, merged into each of their rows in one pass.
  std::vector<int> order(k);
  for (int j = 0; j < k; ++j) order[j] = j;
  std::sort(order.begin(), order.end(), [&](int x, int y) { return factor.landmarks[x] < factor.landmarks[y]; });
  InformationRow merged;
  for (int i = 0; i < k; ++i) {
    const LandmarkId a = factor.landmarks[i];
    auto [it, inserted] = vector_.try_emplace(a, Eigen::Vector2d::Zero());
    it->second += sign * factor.information_vector.segment<2>(2 * i);
    InformationRow& row = rows_[a];
    merged.clear();
    merged.reserve(row.size() + k);
    size_t r = 0;
    for (int j : order) {
      const LandmarkId b = factor.landmarks[j];
      while (r < row.size() && row[r].id < b) merged.push_back(row[r++]);
      LinkedBlock entry = r < row.size() && row[r].id == b ? row[r++] : LinkedBlock{b, InformationBlock{}};
      entry.block.value += sign * factor.information.block<2, 2>(2 * i, 2 * j);
      entry.block.factors += sign;
      if (entry.block.factors != 0 || difference_) merged.push_back(entry);
    }
    while (r < row.size()) merged.push_back(row[r++]);
    row.swap(merged);
    if (row.empty() && !difference_) {
      rows_.erase(a);
      vector_.erase(a);
    }
  }
}

void AssembledInformation::AddBlock(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& value) {
  InformationBlock& ab = BlockIn(rows_[a], b);
  ab.value += value;
  ++ab.factors;
  vector_.try_emplace(a, Eigen::Vector2d::Zero());
  if (a == b) return;
  InformationBlock& ba = BlockIn(rows_[b], a);
  ba.value += value.transpose();
  ++ba.factors;
  vector_.try_emplace(b, Eigen::Vector2d::Zero());
}

void AssembledInformation::AddVector(LandmarkId id, const Eigen::Vector2d& value) {
  auto [it, inserted] = vector_.try_emplace(id, Eigen::Vector2d::Zero());
  it->second += value;
}

InformationBlock AssembledInformation::Block(LandmarkId a, LandmarkId b) const {
  const InformationRow* row = Row(a);
  const InformationBlock* block = row == nullptr ? nullptr : FindIn(*row, b);
  return block == nullptr ? InformationBlock{} : *block;
}

const InformationRow* AssembledInformation::Row(LandmarkId a) const {
  auto it = rows_.find(a);
  return it == rows_.end() ? nullptr : &it->second;
}

Eigen::Vector2d AssembledInformation::Vector(LandmarkId id) const {
  auto it = vector_.find(id);
  return it == vector_.end() ? Eigen::Vector2d::Zero() : it->second;
}

void AssembledInformation::ForEachLinked(LandmarkId a,
                                         const std::function<void(LandmarkId, const InformationBlock&)>& fn) const {
  const InformationRow* row = Row(a);
  if (row == nullptr) return;
  for (const LinkedBlock& e : *row) {
    if (e.id != a) fn(e.id, e.block);
  }
}

const InformationRow* MapState::InformationRowOf(LandmarkId id) const {
  static const InformationRow kEmpty;
  const InformationRow* row = information_.Row(id);
  return row == nullptr ? &kEmpty : row;
}

const Landmark* MapState::FindLandmark(LandmarkId id) const {
  auto it = landmarks_.find(id);
  return it == landmarks_.end() ? nullptr : &it->second;
}

const MapFactor* MapState::FindFactor(int64_t id) const {
  auto it = factors_.find(id);
  return it == factors_.end() ? nullptr : &it->second;
}

void MapState::AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const {
  auto it = factors_of_.find(id);
  if (it != factors_of_.end()) out->insert(out->end(), it->second.begin(), it->second.end());
}

void MapState::AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                                      std::vector<int64_t>* out) const {
  auto it = factors_of_passage_.find({vehicle_id, passage_id});
  if (it != factors_of_passage_.end()) out->insert(out->end(), it->second.begin(), it->second.end());
}

const VehicleCalibration* MapState::FindVehicle(const std::string& vehicle_id) const {
  const auto it = vehicles_.find(vehicle_id);
  return it != vehicles_.end() ? &it->second : nullptr;
}

void MapState::ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const {
  for (const auto& [id, vehicle] : vehicles_) fn(vehicle);
}

void MapState::ForEachLandmark(const std::function<void(const Landmark&)>& fn) const {
  for (const auto& [id, landmark] : landmarks_) fn(landmark);
}

void MapState::ForEachFactor(const std::function<void(const MapFactor&)>& fn) const {
  for (const auto& [id, factor] : factors_) fn(factor);
}

std::vector<LandmarkId> MapState::LandmarkIds() const {
  std::vector<LandmarkId> ids;
  ids.reserve(landmarks_.size());
  for (const auto& [id, landmark] : landmarks_) ids.push_back(id);
  std::sort(ids.begin(), ids.end());
  return ids;
}

void MapState::PutLandmark(const Landmark& landmark) {
  landmarks_[landmark.id] = landmark;
  version_ = std::max(version_, landmark.version);
}

void MapState::PutFactor(MapFactor factor) {
  RemoveFactor(factor.id);
  for (LandmarkId id : factor.landmarks) factors_of_[id].push_back(factor.id);
  information_.Add(factor, +1);
  factors_of_passage_[{factor.vehicle_id, factor.passage_id}].push_back(factor.id);
  last_factor_id_ = std::max(last_factor_id_, factor.id);
  const int64_t id = factor.id;
  factors_.emplace(id, std::move(factor));
}

void MapState::FoldFactor(int64_t id) {
  auto it = factors_.find(id);
  if (it == factors_.end()) return;
  ForgetFactor(it->second);  // its information stays in information_
  factors_.erase(it);
}

void MapState::ForgetFactor(const MapFactor& factor) {
  for (LandmarkId landmark : factor.landmarks) {
    std::vector<int64_t>& ids = factors_of_[landmark];
    ids.erase(std::remove(ids.begin(), ids.end(), factor.id), ids.end());
    if (ids.empty()) factors_of_.erase(landmark);
  }
  auto passage = factors_of_passage_.find({factor.vehicle_id, factor.passage_id});
  if (passage != factors_of_passage_.end()) {
    std::vector<int64_t>& ids = passage->second;
    ids.erase(std::remove(ids.begin(), ids.end(), factor.id), ids.end());
    if (ids.empty()) factors_of_passage_.erase(passage);
  }
}

void MapState::RemoveFactor(int64_t id) {
  auto it = factors_.find(id);
  if (it == factors_.end()) return;
  information_.Add(it->second, -1);
  ForgetFactor(it->second);
  factors_.erase(it);
}

void MapState::Apply(const MapDelta& delta) {
  for (int64_t id : delta.removed_factors) RemoveFactor(id);
  for (int64_t id : delta.folded_factors) FoldFactor(id);
  for (const auto& [id, factor] : delta.added_factors) PutFactor(factor);
  for (const auto& [id, landmark] : delta.landmarks) PutLandmark(landmark);
  for (LandmarkId id : delta.removed_landmarks) RemoveLandmark(id);
  for (const auto& [id, vehicle] : delta.vehicles) PutVehicle(vehicle);
  version_ = std::max(version_, delta.version);
}

MapOverlay::MapOverlay(const MapReaderInterface& base) : base_(base), last_factor_id_(base.last_factor_id()) {
  delta_.base_version = base.version();
  delta_.version = base.version();
}

const VehicleCalibration* MapOverlay::FindVehicle(const std::string& vehicle_id) const {
  const auto it = delta_.vehicles.find(vehicle_id);
  return it != delta_.vehicles.end() ? &it->second : base_.FindVehicle(vehicle_id);
}

void MapOverlay::ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const {
  // The base's records merged with the delta's, which replace them.
  auto next = delta_.vehicles.begin();
  base_.ForEachVehicle([&](const VehicleCalibration& vehicle) {
    for (; next != delta_.vehicles.end() && next->first < vehicle.vehicle_id; ++next) fn(next->second);
    if (next != delta_.vehicles.end() && next->first == vehicle.vehicle_id) {
      fn((next++)->second);
    } else {
      fn(vehicle);
    }
  });
  for (; next != delta_.vehicles.end(); ++next) fn(next->second);
}

const Landmark* MapOverlay::FindLandmark(LandmarkId id) const {
  if (std::find(delta_.removed_landmarks.begin(), delta_.removed_landmarks.end(), id) != delta_.removed_landmarks.end()) {
    return nullptr;
  }
  auto it = delta_.landmarks.find(id);
  return it != delta_.landmarks.end() ? &it->second : base_.FindLandmark(id);
}

InformationBlock MapOverlay::Information(LandmarkId a, LandmarkId b) const {
  InformationBlock block = base_.Information(a, b);
  const InformationBlock change = change_.Block(a, b);
  block.value += change.value;
  block.factors += change.factors;
  return block;
}

Eigen::Vector2d MapOverlay::InformationVector(LandmarkId id) const {
  return base_.InformationVector(id) + change_.Vector(id);
}

void MapOverlay::ForEachLink(LandmarkId id,
                             const std::function<void(LandmarkId, const InformationBlock&)>& fn) const {
  // The base's links and the change's row, both in increasing id, merged.
  const InformationRow* change = change_.Row(id);
  const size_t changes = change == nullptr ? 0 : change->size();
  size_t c = 0;
  const auto change_only = [&](const LinkedBlock& e) {  // a link only the change has
    if (e.id != id && e.block.factors > 0) fn(e.id, e.block);
  };
  base_.ForEachLink(id, [&](LandmarkId b, const InformationBlock& base) {
    for (; c < changes && (*change)[c].id < b; ++c) change_only((*change)[c]);
    InformationBlock block = base;
    if (c < changes && (*change)[c].id == b) {
      block.value += (*change)[c].block.value;
      block.factors += (*change)[c].block.factors;
      ++c;
    }
    if (block.factors > 0) fn(b, block);
  });
  for (; c < changes; ++c) change_only((*change)[c]);
}

const InformationRow* MapOverlay::InformationRowOf(LandmarkId id) const {
  return change_.Row(id) == nullptr ? base_.InformationRowOf(id) : nullptr;
}

const MapFactor* MapOverlay::FindFactor(int64_t id) const {
  auto it = delta_.added_factors.find(id);
  if (it != delta_.added_factors.end()) return &it->second;
  return Hidden(id) ? nullptr : base_.FindFactor(id);
}

bool MapOverlay::AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const {
  auto it = delta_.added_factors.find(id);
  if (it != delta_.added_factors.end()) {
    out->insert(out->end(), it->second.landmarks.begin(), it->second.landmarks.end());
    return true;
  }
  return !Hidden(id) && base_.AppendFactorLandmarks(id, out);
}

bool MapOverlay::Hidden(int64_t id) const { return removed_.count(id) > 0 || folded_.count(id) > 0; }

void MapOverlay::FoldFactor(int64_t id) {
  if (base_.FindFactor(id) == nullptr || Hidden(id)) return;
  folded_.insert(id);
  delta_.folded_factors.push_back(id);
}

void MapOverlay::AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const {
  const size_t start = out->size();
  base_.AppendFactorIds(id, out);
  out->erase(std::remove_if(out->begin() + start, out->end(), [&](int64_t f) { return Hidden(f); }), out->end());
  auto it = added_of_.find(id);
  if (it != added_of_.end()) out->insert(out->end(), it->second.begin(), it->second.end());
}

void MapOverlay::AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                                        std::vector<int64_t>* out) const {
  const size_t start = out->size();
  base_.AppendPassageFactorIds(vehicle_id, passage_id, out);
  out->erase(std::remove_if(out->begin() + start, out->end(), [&](int64_t f) { return Hidden(f); }), out->end());
  for (const auto& [id, factor] : delta_.added_factors) {
    if (factor.vehicle_id == vehicle_id && factor.passage_id == passage_id) out->push_back(id);
  }
}

void MapOverlay::PutLandmark(const Landmark& landmark) {
  delta_.landmarks[landmark.id] = landmark;
  auto& removed = delta_.removed_landmarks;
  removed.erase(std::remove(removed.begin(), removed.end(), landmark.id), removed.end());
}

void MapOverlay::RemoveLandmark(LandmarkId id) {
  delta_.landmarks.erase(id);
  delta_.removed_landmarks.push_back(id);
}

int64_t MapOverlay::AddFactor(MapFactor factor) {
  factor.id = ++last_factor_id_;
  for (LandmarkId landmark : factor.landmarks) added_of_[landmark].push_back(factor.id);
  change_.Add(factor, +1);
  const int64_t id = factor.id;
  delta_.added_factors.emplace(id, std::move(factor));
  return id;
}

void MapOverlay::RemoveFactor(int64_t id) {
  auto it = delta_.added_factors.find(id);
  if (it != delta_.added_factors.end()) {
    change_.Add(it->second, -1);
    for (LandmarkId landmark : it->second.landmarks) {
      std::vector<int64_t>& ids = added_of_[landmark];
      ids.erase(std::remove(ids.begin(), ids.end(), id), ids.end());
    }
    delta_.added_factors.erase(it);
    return;
  }
  const MapFactor* factor = base_.FindFactor(id);
  if (factor == nullptr || folded_.count(id) > 0 || !removed_.insert(id).second) return;
  change_.Add(*factor, -1);
  delta_.removed_factors.push_back(id);
}

namespace {

absl::Status CheckLandmarkRecord(const Landmark& l) {
  const auto on_globe = [](const LatLon& p) {
    return std::isfinite(p.lat_deg) && std::isfinite(p.lon_deg) && std::abs(p.lat_deg) <= 90.0 &&
           std::abs(p.lon_deg) <= 180.0;
  };
  if (!on_globe(l.position) || !on_globe(l.anchor)) {
    return absl::InternalError(absl::StrCat("landmark ", l.id, ": position not finite or off the globe"));
  }
  const Eigen::Matrix2d& c = l.cov_en_m2;
  if (!c.allFinite() || std::abs(c(0, 1) - c(1, 0)) > 1e-9 * c.cwiseAbs().maxCoeff() ||
      Eigen::LLT<Eigen::Matrix2d>(c).info() != Eigen::Success) {
    return absl::InternalError(
        absl::StrCat("landmark ", l.id, ": covariance not finite, symmetric and positive definite"));
  }
  return absl::OkStatus();
}

// `semidefinite`: also check the information's smallest eigenvalue (cubic in the factor's size).
absl::Status CheckFactorRecord(const MapFactor& f, bool semidefinite) {
  const Eigen::Index n = 2 * static_cast<Eigen::Index>(f.landmarks.size());
  if (f.information.rows() != n || f.information.cols() != n || f.information_vector.size() != n) {
    return absl::InternalError(absl::StrCat("factor ", f.id, ": information of the wrong size"));
  }
  if (!f.information.allFinite() || !f.information_vector.allFinite()) {
    return absl::InternalError(absl::StrCat("factor ", f.id, ": information not finite"));
  }
  const double scale = std::max(1.0, f.information.cwiseAbs().maxCoeff());
  if ((f.information - f.information.transpose()).cwiseAbs().maxCoeff() > 1e-9 * scale) {
    return absl::InternalError(absl::StrCat("factor ", f.id, ": information not symmetric"));
  }
  if (semidefinite && n > 0 &&
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(f.information, Eigen::EigenvaluesOnly).eigenvalues()(0) <
          -1e-9 * scale) {
    return absl::InternalError(absl::StrCat("factor ", f.id, ": information not positive semi-definite"));
  }
  return absl::OkStatus();
}

absl::Status CheckVehicleRecord(const VehicleCalibration& v) {
  if (!std::isfinite(v.camera_yaw_offset_rad) || std::abs(v.camera_yaw_offset_rad) > M_PI ||
      !std::isfinite(v.camera_yaw_variance_rad2) || !(v.camera_yaw_variance_rad2 > 0.0) ||
      !std::isfinite(v.camera_yaw_information) || !(v.camera_yaw_information > 0.0) ||
      !std::isfinite(v.camera_yaw_map_term) || v.camera_yaw_map_term < 0.0 || v.passages < 0) {
    return absl::InternalError(absl::StrCat(
        "vehicle ", v.vehicle_id,
        ": camera yaw offset not finite within +-pi, or its variance or information not positive"));
  }
  return absl::OkStatus();
}

absl::Status Prefixed(const char* prefix, const absl::Status& s) {
  return s.ok() ? s : absl::Status(s.code(), absl::StrCat(prefix, s.message()));
}

}  // namespace

absl::Status CheckDeltaInvariants(const MapDelta& delta) {
  for (const auto& [id, l] : delta.landmarks) {
    if (absl::Status s = CheckLandmarkRecord(l); !s.ok()) return Prefixed("map invariant: ", s);
  }
  for (const auto& [id, f] : delta.added_factors) {
    if (absl::Status s = CheckFactorRecord(f, /*semidefinite=*/true); !s.ok()) return Prefixed("map invariant: ", s);
  }
  for (const auto& [id, v] : delta.vehicles) {
    if (absl::Status s = CheckVehicleRecord(v); !s.ok()) return Prefixed("map invariant: ", s);
  }
  return absl::OkStatus();
}

absl::Status CheckStoredMap(const MapState& map) {
  absl::Status status;
  map.ForEachLandmark([&](const Landmark& l) {
    if (status.ok()) status = CheckLandmarkRecord(l);
  });
  map.ForEachFactor([&](const MapFactor& f) {
    if (status.ok()) status = CheckFactorRecord(f, /*semidefinite=*/false);
  });
  map.ForEachVehicle([&](const VehicleCalibration& v) {
    if (status.ok()) status = CheckVehicleRecord(v);
  });
  if (status.ok()) return status;
  return absl::DataLossError(absl::StrCat("the stored map is damaged: ", status.message()));
}

}  // namespace crowdmap
