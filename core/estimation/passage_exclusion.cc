#include "core/estimation/passage_exclusion.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <set>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/estimation/landmark_update.h"

namespace crowdmap {

double ConditionalSigmaM(const MapReaderInterface& map, LandmarkId id) {
  const double weakest = Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(map.Information(id, id).value).eigenvalues()(0);
  return weakest > 0.0 ? 1.0 / std::sqrt(weakest) : INFINITY;
}

absl::StatusOr<std::vector<LandmarkId>> ExcludePassage(const std::string& vehicle_id, const std::string& passage_id,
                                                       const MapUpdateOptions& options, double max_left_sigma_m,
                                                       MapOverlay* map, PassageUpdateSummary* summary) {
  MapOverlay& overlay = *map;
  std::vector<int64_t> factor_ids;
  overlay.AppendPassageFactorIds(vehicle_id, passage_id, &factor_ids);
  if (factor_ids.empty()) {
    return absl::NotFoundError(absl::StrCat("passage ", vehicle_id, "/", passage_id,
                                            ": no factor of it in the map (or folded into the map's base)"));
  }
  std::set<LandmarkId> touched;
  for (int64_t id : factor_ids) {
    const MapFactor* f = overlay.FindFactor(id);
    touched.insert(f->landmarks.begin(), f->landmarks.end());
  }
  for (int64_t id : factor_ids) overlay.RemoveFactor(id);

  std::vector<LandmarkId> left;
  for (LandmarkId id : touched) {
    if (overlay.Information(id, id).factors == 0) {  // no factor, folded or kept, left on it
      overlay.RemoveLandmark(id);
      continue;
    }
    // What is left must still fix the landmark (even with every other landmark known: this is its
    // conditional information); a ray or two from other passages would leave it free along them.
    if (const double sigma_m = ConditionalSigmaM(overlay, id); !(sigma_m <= max_left_sigma_m)) {
      return absl::FailedPreconditionError(absl::StrFormat(
          "landmark %d would be left undetermined without passage %s/%s (sigma %.3g m along its weakest "
          "direction, over %.3g m allowed)",
          id, vehicle_id, passage_id, sigma_m, max_left_sigma_m));
    }
    left.push_back(id);
  }
  const int64_t version = overlay.BumpVersion();
  MapWindowOptions window;
  window.hops = options.strategy == UpdateStrategy::kDecorrelated ? 1 : options.window_hops;
  auto touch = [](Landmark* record) { record->passages_seen = std::max<int64_t>(0, record->passages_seen - 1); };
  if (!left.empty()) {
    MarginalRefresh refresh;
    refresh.others = true;  // information was removed: every marginal in the window grows
    absl::StatusOr<int> conditioned = ResolveAround(left, refresh, window, version, touch, &overlay);
    if (!conditioned.ok()) return conditioned.status();
    summary->landmarks_conditioned += *conditioned;
  }
  summary->landmarks_updated += static_cast<int>(left.size());
  summary->landmarks_removed += static_cast<int>(touched.size() - left.size());
  summary->map_version = version;
  return left;
}

absl::StatusOr<PassageUpdate> ComputePassageExclusion(const std::string& vehicle_id, const std::string& passage_id,
                                                      const MapUpdateOptions& options, const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  MapOverlay overlay(map);
  PassageUpdate out;
  // What is left must fix each landmark as well as a new one has to be.
  absl::StatusOr<std::vector<LandmarkId>> left = ExcludePassage(
      vehicle_id, passage_id, options, options.max_new_landmark_ray_sigma_m, &overlay, &out.summary);
  if (!left.ok()) return left.status();
  out.delta = overlay.TakeDelta();
  if (absl::Status s = CheckDeltaInvariants(out.delta); !s.ok()) return s;
  out.summary.total_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace crowdmap
