#ifndef CROWDMAP_CORE_MAP_MAP_STATE_H_
#define CROWDMAP_CORE_MAP_MAP_STATE_H_

#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"

#include "core/geo/local_frame.h"
#include "core/model/passage.h"

namespace crowdmap {

enum class LandmarkState { kActive = 1 };

// A mapped landmark. Its estimate is an East/North offset from a fixed anchor (its first
// position): the variables of the map's factors. Its covariance is the marginal, in metres^2 in
// the East/North frame at the anchor (which differs from the frame at the position by a rotation
// of offset / earth radius, under 1e-5 rad for any offset the map can hold).
struct Landmark {
  LandmarkId id = 0;
  LatLon anchor;
  LatLon position;
  Eigen::Matrix2d cov_en_m2 = Eigen::Matrix2d::Identity();
  int64_t version = 0;          // map version that last changed it
  int64_t passages_seen = 0;    // passages that detected it
  int64_t last_seen_unix_ms = 0;
  LandmarkState state = LandmarkState::kActive;

  // East/North offset (m) of the position from the anchor.
  Eigen::Vector2d Offset() const { return EastNorthOffset(anchor, position); }
};

// One Gaussian factor on a few landmarks: the information a (sub)graph of one passage brought
// about them once its poses were eliminated. With d the landmarks' offsets from their anchors
// (East, North, metres; stacked in `landmarks` order), it adds
//   1/2 d^T information d - information_vector^T d
// to the map's negative log-likelihood. The map's information is the sum of its factors.
struct MapFactor {
  int64_t id = 0;                   // unique in the map
  std::string vehicle_id;           // provenance: the passage it came from
  std::string passage_id;
  std::vector<LandmarkId> landmarks;
  Eigen::MatrixXd information;      // 2k x 2k, symmetric positive semi-definite
  Eigen::VectorXd information_vector;  // 2k
};

// A vehicle's camera yaw calibration as its passages estimated it (docs/estimation.md, "Per-vehicle
// camera calibration"): the offset to add to the camera yaw its passages declare, and its
// variance, the posterior after its last passage (the prior of its next).
struct VehicleCalibration {
  std::string vehicle_id;
  double camera_yaw_offset_rad = 0.0;
  double camera_yaw_variance_rad2 = 0.0;
  // Its two parts (core/estimation/vehicle_calibration.h, ConsiderCameraYawSolve): the information
  // of the prior and of the solves' own measurements (1/rad^2), and the weighted sum of their
  // map-borne errors' covariances (1/rad^2).
  double camera_yaw_information = 0.0;
  double camera_yaw_map_term = 0.0;
  int64_t passages = 0;         // passages that estimated it
  int64_t version = 0;          // map version that last changed it
  int64_t updated_unix_ms = 0;  // start time of the last passage that changed it
};

// One 2x2 block (a, b) of the map's information matrix: the sum of its factors' blocks, rows in
// a's offsets, columns in b's.
struct InformationBlock {
  // Unaligned: a map's rows hold millions of blocks, and a 16-byte aligned Matrix2d would pad
  // each LinkedBlock from 48 to 64 bytes (210 MB at 100k landmarks).
  Eigen::Matrix<double, 2, 2, Eigen::DontAlign> value = Eigen::Matrix2d::Zero();
  int factors = 0;  // factors contributing to it; 0 = the block is structurally zero
};

// One stored block of a row of the information: (row landmark, `id`).
struct LinkedBlock {
  LandmarkId id = 0;
  InformationBlock block;
};
// A row of the information: its blocks in increasing id order (the diagonal included), contiguous
// so that a window's assembly reads it without chasing pointers.
using InformationRow = std::vector<LinkedBlock>;

// Read access to a map: landmarks, the factors that define its information, the information
// matrix and vector they sum to (kept assembled, sparse), and its version.
class MapReaderInterface {
 public:
  virtual ~MapReaderInterface() = default;
  virtual const Landmark* FindLandmark(LandmarkId id) const = 0;
  // Block (a, b) of the information matrix; a == b is the landmark's own block.
  virtual InformationBlock Information(LandmarkId a, LandmarkId b) const = 0;
  virtual Eigen::Vector2d InformationVector(LandmarkId id) const = 0;
  // Calls fn(b, block (id, b)) for every other landmark b that shares information with `id`, in
  // increasing order of b.
  virtual void ForEachLink(LandmarkId id,
                           const std::function<void(LandmarkId, const InformationBlock&)>& fn) const = 0;
  // Row `id` of the information, the diagonal block included, where the map keeps it assembled
  // (an empty row for a landmark without information); nullptr where it does not, which
  // ForEachLink and Information then read. The whole row at once, for the loops over a window's
  // links, where a call per link costs as much as the rest of the visit.
  virtual const InformationRow* InformationRowOf(LandmarkId /*id*/) const { return nullptr; }
  // Calls fn(b, block (id, b)) for every other landmark b that shares information with `id`, in
  // increasing order of b, and returns the diagonal block (id, id): InformationRowOf's row, or
  // ForEachLink and Information.
  template <typename Fn>
  InformationBlock VisitRow(LandmarkId id, Fn&& fn) const {
    const InformationRow* row = InformationRowOf(id);
    if (row == nullptr) {
      ForEachLink(id, fn);
      return Information(id, id);
    }
    InformationBlock diagonal;
    for (const LinkedBlock& e : *row) {
      if (e.id == id) {
        diagonal = e.block;
      } else {
        fn(e.id, e.block);
      }
    }
    return diagonal;
  }
  // Appends the other landmarks that share information with `id` (each once).
  void AppendLinked(LandmarkId id, std::vector<LandmarkId>* out) const {
    VisitRow(id, [out](LandmarkId b, const InformationBlock&) { out->push_back(b); });
  }
  virtual const MapFactor* FindFactor(int64_t id) const = 0;
  // Appends the landmarks of factor `id`, FindFactor(id)->landmarks, without reading its
  // information; false (nothing appended) when there is no such factor.
  virtual bool AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const {
    const MapFactor* f = FindFactor(id);
    if (f == nullptr) return false;
    out->insert(out->end(), f->landmarks.begin(), f->landmarks.end());
    return true;
  }
  // Appends the ids of the factors on landmark `id`.
  virtual void AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const = 0;
  // Appends the ids of the factors that came from one passage.
  virtual void AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                                      std::vector<int64_t>* out) const = 0;
  // Largest factor id ever used (ids are not reused, also after a removal).
  virtual int64_t last_factor_id() const = 0;
  virtual int64_t version() const = 0;
  // The vehicle's camera calibration; nullptr when none of its passages estimated one.
  virtual const VehicleCalibration* FindVehicle(const std::string& vehicle_id) const = 0;
  // Calls fn for every vehicle's calibration, in increasing vehicle_id.
  virtual void ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const = 0;
};

