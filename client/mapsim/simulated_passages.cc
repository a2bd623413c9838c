#include "client/mapsim/simulated_passages.h"

namespace crowdmap {

absl::StatusOr<SimulatedPassages> MakeSimulatedPassages(const ScenarioOptions& loop, const CityScenarioOptions* city,
                                                        int passages) {
  SimulatedPassages out;
  if (city != nullptr) {
    absl::StatusOr<CityScenario> scenario = CityScenario::Create(*city);
    if (!scenario.ok()) return scenario.status();
    for (int i = 0; i < passages; ++i) out.passages.push_back(scenario->MakePassage(i));
    out.landmarks = scenario->landmarks();
    return out;
  }
  absl::StatusOr<Scenario> scenario = Scenario::Create(loop);
  if (!scenario.ok()) return scenario.status();
  for (int i = 0; i < passages; ++i) out.passages.push_back(scenario->MakePassage(i));
  out.landmarks = scenario->landmarks();
  return out;
}

}  // namespace crowdmap
