#include "core/sim/faults.h"

#include <cmath>
#include <random>

#include "absl/strings/str_cat.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {

absl::Status FaultOptions::Validate() const {
  const std::pair<const char*, double> rates[] = {{"mislabel_rate", mislabel_rate},
                                                  {"multipath_rate", multipath_rate},
                                                  {"overconfident_rate", overconfident_rate},
                                                  {"bad_calibration_rate", bad_calibration_rate}};
  for (const auto& [name, rate] : rates) {
    if (!(rate >= 0.0 && rate <= 1.0)) {
      return absl::InvalidArgumentError(absl::StrCat(name, ": must lie in [0, 1], got ", rate));
    }
  }
  return absl::OkStatus();
}

InjectedFaults InjectFaults(const FaultOptions& options, int index, const LocalFrame& frame, Passage* passage) {
  InjectedFaults out;
  if (!options.any()) return out;
  std::mt19937_64 rng(SplitMix64(options.seed * 1000003ULL + static_cast<uint64_t>(index) + 0x5eed));
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const auto happens = [&](double rate) { return unit(rng) < rate; };

  for (Detection& d : passage->detections) {
    if (!happens(options.mislabel_rate)) continue;
    d.landmark_id = d.landmark_id > 1 && happens(0.5) ? d.landmark_id - 1 : d.landmark_id + 1;
    ++out.mislabelled_detections;
  }
  if (happens(options.multipath_rate) && !passage->gnss.empty()) {
    out.multipath = true;
    const double span_s = passage->gnss.back().t_s;
    const double length_s = 20.0 + 40.0 * unit(rng);
    const double start_s = unit(rng) * std::max(0.0, span_s - length_s);
    const double bearing = 2.0 * M_PI * unit(rng), size_m = 30.0 + 50.0 * unit(rng);
    const Eigen::Vector2d offset = size_m * Eigen::Vector2d(std::cos(bearing), std::sin(bearing));
    for (GnssFix& fix : passage->gnss) {
      if (fix.t_s < start_s || fix.t_s > start_s + length_s) continue;
      const LatLon moved = frame.ToGeo(frame.ToLocal(LatLon{fix.lat_deg, fix.lon_deg}) + offset);
      fix.lat_deg = moved.lat_deg;
      fix.lon_deg = moved.lon_deg;
    }
  }
  if (happens(options.overconfident_rate)) {
    out.overconfident = true;
    for (GnssFix& fix : passage->gnss) fix.cov_en_m2 /= 25.0;
  }
  if (happens(options.bad_calibration_rate)) {
    out.bad_calibration = true;
    passage->calibration.camera_yaw_rad += 3.0 * M_PI / 180.0;
    passage->calibration.wheelbase_m *= 1.15;
  }
  return out;
}

}  // namespace crowdmap
