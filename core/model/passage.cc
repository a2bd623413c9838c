#include "core/model/passage.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/LU>
#include <openssl/evp.h>

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

// One drive, uploaded as a passage, spans at most a day from its first time to its last.
constexpr double kMaxPassageDurationS = 86400.0;
// No time of a passage lies further from its start (some 300 years: any clock's seconds pass, and
// no difference of two times overflows).
constexpr double kMaxTimeS = 1e10;
// Its start: up to 2100-01-01 (a landmark's last_seen_unix_ms is the latest of its passages', and a
// time far ahead would stay there).
constexpr int64_t kMaxStartUnixMs = 4102444800000;

// Times are seconds since the passage start: finite, non-negative, strictly increasing.
absl::Status CheckTime(const char* list, size_t i, double t, double previous, bool strict) {
  const std::string f = Field(list, i, "t_s");
  if (!std::isfinite(t)) return Invalid(f, "must be a finite number");
  if (t < 0.0) return Invalid(f, absl::StrCat("must be >= 0, got ", t));
  if (t > kMaxTimeS) return Invalid(f, absl::StrCat("must be at most ", kMaxTimeS, " s, got ", t));
  if (i > 0 && (strict ? t <= previous : t < previous)) {
    return Invalid(f, absl::StrCat(t < previous ? "time goes backwards: " : "time does not advance: ", t,
                                   " after ", previous));
  }
  return absl::OkStatus();
}

// `v` within [lo, hi] (physical bounds no road vehicle or sensor leaves).
absl::Status CheckRange(const std::string& field, double v, double lo, double hi, const char* unit) {
  if (!std::isfinite(v) || v < lo || v > hi) {
    return Invalid(field, absl::StrCat("must lie in [", lo, ", ", hi, "] ", unit, ", got ", v));
  }
  return absl::OkStatus();
}

// A camera frame (detections at one time) holds at most this many detections.
constexpr size_t kMaxDetectionsPerFrame = 1000;
// Two ids whose detections coincide to this share of the pixel sigma in at least
// kMinCoincidentFrames frames, and in at least half the frames of the one seen less, are at one
// place: one landmark reported twice, or two that stand together (a sign on its pole has the pole's
// bearing from everywhere). A few such pairs are let through; a passage in which more than
// kMaxCoincidentShare of the ids (and more than kMinCoincidentIds) repeat another id's
// detections is refused.
constexpr double kCoincidentPixelSigmas = 0.1;
constexpr int kMinCoincidentFrames = 3;
constexpr double kMaxCoincidentShare = 0.2;
constexpr size_t kMinCoincidentIds = 10;
// At most this many pairs of ids coincide in some frame.
constexpr size_t kMaxCoincidentPairs = 1000;
// No more than this many detections of one frame lie that close to one another.
constexpr size_t kMaxCoincidentDetections = 16;

