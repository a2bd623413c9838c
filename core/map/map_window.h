#ifndef CROWDMAP_CORE_MAP_MAP_WINDOW_H_
#define CROWDMAP_CORE_MAP_MAP_WINDOW_H_

#include <cstdint>
#include <memory>
#include <string_view>
#include <vector>

#include <Eigen/Core>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "core/map/map_state.h"

namespace crowdmap {

// How a window's covariance relates to the map's exact marginal.
enum class CovarianceBound {
  kExact,         // the window is closed: no information reaches outside it
  kConservative,  // never smaller than the exact marginal: all that reaches outside is in kept factors
  kMayBeNarrower  // information folded into the map's base reaches outside and is held there
};
const char* CovarianceBoundName(CovarianceBound bound);

struct MapWindowOptions {
  // Landmarks within this many links (a link: a factor shared by two landmarks) of the seeds are
  // estimated; the rest of the map is held at its estimate. 0 = no limit: the seeds' whole
  // connected part of the map, where estimates and covariances are exact.
  int hops = 0;
  // Solve the window for its estimate (offsets()). Off (reads of covariances), offsets() is empty
  // and a window that is not closed is factorised once instead of twice.
  bool estimate = true;

  absl::Status Validate() const;
};

// What a computation returns when a landmark or a factor that one read named is gone by the time
// it is read: a worker reads a map that other workers' commits change between its reads, and such
// a computation is discarded and made again (its read set overlaps the commit).
absl::Status RemovedWhileRead(std::string_view what, int64_t id);
// The landmark's record, or RemovedWhileRead when `map` no longer has it.
absl::StatusOr<Landmark> LandmarkStillThere(const MapReaderInterface& map, LandmarkId id);

// The map's estimate and covariance over the landmarks around some seeds, from the sparse
// information matrix of its factors (a sparse Cholesky factorisation of the window).
//   - Estimate: the window's offsets minimise the map's cost with every landmark outside held at
//     its estimate (the conditional mean; the map's own mean when the window is closed).
//   - Covariance: exact when the window is closed (no factor reaches outside it). Otherwise each
//     factor that reaches outside enters through its own marginal on the window's landmarks (its
//     Schur complement), which is no more informative than the map's: the covariance is then
//     conservative, never smaller than the exact marginal, as long as the information that
//     reaches outside is in the factors the map keeps (MapFactor records). The information of
//     folded factors (the map's base, MapDelta::folded_factors) has no factors left to
//     marginalise: where it links the window to landmarks outside, it enters held, as the
//     estimate's does, which is more informative than the exact marginal. Over a map with folded
//     passages a window that is not closed can be over-confident (map_covariance_benchmark
//     --retain-passages; docs/results.md, "Bounded windows over folded passages").
class MapWindow {
 public:
  static absl::StatusOr<MapWindow> Build(const MapReaderInterface& map, const std::vector<LandmarkId>& seeds,
                                         const MapWindowOptions& options);

  // The window's landmarks; the seeds first, in the order given.
  const std::vector<LandmarkId>& landmarks() const { return ids_; }
  // Position of `id` in landmarks(), -1 when outside the window.
  int index(LandmarkId id) const;
  bool closed() const { return closed_; }
  CovarianceBound covariance_bound() const { return bound_; }
  // Offsets from the anchors (East, North, metres), 2 per landmark in landmarks() order; empty
  // without MapWindowOptions::estimate.
  const Eigen::VectorXd& offsets() const { return offsets_; }
  // Joint covariance of `ids` (all in the window), East/North at their anchors.
  absl::StatusOr<Eigen::MatrixXd> Covariance(const std::vector<LandmarkId>& ids) const;
  // The covariance of every window landmark (landmarks() order): one dense inversion of the
  // window's information, (2n)^2 doubles; for windows small enough to keep it whole.
  absl::StatusOr<Eigen::MatrixXd> FullCovariance() const;
  // Their columns of the window's covariance: 2 rows per window landmark (landmarks() order), 2
  // columns per landmark of `ids`.
  absl::StatusOr<Eigen::MatrixXd> CovarianceColumns(const std::vector<LandmarkId>& ids) const;
  // The window's covariance columns of `ids` times `v` (2 entries per landmark of `ids`): 2 rows
  // per window landmark, in landmarks() order. One solve, where CovarianceColumns takes 2 per
  // landmark.
  absl::StatusOr<Eigen::VectorXd> CovarianceTimes(const std::vector<LandmarkId>& ids, const Eigen::VectorXd& v) const;
  // 2x2 marginal covariance of every window landmark, in landmarks() order.
  std::vector<Eigen::Matrix2d> Marginals() const;

 private:
  // Supernodal (CHOLMOD) factorisation of a window's information; opaque here so that this header
  // does not pull in CHOLMOD.
  class Factor;
  MapWindow() = default;

  std::vector<LandmarkId> ids_;
  absl::flat_hash_map<LandmarkId, int> index_;
  bool closed_ = true;
  CovarianceBound bound_ = CovarianceBound::kExact;
  Eigen::VectorXd offsets_;
  // The factorisation of the (conservative) window information.
  std::shared_ptr<const Factor> covariance_factor_;
};

// Joint covariance of `ids` in `map` (East/North at the anchors), through a MapWindow around them;
// how it relates to the exact one in `bound` when given.
absl::StatusOr<Eigen::MatrixXd> JointCovariance(const MapReaderInterface& map, const std::vector<LandmarkId>& ids,
                                                const MapWindowOptions& options = {},
                                                CovarianceBound* bound = nullptr);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_MAP_WINDOW_H_
