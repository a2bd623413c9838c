#ifndef CROWDMAP_CORE_ESTIMATION_PASSAGE_EXCLUSION_H_
#define CROWDMAP_CORE_ESTIMATION_PASSAGE_EXCLUSION_H_

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/estimation/map_updater.h"
#include "core/map/map_state.h"

namespace crowdmap {

// The map change that takes back everything one passage brought: its factors are subtracted from
// the map's information, the map is re-solved around the landmarks they were on, and landmarks
// left without any information are removed. The result is the map built without the passage, up to
// the linearisation points of the other passages' factors (exact on linear problems). `map` is
// only read. NotFound when the map holds no factor of the passage (none, or all folded into the
// base: MapDelta::folded_factors); FailedPrecondition when what remains does not determine a
// landmark (nothing is changed then).
absl::StatusOr<PassageUpdate> ComputePassageExclusion(const std::string& vehicle_id, const std::string& passage_id,
                                                      const MapUpdateOptions& options, const MapReaderInterface& map);

// The same, written into `map` (counts added to `summary`). Returns the landmarks the passage's
// factors were on that are left in the map (re-solved). Refused (FailedPrecondition) when what is
// left gives one of them a standard deviation over `max_left_sigma_m` along its weakest direction
// (ConditionalSigmaM): ComputePassageExclusion allows what a new landmark is allowed
// (options.max_new_landmark_ray_sigma_m). On an error `map` is half-changed and must be dropped.
absl::StatusOr<std::vector<LandmarkId>> ExcludePassage(const std::string& vehicle_id, const std::string& passage_id,
                                                       const MapUpdateOptions& options, double max_left_sigma_m,
                                                       MapOverlay* map, PassageUpdateSummary* summary);

// The standard deviation (m) of a landmark along its weakest direction from `map`'s information on
// it with every other landmark known (its conditional information); infinite without any.
double ConditionalSigmaM(const MapReaderInterface& map, LandmarkId id);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_PASSAGE_EXCLUSION_H_