// The detections name each landmark once: no frame overfull, no landmarks under several ids each
// (copied detections count their rays twice or more: one upload copying each detection 200 times
// under new ids made 3,400 landmarks).
absl::Status CheckLandmarksSeenOnce(const Passage& p) {
  const double close_px = kCoincidentPixelSigmas * p.noise.pixel_sigma_px;
  std::map<LandmarkId, int> frames;                             // per id: the frames it is seen in
  std::map<std::pair<LandmarkId, LandmarkId>, int> coincident;  // per pair of ids: the frames they coincide in
  std::vector<const Detection*> frame;
  std::set<LandmarkId> in_frame;
  std::set<std::pair<LandmarkId, LandmarkId>> pairs_in_frame;
  for (size_t begin = 0; begin < p.detections.size();) {
    size_t end = begin;
    while (end < p.detections.size() && p.detections[end].t_s == p.detections[begin].t_s) ++end;
    if (end - begin > kMaxDetectionsPerFrame) {
      return Invalid(Field("detections", begin, "t_s"),
                     absl::StrCat(end - begin, " detections at ", p.detections[begin].t_s,
                                  " s; a frame holds at most ", kMaxDetectionsPerFrame));
    }
    frame.clear();
    in_frame.clear();
    pairs_in_frame.clear();
    for (size_t i = begin; i < end; ++i) frame.push_back(&p.detections[i]);
    std::stable_sort(frame.begin(), frame.end(),
                     [](const Detection* a, const Detection* b) { return a->u_px < b->u_px; });
    for (size_t a = 0; a < frame.size(); ++a) {
      if (in_frame.insert(frame[a]->landmark_id).second) ++frames[frame[a]->landmark_id];
      for (size_t b = a + 1; b < frame.size() && frame[b]->u_px - frame[a]->u_px <= close_px; ++b) {
        // (which also bounds this loop's work on a hostile frame)
        if (b - a >= kMaxCoincidentDetections) {
          return Invalid(Field("detections", static_cast<size_t>(frame[b] - p.detections.data()), "u_px"),
                         absl::StrCat("more than ", kMaxCoincidentDetections, " detections at ", frame[b]->t_s,
                                      " s within ", close_px, " px of one another"));
        }
        const auto [lo, hi] = std::minmax(frame[a]->landmark_id, frame[b]->landmark_id);
        if (lo != hi && pairs_in_frame.insert({lo, hi}).second) ++coincident[{lo, hi}];
      }
    }
    // Honest data has a handful of such pairs; this bounds the memory a hostile passage takes here.
    if (coincident.size() > kMaxCoincidentPairs) {
      return Invalid(Field("detections", begin, "u_px"),
                     absl::StrCat("more than ", kMaxCoincidentPairs, " pairs of landmark ids seen within ", close_px,
                                  " px of one another by ", p.detections[begin].t_s, " s"));
    }
    begin = end;
  }
  std::set<LandmarkId> repeating;  // the second id of each pair at one place
  std::pair<LandmarkId, LandmarkId> first_pair;
  for (const auto& [ids, count] : coincident) {
    if (count < kMinCoincidentFrames || 2 * count < std::min(frames[ids.first], frames[ids.second])) continue;
    if (repeating.empty()) first_pair = ids;
    repeating.insert(ids.second);
  }
  if (repeating.size() <= std::max(kMinCoincidentIds, static_cast<size_t>(kMaxCoincidentShare * frames.size()))) {
    return absl::OkStatus();
  }
  return Invalid("detections",
                 absl::StrCat(repeating.size(), " of the passage's ", frames.size(),
                              " landmark ids are seen at the pixel of another (within ", close_px,
                              " px, in at least ", kMinCoincidentFrames, " frames and half of those of the one seen "
                              "less; e.g. landmarks ", first_pair.first, " and ", first_pair.second,
                              "): the same landmarks under several ids"));
}

}  // namespace

absl::Status ValidateId(const char* field, const std::string& id) {
  if (id.empty()) return Invalid(field, "must not be empty");
  if (id.size() > kMaxIdLength) {
    return Invalid(field, absl::StrCat("must be at most ", kMaxIdLength, " characters, got ", id.size()));
  }
  for (unsigned char c : id) {
    if (c < 0x21 || c > 0x7e) {
      return Invalid(field, absl::StrCat("must be printable ASCII without spaces; character ", static_cast<int>(c),
                                         " is not"));
    }
  }
  return absl::OkStatus();
}

