#include "core/model/motion_model.h"

#include <algorithm>
#include <cmath>

namespace crowdmap {

double WrapAngle(double a) {
  a = std::remainder(a, 2.0 * M_PI);
  return a <= -M_PI ? a + 2.0 * M_PI : a;
}

namespace {

// sin(h) / h and its derivative, by their series near 0.
double Sinc(double h) { return std::abs(h) < 1e-4 ? 1.0 - h * h / 6.0 : std::sin(h) / h; }
double SincDerivative(double h) {
  return std::abs(h) < 1e-4 ? -h / 3.0 : (h * std::cos(h) - std::sin(h)) / (h * h);
}

}  // namespace

Pose2 BicycleStep(const Pose2& pose, double v, double xi, double dt, double wheelbase_m, Eigen::Matrix3d* d_pose,
                  Eigen::Matrix<double, 3, 2>* d_input, double turn_scale) {
  const double turn = turn_scale * v * std::sin(xi) * dt / wheelbase_m;
  const double phi = pose.z() + 0.5 * turn;
  const double c = std::cos(phi), s = std::sin(phi);
  // The chord of the arc: v dt sin(turn / 2) / (turn / 2).
  const double sinc = Sinc(0.5 * turn);
  const double chord = v * dt * sinc;
  if (d_pose) {
    *d_pose << 1, 0, -chord * s,  //
        0, 1, chord * c,          //
        0, 0, 1;
  }
  if (d_input) {
    const double dturn_dv = turn_scale * std::sin(xi) * dt / wheelbase_m;
    const double dturn_dxi = turn_scale * v * std::cos(xi) * dt / wheelbase_m;
    const double dsinc = 0.5 * SincDerivative(0.5 * turn);
    const double dchord_dv = dt * sinc + v * dt * dsinc * dturn_dv;
    const double dchord_dxi = v * dt * dsinc * dturn_dxi;
    *d_input << dchord_dv * c - 0.5 * chord * s * dturn_dv, dchord_dxi * c - 0.5 * chord * s * dturn_dxi,  //
        dchord_dv * s + 0.5 * chord * c * dturn_dv, dchord_dxi * s + 0.5 * chord * c * dturn_dxi,          //
        dturn_dv, dturn_dxi;
  }
  return {pose.x() + chord * c, pose.y() + chord * s, pose.z() + turn};
}

namespace {

// The time sample i is held for: to the next sample, or for the last one the spacing before it.
double HoldInterval(const std::vector<OdometrySample>& odometry, size_t i) {
  if (i + 1 < odometry.size()) return odometry[i + 1].t_s - odometry[i].t_s;
  return i > 0 ? odometry[i].t_s - odometry[i - 1].t_s : 0.0;
}

}  // namespace

// The heading variance (rad^2) up to which the displacement is lengthened (Preintegrate); within
// it the lengthening stays within exp(0.005), half a percent. A node interval of the thesis's
// noise at 12 m/s gathers about 1.5e-3 rad^2 a second.
constexpr double kMaxUnbiasHeadingVariance = 0.01;

RelativeMotion Preintegrate(const std::vector<OdometrySample>& odometry, double t0, double t1, double wheelbase_m,
                            const NoiseModel& noise) {
  RelativeMotion m;
  m.duration_s = t1 - t0;
  if (odometry.empty() || t1 <= t0) return m;
  Eigen::Matrix2d input_cov = Eigen::Vector2d(noise.speed_sigma_mps * noise.speed_sigma_mps,
                                              noise.steering_sigma_rad * noise.steering_sigma_rad)
                                  .asDiagonal();
  // Steering noise shrinks the measured turn on average: E[sin(xi + n)] = sin(xi) exp(-var / 2).
  // Scaling the turn by exp(var / 2) makes it unbiased; otherwise each curve is under-turned by
  // 0.1% of its angle with the thesis's steering noise, the same on every passage of the road,
  // which no number of passages averages out (on the loop the maps moved by 0.1 mm with it).
  const double turn_unbias = std::exp(0.5 * input_cov(1, 1));
  // First sample whose hold interval reaches past t0.
  auto it = std::upper_bound(odometry.begin(), odometry.end(), t0,
                             [](double t, const OdometrySample& o) { return t < o.t_s; });
  size_t i = it == odometry.begin() ? 0 : static_cast<size_t>(it - odometry.begin()) - 1;
  double t = t0;
  Eigen::Matrix3d f;
  Eigen::Matrix<double, 3, 2> g;
  while (t < t1) {
    const double end = i + 1 < odometry.size() ? std::min(odometry[i + 1].t_s, t1) : t1;
    const double dt = end - t;
    if (dt > 0.0) {
      // Heading noise accumulated since t0 shortens the measured displacement on average:
      // E[cos(theta + e)] = cos(theta) exp(-var / 2). Lengthening each step by exp(var / 2)
      // makes the predicted motion unbiased (otherwise a coherent scale error of ~0.1%). The
      // turn is not lengthened with it: it has its own correction above.
      // Only while the heading is still known to a tenth of a radian (kMaxUnbiasHeadingVariance):
      // over a long gap between nodes (a GNSS outage without detections) the factor would grow
      // without bound, exp(var / 2), and stretch the motion far beyond what its covariance admits.
      const double unbias = std::exp(0.5 * std::min(m.cov(2, 2), kMaxUnbiasHeadingVariance));
      m.delta = BicycleStep(m.delta, odometry[i].speed_mps * unbias, odometry[i].steering_rad, dt, wheelbase_m, &f, &g,
                            turn_unbias / unbias);
      // A sample's error holds over its whole interval: a node inside the interval splits it
      // between two motions whose errors are then the same draw, not independent ones. Each part
      // takes its share of the whole interval's variance (dt / interval of it, instead of
      // (dt / interval)^2), so that the parts add up to the interval's variance and no part claims
      // less than it knows: with nodes denser than the samples (a 50 Hz camera, 25 Hz encoders)
      // the motions would otherwise claim up to twice the information the encoders give.
      const double interval = HoldInterval(odometry, i);
      const double split = interval > dt ? interval / dt : 1.0;
      m.cov = f * m.cov * f.transpose() + split * (g * input_cov * g.transpose());
    }
    t = end;
    if (i + 1 < odometry.size()) ++i;
  }
  m.delta.z() = WrapAngle(m.delta.z());
  m.cov.diagonal().array() += kMotionCovarianceFloor * std::max(m.duration_s, 1e-3);
  return m;
}

Pose2 ComposeMotion(const Pose2& start, const Pose2& delta) {
  const double c = std::cos(start.z()), s = std::sin(start.z());
  return {start.x() + c * delta.x() - s * delta.y(), start.y() + s * delta.x() + c * delta.y(),
          WrapAngle(start.z() + delta.z())};
}

}  // namespace crowdmap
