#ifndef CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_
#define CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_

#include <string>

#include "absl/status/status.h"

namespace crowdmap {

struct ReproduceOptions {
  std::string out_dir = "out/reproduce";
  int passages = 1000;
  int jobs = 2;        // experiments run in parallel
  uint64_t seed = 1;   // the first seed
  int seeds = 3;       // every experiment runs with seeds seed, seed+1, ..., seed+seeds-1
};

// Runs the thesis's table 5.2 grid (N in {4,25,50,75,100} x {cc, dc, cc-gsd}, white noise) and its
// robustness grid (N=50, cc-gsd, four noise configurations) for each seed, each experiment into
// its own folder, and writes OUT/reproduction.md with our figures (means over the seeds) beside
// the thesis's.
absl::Status RunReproduction(const ReproduceOptions& options);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_REPRODUCE_H_
