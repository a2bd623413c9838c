#include "core/estimation/passage_exclusion.h"

#include <algorithm>
#include <chrono>
#include <set>

#include "absl/strings/str_cat.h"
#include "core/estimation/landmark_update.h"

namespace crowdmap {

absl::StatusOr<PassageUpdate> ComputePassageExclusion(const std::string& vehicle_id, const std::string& passage_id,
                                                      const MapUpdateOptions& options, const MapReaderInterface& map) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  MapOverlay overlay(map);
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

  PassageUpdate out;
  std::vector<LandmarkId> seeds;
  for (LandmarkId id : touched) {
    if (overlay.Information(id, id).factors == 0) {  // no factor, folded or kept, left on it
      overlay.RemoveLandmark(id);
    } else {
      seeds.push_back(id);
    }
  }
  const int64_t version = overlay.BumpVersion();
  MapWindowOptions window;
  window.hops = options.strategy == UpdateStrategy::kDecorrelated ? 1 : options.window_hops;
  auto touch = [](Landmark* record) { record->passages_seen = std::max<int64_t>(0, record->passages_seen - 1); };
  if (!seeds.empty()) {
    MarginalRefresh refresh;
    refresh.others = true;  // information was removed: every marginal in the window grows
    absl::StatusOr<int> conditioned = ResolveAround(seeds, refresh, window, version, touch, &overlay);
    if (!conditioned.ok()) return conditioned.status();
    out.summary.landmarks_conditioned = *conditioned;
  }
  out.summary.landmarks_updated = static_cast<int>(seeds.size());
  out.summary.landmarks_removed = static_cast<int>(touched.size() - seeds.size());
  out.summary.map_version = version;
  out.delta = overlay.TakeDelta();
  if (absl::Status s = CheckDeltaInvariants(out.delta); !s.ok()) return s;
  out.summary.total_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace crowdmap
