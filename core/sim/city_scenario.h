#ifndef CROWDMAP_CORE_SIM_CITY_SCENARIO_H_
#define CROWDMAP_CORE_SIM_CITY_SCENARIO_H_

#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "core/model/passage.h"
#include "core/sim/city_drive.h"
#include "core/sim/city_layout.h"
#include "core/sim/city_options.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// One vehicle of the city fleet: what differs from one vehicle to the next.
struct CityVehicle {
  int index = 0;
  std::string vehicle_id;  // "city-v<index>"
  double odometry_rate_hz = 25.0;
  double gnss_rate_hz = 1.0;
  double camera_rate_hz = 2.0;
  Calibration calibration;  // what its passages declare (CityScenarioOptions::vary_calibration)
  Calibration true_camera;  // `calibration` plus this vehicle's camera yaw error
  double speed_scale = 1.0;  // its encoders report the true speed times this
};

// A landmark a camera sees, with its true (noise-free) pixel.
struct VisibleLandmark {
  LandmarkId id = 0;
  double u_px = 0.0;
};

// A city: a street grid with buildings and landmarks along both sides of every street
// (CityLayout), and a fleet whose passages are random partial routes through it. Passage i is
// driven by vehicle i % options.vehicles and depends only on (options, i); the layout only on the
// layout options and layout_seed. Detections are those of the thesis scenario's camera (range,
// image, pixel noise) minus the landmarks hidden by a building.
class CityScenario {
 public:
  static absl::StatusOr<CityScenario> Create(const CityScenarioOptions& options);

  const CityScenarioOptions& options() const { return options_; }
  const CityLayout& layout() const { return layout_; }
  const LocalFrame& frame() const { return layout_.frame(); }
  // Landmark id k + 1 at index k; positions in the frame above.
  const std::vector<TruthLandmark>& landmarks() const { return layout_.landmarks(); }
  size_t landmark_count() const { return layout_.landmarks().size(); }

  CityVehicle Vehicle(int vehicle_index) const;
  // The true motion of passage `index` (0-based).
  CityDrive TrueDrive(int index) const;
  // Passage `index` as its vehicle would upload it: vehicle_id "city-v<k>", passage_id naming the
  // scenario ("city-p<i>-s<seed>-l<layout_seed>-g<bx>x<by>x<block_m>-r<route_m>-<noise>").
  Passage MakePassage(int index) const;
  // The same, with its true motion.
  std::pair<Passage, CityDrive> MakePassageWithTruth(int index) const;

  // Landmarks seen by `camera` from the vehicle pose `pose`: in front, within the detection
  // range, inside the image and (with options.occlusion) not behind a building. In id order.
  std::vector<VisibleLandmark> VisibleLandmarks(const Pose2& pose, const Calibration& camera) const;

 private:
  explicit CityScenario(const CityScenarioOptions& options) : options_(options), layout_(options) {}

  CityScenarioOptions options_;
  CityLayout layout_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_CITY_SCENARIO_H_