// The information matrix and vector that a set of factors sums to, as sparse 2x2 blocks.
class AssembledInformation {
 public:
  // A difference (of added and removed factors) keeps blocks whose factor count returns to zero:
  // their values need not.
  explicit AssembledInformation(bool difference = false) : difference_(difference) {}

  // Adds (sign +1) or subtracts (sign -1) a factor.
  void Add(const MapFactor& factor, int sign);
  // Adds one block (a, b) (and its transpose at (b, a) when a != b), counted as one more factor.
  void AddBlock(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& value);
  void AddVector(LandmarkId id, const Eigen::Vector2d& value);
  // Block (a, b); zero with factors == 0 when absent.
  InformationBlock Block(LandmarkId a, LandmarkId b) const;
  Eigen::Vector2d Vector(LandmarkId id) const;
  // Calls fn(b, block) for every stored block (a, b), b != a, in increasing b.
  void ForEachLinked(LandmarkId a, const std::function<void(LandmarkId, const InformationBlock&)>& fn) const;
  // Row a; nullptr when it holds no block.
  const InformationRow* Row(LandmarkId a) const;

 private:
  std::unordered_map<LandmarkId, InformationRow> rows_;
  std::unordered_map<LandmarkId, Eigen::Vector2d> vector_;
  bool difference_;
};

