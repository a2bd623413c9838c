#ifndef CROWDMAP_CORE_SIM_SENSOR_SIMULATION_H_
#define CROWDMAP_CORE_SIM_SENSOR_SIMULATION_H_

// Measurement simulation shared by the scenarios: the encoders, the GNSS receiver and the camera
// of one vehicle, given its true trajectory.

#include <cstdint>
#include <functional>
#include <random>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"

#include "core/geo/local_frame.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

uint64_t SplitMix64(uint64_t x);

// The Gaussian draws of one simulated passage, in one sequence (the order of the draws is part of
// what makes a passage reproducible from its seed).
class NoiseSource {
 public:
  explicit NoiseSource(uint64_t seed) : rng_(seed) {}
  double Normal() { return normal_(rng_); }
  std::mt19937_64& rng() { return rng_; }

 private:
  std::mt19937_64 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
};

// How much larger than declared a fleet's sensor noise really is: a passage declares the
// scenario's NoiseModel and its noise is drawn with those sigmas times these factors (a detector
// or encoders worse than their data sheet). 1 = as declared.
struct UndeclaredNoiseScales {
  double speed = 1.0;
  double steering = 1.0;
  double pixel = 1.0;
  double gnss = 1.0;  // GnssSimulation::undeclared_scale

  // InvalidArgument naming the first factor that is not finite and > 0.
  absl::Status Validate() const;
};

// The sigmas noise is drawn with: `declared` times `scales`.
NoiseModel DrawnNoise(const NoiseModel& declared, const UndeclaredNoiseScales& scales);

// The true pose at time t_s (seconds since the passage start).
using TruePoseFn = std::function<Pose2(double t_s)>;

// Pose at t_s along poses[j] = pose at inputs[j].t_s, each input held for one step of dt_s, by
// the same bicycle steps that produced the poses (so exactly consistent with them).
Pose2 PoseAlongInputs(const std::vector<Pose2>& poses, const std::vector<OdometrySample>& inputs, double dt_s,
                      double wheelbase_m, double t_s);

// The encoder readings of the true inputs up to duration_s, with white speed and steering noise.
std::vector<OdometrySample> SimulateOdometry(const std::vector<OdometrySample>& truth, double duration_s,
                                             const NoiseModel& noise, NoiseSource* source);

struct GnssSimulation {
  double rate_hz = 1.0;
  double sigma_m = 10.0;        // declared with each fix
  double undeclared_scale = 1.0;  // the error is drawn with sigma_m times this
  bool ar1 = false;          // e_k = alpha e_(k-1) + sqrt(1 - alpha^2) w_k per axis, else white
  double ar1_alpha = 0.988;

  // The process as a passage declares it (NoiseModel::gnss_correlation_time_s): tau with
  // alpha = exp(-1 / (rate tau)); 0 for white noise.
  double CorrelationTimeS() const;
};

// Fixes at k / rate_hz for k = 0.. while t <= duration_s, of the antenna (lever arm from
// `calibration`) with the declared covariance sigma_m^2 I (their error drawn with sigma_m times
// undeclared_scale).
std::vector<GnssFix> SimulateGnss(const TruePoseFn& pose_at, double duration_s, const LocalFrame& frame,
                                  const Calibration& calibration, const GnssSimulation& gnss, NoiseSource* source);

// The true horizontal pixel of `landmark_m` seen by `camera` from `pose`; false when it is behind
// the camera, outside [min_range_m, max_range_m] or outside the image.
bool TruePixel(const Pose2& pose, const Eigen::Vector2d& landmark_m, const Calibration& camera, double min_range_m,
               double max_range_m, double* u_px);

// The detector's pixel for a true pixel: Gaussian noise, and nothing (false) when the noisy pixel
// falls outside the image, as a detector reports only what is inside it.
bool DetectedPixel(double u_true_px, const Calibration& camera, double pixel_sigma_px, NoiseSource* source,
                   double* u_px);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_SENSOR_SIMULATION_H_
