#ifndef CROWDMAP_CLIENT_MAPSIM_SVG_PLOT_H_
#define CROWDMAP_CLIENT_MAPSIM_SVG_PLOT_H_

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "client/mapsim/experiment.h"

namespace crowdmap {

// Writes an SVG with two panels over the passages, like the thesis's figures 5.4 and 5.5: the
// mean distance error (log scale), and the mean East and North errors with their +-3 sigma bands.
absl::Status WriteErrorPlot(const std::vector<PassageRecord>& records, const std::string& title,
                            const std::string& path);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_SVG_PLOT_H_