// The changes one passage makes to a map; applied atomically (in memory or in one transaction).
struct MapDelta {
  int64_t base_version = 0;  // map version the delta was computed against
  int64_t version = 0;       // map version after applying it
  std::unordered_map<LandmarkId, Landmark> landmarks;  // full new records, created or changed
  std::map<int64_t, MapFactor> added_factors;          // by id
  std::vector<int64_t> removed_factors;                // ids of base factors removed
  // Ids of factors folded into the map's base: their information stays, summed with the others';
  // the factor itself, and with it the passage's provenance, is dropped (so it can no longer be
  // excluded).
  std::vector<int64_t> folded_factors;
  std::vector<LandmarkId> removed_landmarks;            // left without any factor
  std::map<std::string, VehicleCalibration> vehicles;  // full new records, by vehicle_id

  bool empty() const {
    return landmarks.empty() && added_factors.empty() && removed_factors.empty() && removed_landmarks.empty() &&
           folded_factors.empty() && vehicles.empty();
  }
};

// The invariants every committed change keeps: each landmark record it writes has a finite
// position on the globe and a finite, symmetric, positive-definite covariance; each factor it adds
// has finite, symmetric, positive semi-definite information of the right size and a finite
// information vector. Internal error naming the landmark or factor otherwise: the change must be
// refused, the map left as it was.
absl::Status CheckDeltaInvariants(const MapDelta& delta);

class MapState;
// The same checks on a whole loaded map, in time linear in its size (a factor's information is
// checked finite and symmetric, not for its eigenvalues). DataLoss naming the first damaged
// record: a service must not serve, nor update, a damaged map.
absl::Status CheckStoredMap(const MapState& map);

// In-memory map: the estimation core's map type, mirrored by the persistent store.
class MapState : public MapReaderInterface {
 public:
  const Landmark* FindLandmark(LandmarkId id) const override;
  InformationBlock Information(LandmarkId a, LandmarkId b) const override { return information_.Block(a, b); }
  Eigen::Vector2d InformationVector(LandmarkId id) const override { return information_.Vector(id); }
  void ForEachLink(LandmarkId id,
                   const std::function<void(LandmarkId, const InformationBlock&)>& fn) const override {
    information_.ForEachLinked(id, fn);
  }
  const InformationRow* InformationRowOf(LandmarkId id) const override;
  const MapFactor* FindFactor(int64_t id) const override;
  void AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const override;
  void AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                              std::vector<int64_t>* out) const override;
  int64_t last_factor_id() const override { return last_factor_id_; }
  int64_t version() const override { return version_; }
  const VehicleCalibration* FindVehicle(const std::string& vehicle_id) const override;

  size_t landmark_count() const { return landmarks_.size(); }
  size_t factor_count() const { return factors_.size(); }
  void ForEachLandmark(const std::function<void(const Landmark&)>& fn) const;
  void ForEachFactor(const std::function<void(const MapFactor&)>& fn) const;
  void ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const override;
  // Ids in increasing order.
  std::vector<LandmarkId> LandmarkIds() const;

  // Inserts or replaces records; used by the store when loading. Sets the version when larger.
  void PutLandmark(const Landmark& landmark);
  void PutFactor(MapFactor factor);
  void PutVehicle(const VehicleCalibration& vehicle) { vehicles_[vehicle.vehicle_id] = vehicle; }
  void RemoveFactor(int64_t id);
  // Drops factor `id`'s record but keeps its information in the map (see MapDelta::folded_factors).
  void FoldFactor(int64_t id);
  // Adds information folded earlier (loading a stored base): block (a, b) and its transpose.
  void PutBaseBlock(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& value) { information_.AddBlock(a, b, value); }
  void PutBaseVector(LandmarkId id, const Eigen::Vector2d& value) { information_.AddVector(id, value); }
  void RemoveLandmark(LandmarkId id) { landmarks_.erase(id); }
  void set_version(int64_t v) { version_ = v; }
  void set_last_factor_id(int64_t id) { last_factor_id_ = std::max(last_factor_id_, id); }

  // Applies a delta computed against this map's current version.
  void Apply(const MapDelta& delta);

 private:
  // Removes a factor's record from the indexes (not from information_).
  void ForgetFactor(const MapFactor& factor);

  std::unordered_map<LandmarkId, Landmark> landmarks_;
  std::unordered_map<int64_t, MapFactor> factors_;
  std::unordered_map<LandmarkId, std::vector<int64_t>> factors_of_;
  std::map<std::pair<std::string, std::string>, std::vector<int64_t>> factors_of_passage_;
  AssembledInformation information_;
  std::map<std::string, VehicleCalibration> vehicles_;
  int64_t last_factor_id_ = 0;
  int64_t version_ = 0;
};

