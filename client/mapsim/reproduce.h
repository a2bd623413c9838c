#ifndef CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_
#define CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_

#include <string>

#include "absl/status/status.h"
#include "core/estimation/map_update_options.h"

namespace crowdmap {

struct ReproduceOptions {
  std::string out_dir = "out/reproduce";
  int passages = 1000;
  int jobs = 2;        // experiments run in parallel
  uint64_t seed = 1;   // the first seed
  int seeds = 3;       // every experiment runs with seeds seed, seed+1, ..., seed+seeds-1
  // The CC and CC+GSD cells of table 5.2 (where consistency is judged) take further seeds until
  // the standard deviation their mean NEES would have if the maps were consistent is at most this,
  // or they have max_seeds. One run's NEES is a draw of few degrees of freedom (about 0.5 at 4
  // landmarks, 0.3 at 25-100), so a mean over few seeds cannot tell 1.0 from 1.4. 0: no more seeds.
  double nees_sd_target = 0.2;
  int max_seeds = 20;
  // Detections used per landmark and passage in every experiment (MapUpdateOptions's; 0 = all).
  int detections_per_landmark = MapUpdateOptions().detections_per_landmark;

  // InvalidArgument naming the first field out of range.
  absl::Status Validate() const;
};

// Runs the thesis's table 5.2 grid (N in {4,25,50,75,100} x {cc, dc, cc-gsd}, white noise) and its
// robustness grid (N=50, cc-gsd, four noise configurations; again with the camera yaw estimated,
// and a fleet of vehicles with their own yaw errors) for each seed (and the further seeds
// of nees_sd_target), each experiment into its own folder, and writes OUT/reproduction.md with our
// figures (means over the seeds) beside the thesis's.
absl::Status RunReproduction(const ReproduceOptions& options);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_
