#include "core/sim/city_options.h"

#include <cmath>
#include <string>
#include <tuple>

#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

absl::Status Invalid(const std::string& field, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(field, ": ", what));
}

absl::Status CheckPositive(const char* field, double v) {
  if (!(std::isfinite(v) && v > 0.0)) return Invalid(field, absl::StrCat("must be > 0, got ", v));
  return absl::OkStatus();
}

absl::Status CheckNonNegative(const char* field, double v) {
  if (!(std::isfinite(v) && v >= 0.0)) return Invalid(field, absl::StrCat("must be >= 0, got ", v));
  return absl::OkStatus();
}

}  // namespace

absl::Status CityScenarioOptions::Validate() const {
  if (blocks_x < 1) return Invalid("blocks_x", absl::StrCat("must be >= 1, got ", blocks_x));
  if (blocks_y < 1) return Invalid("blocks_y", absl::StrCat("must be >= 1, got ", blocks_y));
  for (const auto& [field, value] :
       {std::pair<const char*, double>{"block_m", block_m}, {"road_width_m", road_width_m},
        {"building_setback_m", building_setback_m}, {"spacing_min_m", spacing_min_m},
        {"route_length_m", route_length_m}, {"speed_min_mps", speed_min_mps}, {"turn_speed_mps", turn_speed_mps},
        {"max_steering_rad", max_steering_rad}, {"odometry_rate_hz", odometry_rate_hz},
        {"gnss_rate_hz", gnss_rate_hz}, {"camera_rate_hz", camera_rate_hz}, {"gnss_sigma_m", gnss_sigma_m},
        {"max_detection_range_m", max_detection_range_m}}) {
    if (absl::Status s = CheckPositive(field, value); !s.ok()) return s;
  }
  for (const auto& [field, value] :
       {std::pair<const char*, double>{"street_jitter_m", street_jitter_m},
        {"landmark_kerb_offset_min_m", landmark_kerb_offset_min_m}, {"corner_clearance_m", corner_clearance_m},
        {"vehicle_yaw_bias_sigma_rad", vehicle_yaw_bias_sigma_rad}, {"min_detection_range_m", min_detection_range_m},
        {"vehicle_speed_scale_sigma", vehicle_speed_scale_sigma},
        {"rate_variation", rate_variation}, {"noise_model.speed_sigma_mps", noise_model.speed_sigma_mps},
        {"noise_model.steering_sigma_rad", noise_model.steering_sigma_rad},
        {"noise_model.pixel_sigma_px", noise_model.pixel_sigma_px}}) {
    if (absl::Status s = CheckNonNegative(field, value); !s.ok()) return s;
  }
  if (!(spacing_max_m >= spacing_min_m)) {
    return Invalid("spacing_max_m", absl::StrCat("must be >= spacing_min_m (", spacing_min_m, "), got ", spacing_max_m));
  }
  if (!(landmark_kerb_offset_max_m >= landmark_kerb_offset_min_m)) {
    return Invalid("landmark_kerb_offset_max_m", "must be >= landmark_kerb_offset_min_m");
  }
  if (!(building_setback_m > landmark_kerb_offset_max_m)) {
    return Invalid("building_setback_m", absl::StrCat("must exceed landmark_kerb_offset_max_m (",
                                                      landmark_kerb_offset_max_m, ") so that no landmark stands in a "
                                                      "building, got ", building_setback_m));
  }
  // The narrowest block must still hold a building of at least a metre.
  const double building_m = block_m - 2.0 * street_jitter_m - road_width_m - 2.0 * building_setback_m;
  if (building_m < 1.0) {
    return Invalid("block_m", absl::StrCat("too small for the roads, setbacks and jitter: a building would be ",
                                           building_m, " m wide"));
  }
  if (!(speed_max_mps >= speed_min_mps)) return Invalid("speed_max_mps", "must be >= speed_min_mps");
  if (absl::Status s = undeclared_noise.Validate(); !s.ok()) return s;
  if (!(max_steering_rad < 1.2)) return Invalid("max_steering_rad", "must be < 1.2");
  // The lane's arcs through turns (see TurnRadiusM: 0.7 and 1.1 road widths) must be drivable at
  // the steering limit, and two of them must fit along the shortest block.
  const double wheelbase_m = vary_calibration ? CalibrationSpread().wheelbase_max_m : calibration.wheelbase_m;
  const double min_turn_radius_m = wheelbase_m / std::sin(max_steering_rad);
  if (!(min_turn_radius_m < 0.7 * road_width_m)) {
    return Invalid("max_steering_rad", absl::StrCat("the tightest turn it allows (", min_turn_radius_m,
                                                    " m radius) is wider than a right turn's lane (",
                                                    0.7 * road_width_m, " m)"));
  }
  if (2.2 * road_width_m > block_m - 2.0 * street_jitter_m) {
    return Invalid("block_m", "too short for two left turns in a row");
  }
  if (late_blocks_x < 0 || late_blocks_x >= blocks_x) {
    return Invalid("late_blocks_x", absl::StrCat("must lie in [0, blocks_x - 1 = ", blocks_x - 1, "], got ", late_blocks_x));
  }
  if (late_from_passage < 0) return Invalid("late_from_passage", absl::StrCat("must be >= 0, got ", late_from_passage));
  if (vehicles < 1) return Invalid("vehicles", absl::StrCat("must be >= 1, got ", vehicles));
  if (!(vehicle_speed_scale_sigma <= 0.1)) {
    return Invalid("vehicle_speed_scale_sigma", absl::StrCat("must be <= 0.1, got ", vehicle_speed_scale_sigma));
  }
  if (!(rate_variation < 0.5)) return Invalid("rate_variation", absl::StrCat("must be < 0.5, got ", rate_variation));
  for (const auto& [field, value] : {std::pair<const char*, double>{"stop_probability", stop_probability},
                                     {"gnss_outage_probability", gnss_outage_probability}}) {
    if (!(value >= 0.0 && value <= 1.0)) return Invalid(field, absl::StrCat("must lie in [0, 1], got ", value));
  }
  for (const auto& [min_field, min_s, max_field, max_s] :
       {std::tuple<const char*, double, const char*, double>{"stop_min_s", stop_min_s, "stop_max_s", stop_max_s},
        {"gnss_outage_min_s", gnss_outage_min_s, "gnss_outage_max_s", gnss_outage_max_s}}) {
    if (absl::Status s = CheckNonNegative(min_field, min_s); !s.ok()) return s;
    if (!(max_s >= min_s && max_s <= 3600.0)) {
      return Invalid(max_field, absl::StrCat("must lie in [", min_field, " = ", min_s, ", 3600], got ", max_s));
    }
  }
  if (!(gnss_ar1_alpha >= 0.0 && gnss_ar1_alpha < 1.0)) return Invalid("gnss_ar1_alpha", "must lie in [0, 1)");
  if (!std::isfinite(camera_yaw_bias_rad)) return Invalid("camera_yaw_bias_rad", "must be finite");
  if (!(max_detection_range_m > min_detection_range_m)) {
    return Invalid("max_detection_range_m", "must exceed min_detection_range_m");
  }
  if (std::abs(origin.lat_deg) > 85.0 || std::abs(origin.lon_deg) > 180.0) {
    return Invalid("origin", "latitude must lie in [-85, 85] and longitude in [-180, 180]");
  }
  if (!(calibration.wheelbase_m > 0.0)) return Invalid("calibration.wheelbase_m", "must be > 0");
  return absl::OkStatus();
}

}  // namespace crowdmap