// A map seen through pending changes: reads see `delta` over `base`; writes go to the delta.
class MapOverlay : public MapReaderInterface {
 public:
  explicit MapOverlay(const MapReaderInterface& base);

  const Landmark* FindLandmark(LandmarkId id) const override;
  InformationBlock Information(LandmarkId a, LandmarkId b) const override;
  Eigen::Vector2d InformationVector(LandmarkId id) const override;
  void ForEachLink(LandmarkId id,
                   const std::function<void(LandmarkId, const InformationBlock&)>& fn) const override;
  // The base's row where the pending changes leave it as it is; nullptr otherwise.
  const InformationRow* InformationRowOf(LandmarkId id) const override;
  const MapFactor* FindFactor(int64_t id) const override;
  bool AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const override;
  void AppendFactorIds(LandmarkId id, std::vector<int64_t>* out) const override;
  void AppendPassageFactorIds(const std::string& vehicle_id, const std::string& passage_id,
                              std::vector<int64_t>* out) const override;
  int64_t last_factor_id() const override { return last_factor_id_; }
  int64_t version() const override { return delta_.version; }
  const VehicleCalibration* FindVehicle(const std::string& vehicle_id) const override;
  void ForEachVehicle(const std::function<void(const VehicleCalibration&)>& fn) const override;

  void PutLandmark(const Landmark& landmark);
  void PutVehicle(const VehicleCalibration& vehicle) { delta_.vehicles[vehicle.vehicle_id] = vehicle; }
  // Removes a landmark (one left without factors).
  void RemoveLandmark(LandmarkId id);
  // Adds a factor under a new id; returns the id.
  int64_t AddFactor(MapFactor factor);
  // Removes a factor of the base or one added here.
  void RemoveFactor(int64_t id);
  // Folds a factor of the base into the map's base (MapDelta::folded_factors).
  void FoldFactor(int64_t id);
  // Starts the next map version; returns it.
  int64_t BumpVersion() { return ++delta_.version; }

  const MapDelta& delta() const { return delta_; }
  MapDelta TakeDelta() { return std::move(delta_); }

 private:
  const MapReaderInterface& base_;
  MapDelta delta_;
  int64_t last_factor_id_ = 0;
  // Whether a factor of the base was removed or folded here.
  bool Hidden(int64_t id) const;

  std::unordered_set<int64_t> removed_;
  std::unordered_set<int64_t> folded_;
  std::unordered_map<LandmarkId, std::vector<int64_t>> added_of_;
  AssembledInformation change_{/*difference=*/true};  // added factors minus removed ones
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_MAP_STATE_H_
