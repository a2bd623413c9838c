#ifndef CROWDMAP_CORE_SIM_CITY_OPTIONS_H_
#define CROWDMAP_CORE_SIM_CITY_OPTIONS_H_

#include <cstdint>

#include "absl/status/status.h"
#include "core/geo/local_frame.h"
#include "core/model/passage.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// The city scenario (see CityScenario): a street grid with buildings, landmarks along the streets
// and a fleet driving random partial routes through it.
struct CityScenarioOptions {
  // --- Street grid (the layout depends only on these and layout_seed) ---
  int blocks_x = 6;                 // blocks from west to east
  int blocks_y = 6;                 // blocks from south to north
  double block_m = 150.0;           // nominal distance between neighbouring street centrelines
  double street_jitter_m = 3.0;     // each street's centreline is moved by up to this, per layout
  double road_width_m = 10.0;       // carriageway, kerb to kerb; vehicles keep right
  double building_setback_m = 8.0;  // kerb to facade; must exceed landmark_kerb_offset_max_m
  LatLon origin{45.76, 4.84};       // WGS84 position of the nominal south-west intersection
  uint64_t layout_seed = 1;
  // Landmarks stand on both sides of every street, this far apart along it (uniform)...
  double spacing_min_m = 8.0;
  double spacing_max_m = 40.0;
  // ...this far beyond the kerb (uniform)...
  double landmark_kerb_offset_min_m = 2.0;
  double landmark_kerb_offset_max_m = 6.0;
  // ...and at least this far from the kerb of a crossing street.
  double corner_clearance_m = 3.0;

  // --- Fleet: passage i is driven by vehicle i % vehicles and drawn from (seed, i) only ---
  uint64_t seed = 1;
  int vehicles = 20;
  double route_length_m = 2000.0;  // distance driven per passage
  double speed_min_mps = 8.0;      // cruise speed of a passage, uniform in [min, max]
  double speed_max_mps = 14.0;
  double turn_speed_mps = 5.0;     // speed through a turn at an intersection
  double max_steering_rad = 0.6;
  // A district mapped late: the fleet drives the city's eastern late_blocks_x blocks only from
  // passage late_from_passage on (before, its routes stay on the streets west of them), as a new
  // part of town that the map first sees on day 300. 0 = the whole grid from the first passage.
  int late_blocks_x = 0;
  int late_from_passage = 0;
  // Each vehicle's sensor rates are those below times a factor drawn in [1 - x, 1 + x]. 0 = off.
  double rate_variation = 0.0;
  // Traffic: before each intersection of its route the vehicle stops (a red light, a give-way)
  // with this probability, standing still for a time uniform in [stop_min_s, stop_max_s]. 0 = never.
  double stop_probability = 0.0;
  double stop_min_s = 5.0;
  double stop_max_s = 40.0;
  // A GNSS outage (an underpass, an urban canyon): with this probability a passage has no fix for a
  // time uniform in [gnss_outage_min_s, gnss_outage_max_s], placed at random inside the passage
  // (its first and last 10 s keep their fixes). 0 = never.
  double gnss_outage_probability = 0.0;
  double gnss_outage_min_s = 10.0;
  double gnss_outage_max_s = 60.0;

  // --- Sensors ---
  NoiseConfig noise = NoiseConfig::kWhite;
  double odometry_rate_hz = 25.0;
  double gnss_rate_hz = 1.0;
  double camera_rate_hz = 2.0;
  double gnss_sigma_m = 10.0;
  double gnss_ar1_alpha = 0.988;          // with noise gnss-ar1 and ar1+yaw
  double camera_yaw_bias_rad = 0.009;     // with noise yaw-bias and ar1+yaw, the same on every vehicle
  double vehicle_yaw_bias_sigma_rad = 0.0;  // each vehicle's own camera yaw error, Gaussian; 0 = off
  // Each vehicle's wheel-speed scale error (tyre radius, pressure, wear): its encoders report the
  // speed times 1 + this sigma times a Gaussian draw. 0 = off.
  double vehicle_speed_scale_sigma = 0.0;
  // Each vehicle declares its own calibration (VariedCalibration): camera, its mount, the GNSS
  // antenna and the wheelbase differ from one vehicle to the next, as in a fleet of several car
  // models. false = every vehicle declares `calibration`.
  bool vary_calibration = false;
  double min_detection_range_m = 5.0;
  double max_detection_range_m = 50.0;
  bool occlusion = true;  // buildings hide the landmarks behind them
  Calibration calibration;  // true calibration (and what the vehicles report)
  NoiseModel noise_model;   // sigmas declared in the uploaded passages (and drawn, times undeclared_noise)
  UndeclaredNoiseScales undeclared_noise;

  // InvalidArgument naming the first bad field, e.g. "block_m: ...".
  absl::Status Validate() const;
};

// The spread of vary_calibration, each figure drawn uniformly per vehicle (in place of
// `calibration`'s): a 1280-2560 px wide image with a 50-110 degree horizontal field of view, its
// principal point off centre by up to 3% of the width; the camera 0.5-2.5 m ahead of the rear axle
// and up to 0.5 m to either side, its axis up to 5 degrees off the vehicle's; the GNSS antenna
// 0.5 m behind to 2 m ahead of the rear axle and up to 0.5 m to either side; a wheelbase of
// 2.4-3.2 m.
struct CalibrationSpread {
  static constexpr double kRadPerDegree = 3.14159265358979323846 / 180.0;
  double image_width_min_px = 1280.0, image_width_max_px = 2560.0;
  double fov_min_rad = 50.0 * kRadPerDegree, fov_max_rad = 110.0 * kRadPerDegree;
  double principal_point_offset_max = 0.03;  // of the image width
  double camera_x_min_m = 0.5, camera_x_max_m = 2.5, camera_y_max_m = 0.5;
  double camera_yaw_max_rad = 5.0 * kRadPerDegree;
  double antenna_x_min_m = -0.5, antenna_x_max_m = 2.0, antenna_y_max_m = 0.5;
  double wheelbase_min_m = 2.4, wheelbase_max_m = 3.2;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_CITY_OPTIONS_H_
