#ifndef CROWDMAP_CLIENT_MAPSIM_POSE_BIAS_H_
#define CROWDMAP_CLIENT_MAPSIM_POSE_BIAS_H_

#include <functional>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Bias of the maximum-a-posteriori pose estimate of one passage (odometry + GNSS pose graph, no
// landmarks) along the route: many passages with independent noise, each solved alone, errors
// against the true poses averaged in time bins. Every measurement model is unbiased, so a mean
// error well above its standard error is the bias of the MAP estimate of a nonlinear problem.
// The same estimates after the second-order bias correction the map update applies
// (GraphLinearization::CorrectSecondOrderBias) are measured beside them.
struct PoseBiasOptions {
  ScenarioOptions scenario;
  int passages = 1000;
  double bin_s = 5.0;  // width of the time bins (s)

  absl::Status Validate() const;
};

// Errors in the frame of the true pose: along track (forward), cross track (left), heading.
struct PoseBiasBin {
  double start_s = 0.0;
  int samples = 0;               // pose nodes that fell in the bin, over all passages
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();     // mean error (m, m, rad)
  Eigen::Vector3d sd = Eigen::Vector3d::Zero();       // spread of one pose's error
  Eigen::Vector3d mean_se = Eigen::Vector3d::Zero();  // standard error of `mean`
  Eigen::Vector3d corrected_mean = Eigen::Vector3d::Zero();  // after the bias correction
  Eigen::Vector3d corrected_se = Eigen::Vector3d::Zero();
};

// Called after each passage with the number done.
using PoseBiasProgress = std::function<void(int done)>;

absl::StatusOr<std::vector<PoseBiasBin>> RunPoseBias(const PoseBiasOptions& options,
                                                     const PoseBiasProgress& progress = nullptr);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_POSE_BIAS_H_
