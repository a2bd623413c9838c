#include "core/model/passage.h"

#include <cmath>
#include <string>

#include <Eigen/LU>

#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

std::string Field(const char* list, size_t i, const char* member) {
  return absl::StrCat(list, "[", i, "].", member);
}

absl::Status Invalid(const std::string& field, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(field, ": ", what));
}

absl::Status CheckFinite(const std::string& field, double v) {
  if (!std::isfinite(v)) return Invalid(field, "must be a finite number");
  return absl::OkStatus();
}

absl::Status CheckPositive(const std::string& field, double v) {
  if (!std::isfinite(v) || v <= 0.0) return Invalid(field, absl::StrCat("must be > 0, got ", v));
  return absl::OkStatus();
}

// Times are seconds since the passage start: finite, non-negative, strictly increasing.
absl::Status CheckTime(const char* list, size_t i, double t, double previous, bool strict) {
  const std::string f = Field(list, i, "t_s");
  if (!std::isfinite(t)) return Invalid(f, "must be a finite number");
  if (t < 0.0) return Invalid(f, absl::StrCat("must be >= 0, got ", t));
  if (i > 0 && (strict ? t <= previous : t < previous)) {
    return Invalid(f, absl::StrCat("time goes backwards: ", t, " after ", previous));
  }
  return absl::OkStatus();
}

absl::Status ValidateCalibration(const Calibration& c) {
  if (auto s = CheckPositive("calibration.wheelbase_m", c.wheelbase_m); !s.ok()) return s;
  for (int k = 0; k < 2; ++k) {
    if (auto s = CheckFinite("calibration.gnss_lever_arm_m", c.gnss_lever_arm_m[k]); !s.ok()) return s;
    if (auto s = CheckFinite("calibration.camera_position_m", c.camera_position_m[k]); !s.ok()) return s;
  }
  if (auto s = CheckFinite("calibration.camera_yaw_rad", c.camera_yaw_rad); !s.ok()) return s;
  if (auto s = CheckPositive("calibration.fx_px", c.fx_px); !s.ok()) return s;
  if (auto s = CheckPositive("calibration.image_width_px", c.image_width_px); !s.ok()) return s;
  if (!std::isfinite(c.cx_px) || c.cx_px < 0.0 || c.cx_px > c.image_width_px) {
    return Invalid("calibration.cx_px", absl::StrCat("must lie in [0, image_width_px], got ", c.cx_px));
  }
  return absl::OkStatus();
}

absl::Status ValidateNoise(const NoiseModel& n) {
  if (auto s = CheckPositive("noise.speed_sigma_mps", n.speed_sigma_mps); !s.ok()) return s;
  if (auto s = CheckPositive("noise.steering_sigma_rad", n.steering_sigma_rad); !s.ok()) return s;
  return CheckPositive("noise.pixel_sigma_px", n.pixel_sigma_px);
}

}  // namespace

absl::Status ValidatePassage(const Passage& p) {
  if (p.vehicle_id.empty()) return Invalid("vehicle_id", "must not be empty");
  if (p.passage_id.empty()) return Invalid("passage_id", "must not be empty");
  if (p.odometry.empty()) return Invalid("odometry", "passage has no odometry samples");
  if (p.gnss.size() < 2) return Invalid("gnss", "passage needs at least 2 GNSS fixes");
  if (p.detections.empty()) return Invalid("detections", "passage has no detections");
  if (auto s = ValidateCalibration(p.calibration); !s.ok()) return s;
  if (auto s = ValidateNoise(p.noise); !s.ok()) return s;

  for (size_t i = 0; i < p.odometry.size(); ++i) {
    const OdometrySample& o = p.odometry[i];
    if (auto s = CheckTime("odometry", i, o.t_s, i ? p.odometry[i - 1].t_s : 0.0, true); !s.ok()) return s;
    if (auto s = CheckFinite(Field("odometry", i, "speed_mps"), o.speed_mps); !s.ok()) return s;
    if (auto s = CheckFinite(Field("odometry", i, "steering_rad"), o.steering_rad); !s.ok()) return s;
    if (std::abs(o.steering_rad) >= M_PI / 2) {
      return Invalid(Field("odometry", i, "steering_rad"),
                     absl::StrCat("must lie in (-pi/2, pi/2), got ", o.steering_rad));
    }
  }
  for (size_t i = 0; i < p.gnss.size(); ++i) {
    const GnssFix& g = p.gnss[i];
    if (auto s = CheckTime("gnss", i, g.t_s, i ? p.gnss[i - 1].t_s : 0.0, true); !s.ok()) return s;
    if (!std::isfinite(g.lat_deg) || g.lat_deg < -90.0 || g.lat_deg > 90.0) {
      return Invalid(Field("gnss", i, "lat_deg"), absl::StrCat("latitude ", g.lat_deg, " outside [-90, 90]"));
    }
    if (!std::isfinite(g.lon_deg) || g.lon_deg < -180.0 || g.lon_deg > 180.0) {
      return Invalid(Field("gnss", i, "lon_deg"),
                     absl::StrCat("longitude ", g.lon_deg, " outside [-180, 180]"));
    }
    const Eigen::Matrix2d& c = g.cov_en_m2;
    if (!c.allFinite() || std::abs(c(0, 1) - c(1, 0)) > 1e-9 * (std::abs(c(0, 0)) + std::abs(c(1, 1))) ||
        c(0, 0) <= 0.0 || c(1, 1) <= 0.0 || c.determinant() <= 0.0) {
      return Invalid(Field("gnss", i, "cov_en_m2"), "must be a finite, symmetric, positive-definite 2x2 matrix");
    }
  }
  for (size_t i = 0; i < p.detections.size(); ++i) {
    const Detection& d = p.detections[i];
    if (auto s = CheckTime("detections", i, d.t_s, i ? p.detections[i - 1].t_s : 0.0, false); !s.ok()) return s;
    if (!std::isfinite(d.u_px) || d.u_px < 0.0 || d.u_px > p.calibration.image_width_px) {
      return Invalid(Field("detections", i, "u_px"),
                     absl::StrCat("pixel ", d.u_px, " outside the image [0, ", p.calibration.image_width_px, "]"));
    }
  }
  return absl::OkStatus();
}

}  // namespace crowdmap
