#ifndef CROWDMAP_CORE_MODEL_MOTION_MODEL_H_
#define CROWDMAP_CORE_MODEL_MOTION_MODEL_H_

#include <vector>

#include <Eigen/Core>

#include "core/model/passage.h"

namespace crowdmap {

// Vehicle pose (x, y, theta) in a local East/North frame; theta is the heading from East (rad).
using Pose2 = Eigen::Vector3d;

// One bicycle-model step of duration dt_s with speed v and steering angle xi held: the arc of
// constant turn. The heading turns by d = v sin(xi) dt / R and the origin moves along the arc's
// chord, of length v dt sin(d / 2) / (d / 2), in the direction of the mean heading:
//   x += L cos(theta + d / 2),  y += L sin(theta + d / 2),  theta += d.
// The thesis's eq. 4.43 moves v dt instead (L within v dt d^2 / 24 of it: 1e-5 of a 25 Hz step in a
// 10 m curve). With the arc, a step split in parts ends where the whole step does, so a pose node
// inside a long sample interval (an encoder gap) does not change the motion. The heading change
// is multiplied by `turn_scale` (1 for the model itself).
// If the Jacobians are non-null they receive d(result)/d(pose) and d(result)/d(v, xi).
Pose2 BicycleStep(const Pose2& pose, double speed_mps, double steering_rad, double dt_s, double wheelbase_m,
                  Eigen::Matrix3d* d_pose = nullptr, Eigen::Matrix<double, 3, 2>* d_input = nullptr,
                  double turn_scale = 1.0);

// The motion between two times predicted by the encoders, in the frame of the earlier pose.
struct RelativeMotion {
  Pose2 delta = Pose2::Zero();                    // (dx, dy, dtheta) in the start pose's frame
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();  // first-order covariance of delta
  double duration_s = 0.0;
};

// Composes the bicycle steps between t0_s and t1_s (t0 < t1). Each sample is held from its time
// to the next sample's (the first sample also covers earlier times, the last one later times).
// Speed and steering noise (independent per sample) are propagated to first order. A small floor
// (kMotionCovarianceFloor per second, on x, y and heading) stands for the bicycle model's own
// error: without it a motion over one sample (two inputs, three outputs) is a hard constraint
// along one direction, and standing still has no covariance at all.
RelativeMotion Preintegrate(const std::vector<OdometrySample>& odometry, double t0_s, double t1_s,
                            double wheelbase_m, const NoiseModel& noise);

// Pose reached from `start` after the relative motion `delta` (SE(2) composition).
Pose2 ComposeMotion(const Pose2& start, const Pose2& delta);

// Wraps an angle to (-pi, pi].
double WrapAngle(double a);

// 1e-6 m^2 and rad^2 per second: 0.2 mm and 0.2 mrad over a 25 Hz sample, about 1% of the
// thesis's steering noise's heading variance and 0.3% of its speed noise's. At 1e-8 two nodes one
// encoder sample apart (a 25 Hz camera on the 25 Hz encoders' clock) were tied 1e9 times stiffer
// along that direction than along the others, and 11 of 300 such loop passages failed the
// consistency test (docs/results.md, "Camera frame rates").
constexpr double kMotionCovarianceFloor = 1e-6;

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MODEL_MOTION_MODEL_H_
