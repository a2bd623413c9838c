#ifndef CROWDMAP_CLIENT_MAPSIM_SIMULATED_PASSAGES_H_
#define CROWDMAP_CLIENT_MAPSIM_SIMULATED_PASSAGES_H_

#include <vector>

#include "absl/status/statusor.h"
#include "core/model/passage.h"
#include "core/sim/city_scenario.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Passages 0..P-1 of a simulation and the true landmarks they see: the loop's or the city's.
struct SimulatedPassages {
  std::vector<Passage> passages;
  std::vector<TruthLandmark> landmarks;
};

// `city` null: the loop's passages (`loop`); otherwise the city's.
absl::StatusOr<SimulatedPassages> MakeSimulatedPassages(const ScenarioOptions& loop, const CityScenarioOptions* city,
                                                        int passages);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_SIMULATED_PASSAGES_H_