namespace {

// Physical bounds of the rules below.
constexpr double kMaxSpeedMps = 100.0;         // 360 km/h
constexpr double kMaxReverseSpeedMps = 15.0;
constexpr double kMaxSteeringRad = 1.0;        // about 57 degrees at the wheel
constexpr double kMaxAbsLatitudeDeg = 85.0;    // the map's East/North frames degenerate at the poles
constexpr double kMaxMountOffsetM = 20.0;      // lever arm and camera position from the rear axle

// Measurement times may run past the last odometry sample by this much (rates differ).
constexpr double kTimeSlackS = 1.0;

// Two consecutive fixes no further apart than the vehicle can drive in between, plus five sigmas
// of each and 50 m: a jump across the globe, or a fix from another passage, is not a GNSS error.
absl::Status CheckGnssStep(const GnssFix& a, const GnssFix& b, size_t i) {
  constexpr double kEarthRadiusM = 6371000.0;
  constexpr double kDeg = M_PI / 180.0;
  double dlon = b.lon_deg - a.lon_deg;
  dlon -= 360.0 * std::round(dlon / 360.0);  // across the antimeridian the short way
  const double east = dlon * kDeg * std::cos(0.5 * (a.lat_deg + b.lat_deg) * kDeg) * kEarthRadiusM;
  const double north = (b.lat_deg - a.lat_deg) * kDeg * kEarthRadiusM;
  const double sigmas = std::sqrt(a.cov_en_m2.trace()) + std::sqrt(b.cov_en_m2.trace());
  const double limit = kMaxSpeedMps * (b.t_s - a.t_s) + 5.0 * sigmas + 50.0;
  const double distance = std::hypot(east, north);
  if (distance > limit) {
    return Invalid(absl::StrCat("gnss[", i, "]"),
                   absl::StrCat("fix ", distance, " m from the previous one after ", b.t_s - a.t_s,
                                " s: more than driving at ", kMaxSpeedMps, " m/s and five sigmas allow (", limit, " m)"));
  }
  return absl::OkStatus();
}

absl::Status ValidateCalibration(const Calibration& c) {
  if (auto s = CheckRange("calibration.wheelbase_m", c.wheelbase_m, 0.5, 20.0, "m"); !s.ok()) return s;
  for (int k = 0; k < 2; ++k) {
    const char* axis = k == 0 ? ".x_m" : ".y_m";
    if (auto s = CheckRange(absl::StrCat("calibration.gnss_lever_arm_m", axis), c.gnss_lever_arm_m[k], -kMaxMountOffsetM,
                            kMaxMountOffsetM, "m");
        !s.ok()) {
      return s;
    }
    if (auto s = CheckRange(absl::StrCat("calibration.camera_position_m", axis), c.camera_position_m[k],
                            -kMaxMountOffsetM, kMaxMountOffsetM, "m");
        !s.ok()) {
      return s;
    }
  }
  if (auto s = CheckRange("calibration.camera_yaw_rad", c.camera_yaw_rad, -M_PI, M_PI, "rad"); !s.ok()) return s;
  if (auto s = CheckRange("calibration.fx_px", c.fx_px, 10.0, 1e5, "px"); !s.ok()) return s;
  if (auto s = CheckRange("calibration.image_width_px", c.image_width_px, 16.0, 1e5, "px"); !s.ok()) return s;
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
  // No wheel encoder is worse than this and still worth declaring (a steering sigma of a radian
  // says the wheels point anywhere; tens of radians made the preintegration's covariance NaN).
  if (auto s = CheckRange("noise.speed_sigma_mps", n.speed_sigma_mps, 0.0, 10.0, "m/s"); !s.ok()) return s;
  if (auto s = CheckRange("noise.steering_sigma_rad", n.steering_sigma_rad, 0.0, 0.5, "rad"); !s.ok()) return s;
  // From a hundredth of a pixel (no detector of a pole or sign is surer) to a thousand.
  if (auto s = CheckRange("noise.pixel_sigma_px", n.pixel_sigma_px, 0.01, 1000.0, "px"); !s.ok()) return s;
  // Up to a day: a longer correlation is a constant bias over any drive.
  if (auto s = CheckRange("noise.gnss_correlation_time_s", n.gnss_correlation_time_s, 0.0, 86400.0, "s"); !s.ok()) {
    return s;
  }
  return CheckRange("noise.gnss_process_sigma_m", n.gnss_process_sigma_m, 0.0, 1000.0, "m");
}

}  // namespace

