#ifndef CROWDMAP_CORE_SIM_FAULTS_H_
#define CROWDMAP_CORE_SIM_FAULTS_H_

// Faults a real fleet's uploads carry, injected into simulated passages: the inputs the map's
// trust rules (safe landmark creation, the disagreement gate, the consistency test) must survive.

#include <cstdint>

#include "absl/status/status.h"
#include "core/geo/local_frame.h"
#include "core/model/passage.h"

namespace crowdmap {

// Each rate is a probability, drawn independently per passage (or per detection) from (seed,
// passage index): the same passage gets the same faults in every run.
struct FaultOptions {
  uint64_t seed = 1;
  // Per detection: reported under the id of the landmark next to it (id + 1 or id - 1), as a
  // detector that confuses two poles would.
  double mislabel_rate = 0.0;
  // Per passage: a GNSS multipath burst, 20 to 60 s during which every fix is off by the same 30
  // to 80 m, with its declared covariance unchanged.
  double multipath_rate = 0.0;
  // Per passage: GNSS covariances declared 25 times too small (sigma 5 times too small).
  double overconfident_rate = 0.0;
  // Per passage: a garbage calibration declared: camera yaw off by 3 degrees and wheelbase by 15%.
  double bad_calibration_rate = 0.0;

  bool any() const {
    return mislabel_rate > 0.0 || multipath_rate > 0.0 || overconfident_rate > 0.0 || bad_calibration_rate > 0.0;
  }
  // InvalidArgument naming the first rate outside [0, 1].
  absl::Status Validate() const;
};

// What InjectFaults did to one passage.
struct InjectedFaults {
  int mislabelled_detections = 0;
  bool multipath = false;
  bool overconfident = false;
  bool bad_calibration = false;

  bool any() const { return mislabelled_detections > 0 || multipath || overconfident || bad_calibration; }
};

// Applies the faults drawn for passage `index` to `passage`; `frame` is the frame its GNSS fixes
// are simulated in (offsets are applied there).
InjectedFaults InjectFaults(const FaultOptions& options, int index, const LocalFrame& frame, Passage* passage);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_FAULTS_H_