absl::Status ValidatePassage(const Passage& p) {
  if (auto s = ValidateId("vehicle_id", p.vehicle_id); !s.ok()) return s;
  if (auto s = ValidateId("passage_id", p.passage_id); !s.ok()) return s;
  if (p.odometry.empty()) return Invalid("odometry", "passage has no odometry samples");
  if (p.gnss.size() < 2) return Invalid("gnss", "passage needs at least 2 GNSS fixes");
  if (p.detections.empty()) return Invalid("detections", "passage has no detections");
  if (auto s = ValidateCalibration(p.calibration); !s.ok()) return s;
  if (auto s = ValidateNoise(p.noise); !s.ok()) return s;
  if (p.start_time_unix_ms < 0 || p.start_time_unix_ms > kMaxStartUnixMs) {
    return Invalid("start_time_unix_ms", absl::StrCat("must lie in [0, ", kMaxStartUnixMs,
                                                      "] (up to the year 2100), got ", p.start_time_unix_ms));
  }

  for (size_t i = 0; i < p.odometry.size(); ++i) {
    const OdometrySample& o = p.odometry[i];
    if (auto s = CheckTime("odometry", i, o.t_s, i ? p.odometry[i - 1].t_s : 0.0, true); !s.ok()) return s;
    if (auto s = CheckRange(Field("odometry", i, "speed_mps"), o.speed_mps, -kMaxReverseSpeedMps, kMaxSpeedMps, "m/s");
        !s.ok()) {
      return s;
    }
    if (auto s = CheckRange(Field("odometry", i, "steering_rad"), o.steering_rad, -kMaxSteeringRad, kMaxSteeringRad,
                            "rad");
        !s.ok()) {
      return s;
    }
  }
  for (size_t i = 0; i < p.gnss.size(); ++i) {
    const GnssFix& g = p.gnss[i];
    if (auto s = CheckTime("gnss", i, g.t_s, i ? p.gnss[i - 1].t_s : 0.0, true); !s.ok()) return s;
    if (!std::isfinite(g.lat_deg) || std::abs(g.lat_deg) > kMaxAbsLatitudeDeg) {
      return Invalid(Field("gnss", i, "lat_deg"),
                     absl::StrCat("latitude ", g.lat_deg, " outside [-", kMaxAbsLatitudeDeg, ", ", kMaxAbsLatitudeDeg,
                                  "] (no road the map can hold)"));
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
    const double min_variance = kMinGnssSigmaM * kMinGnssSigmaM, max_variance = kMaxGnssSigmaM * kMaxGnssSigmaM;
    if (c(0, 0) < min_variance || c(0, 0) > max_variance || c(1, 1) < min_variance || c(1, 1) > max_variance) {
      return Invalid(Field("gnss", i, "cov_en_m2"),
                     absl::StrCat("East and North variances must lie in [", min_variance, ", ", max_variance,
                                  "] m^2 (sigmas of ", kMinGnssSigmaM, " to ", kMaxGnssSigmaM, " m), got ", c(0, 0),
                                  " and ", c(1, 1)));
    }
    if (g.lat_deg == 0.0 && g.lon_deg == 0.0) {
      return Invalid(absl::StrCat("gnss[", i, "]"), "(0, 0) is what a receiver without a fix reports; leave such fixes out");
    }
    if (i > 0) {
      if (auto s = CheckGnssStep(p.gnss[i - 1], g, i); !s.ok()) return s;
    }
  }
  const double odometry_end_s = p.odometry.back().t_s;
  for (size_t i = 0; i < p.detections.size(); ++i) {
    const Detection& d = p.detections[i];
    if (auto s = CheckTime("detections", i, d.t_s, i ? p.detections[i - 1].t_s : 0.0, false); !s.ok()) return s;
    if (d.t_s > odometry_end_s + kTimeSlackS) {
      return Invalid(Field("detections", i, "t_s"),
                     absl::StrCat("detection at ", d.t_s, " s after the odometry ends (", odometry_end_s, " s)"));
    }
    if (d.landmark_id < 1) {
      return Invalid(Field("detections", i, "landmark_id"), absl::StrCat("must be 1 or more, got ", d.landmark_id));
    }
    if (!std::isfinite(d.u_px) || d.u_px < 0.0 || d.u_px > p.calibration.image_width_px) {
      return Invalid(Field("detections", i, "u_px"),
                     absl::StrCat("pixel ", d.u_px, " outside the image [0, ", p.calibration.image_width_px, "]"));
    }
  }
  // The span, from the first time of any list (each is in order): the first time beyond a day.
  const double first_s = std::min({p.odometry.front().t_s, p.gnss.front().t_s, p.detections.front().t_s});
  const auto beyond_a_day = [&](const char* list, const auto& samples) -> absl::Status {
    const auto it = std::find_if(samples.begin(), samples.end(),
                                 [&](const auto& x) { return x.t_s - first_s > kMaxPassageDurationS; });
    if (it == samples.end()) return absl::OkStatus();
    return Invalid(Field(list, static_cast<size_t>(it - samples.begin()), "t_s"),
                   absl::StrCat(it->t_s, " s is more than ", kMaxPassageDurationS,
                                " s (a day) after the passage's first time, ", first_s, " s: one drive per passage"));
  };
  if (auto s = beyond_a_day("odometry", p.odometry); !s.ok()) return s;
  if (auto s = beyond_a_day("gnss", p.gnss); !s.ok()) return s;
  if (auto s = beyond_a_day("detections", p.detections); !s.ok()) return s;
  return CheckLandmarksSeenOnce(p);
}

namespace {

// The bytes a digest is taken of: each number's bit pattern, in a fixed order.
class DigestBytes {
 public:
  void Add(double v) { Append(&v, sizeof v); }
  void Add(int64_t v) { Append(&v, sizeof v); }
  void Add(const Eigen::Vector2d& v) {
    Add(v.x());
    Add(v.y());
  }
  const std::string& bytes() const { return bytes_; }

 private:
  void Append(const void* p, size_t n) { bytes_.append(static_cast<const char*>(p), n); }
  std::string bytes_ = "crowdmap.passage-content.v1";
};

}  // namespace

std::string PassageContentDigest(const Passage& passage) {
  DigestBytes b;
  b.Add(passage.start_time_unix_ms);
  const Calibration& c = passage.calibration;
  b.Add(c.wheelbase_m);
  b.Add(c.gnss_lever_arm_m);
  b.Add(c.camera_position_m);
  b.Add(c.camera_yaw_rad);
  b.Add(c.fx_px);
  b.Add(c.cx_px);
  b.Add(c.image_width_px);
  const NoiseModel& n = passage.noise;
  b.Add(n.speed_sigma_mps);
  b.Add(n.steering_sigma_rad);
  b.Add(n.pixel_sigma_px);
  b.Add(n.gnss_correlation_time_s);
  b.Add(n.gnss_process_sigma_m);
  // Each list with its length first, so that no sample can pass for another list's.
  b.Add(static_cast<int64_t>(passage.odometry.size()));
  for (const OdometrySample& o : passage.odometry) {
    b.Add(o.t_s);
    b.Add(o.speed_mps);
    b.Add(o.steering_rad);
  }
  b.Add(static_cast<int64_t>(passage.gnss.size()));
  for (const GnssFix& g : passage.gnss) {
    b.Add(g.t_s);
    b.Add(g.lat_deg);
    b.Add(g.lon_deg);
    for (int i = 0; i < 4; ++i) b.Add(g.cov_en_m2(i));
  }
  b.Add(static_cast<int64_t>(passage.detections.size()));
  for (const Detection& d : passage.detections) {
    b.Add(d.t_s);
    b.Add(static_cast<int64_t>(d.landmark_id));
    b.Add(d.u_px);
  }
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int size = 0;
  EVP_Digest(b.bytes().data(), b.bytes().size(), digest, &size, EVP_sha256(), nullptr);
  return std::string(reinterpret_cast<const char*>(digest), size);
}

}  // namespace crowdmap
