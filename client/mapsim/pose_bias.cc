#include "client/mapsim/pose_bias.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/estimation/graph_builder.h"
#include "core/estimation/graph_linearization.h"

namespace crowdmap {

absl::Status PoseBiasOptions::Validate() const {
  if (passages < 2) return absl::InvalidArgumentError(absl::StrCat("passages: must be >= 2, got ", passages));
  if (!(bin_s > 0.0)) return absl::InvalidArgumentError("bin_s: must be > 0");
  return scenario.Validate();
}

absl::StatusOr<std::vector<PoseBiasBin>> RunPoseBias(const PoseBiasOptions& options,
                                                     const PoseBiasProgress& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options.scenario);
  if (!scenario.ok()) return scenario.status();

  // Per bin: the spread of single node errors, and the mean over passages of each passage's mean
  // error in the bin (its standard error counts passages, the independent draws, not the
  // correlated nodes of one passage).
  const int bins = static_cast<int>(std::ceil(options.scenario.duration_s / options.bin_s)) + 1;
  std::vector<Eigen::Vector3d> sum(bins, Eigen::Vector3d::Zero()), sum_sq(bins, Eigen::Vector3d::Zero());
  // [0]: the MAP, [1]: after the bias correction.
  std::vector<Eigen::Vector3d> passage_sum[2], passage_sum_sq[2];
  for (int c = 0; c < 2; ++c) {
    passage_sum[c].assign(bins, Eigen::Vector3d::Zero());
    passage_sum_sq[c].assign(bins, Eigen::Vector3d::Zero());
  }
  std::vector<int> samples(bins, 0), passages_in(bins, 0);
  GraphOptions graph_options;  // refines the odometry + GNSS pose graph (the MAP without landmarks)
  for (int i = 0; i < options.passages; ++i) {
    const Passage passage = scenario->MakePassage(i);
    absl::StatusOr<PassageGraph> graph = BuildPassageGraph(passage, graph_options);
    if (!graph.ok()) return graph.status();
    std::vector<Pose2> corrected = graph->initial_poses;
    ceres::Problem problem;
    AddPoseGraphFactors(*graph, 0, graph->node_count() - 1, passage.calibration.gnss_lever_arm_m, nullptr, nullptr,
                        &corrected, &problem);
    absl::StatusOr<GraphLinearization> linearization = GraphLinearization::Compute(&problem, {});
    if (!linearization.ok()) return linearization.status();
    if (absl::Status s = linearization->CorrectSecondOrderBias(&problem, nullptr); !s.ok()) return s;
    std::vector<Eigen::Vector3d> mine[2] = {std::vector<Eigen::Vector3d>(bins, Eigen::Vector3d::Zero()),
                                            std::vector<Eigen::Vector3d>(bins, Eigen::Vector3d::Zero())};
    std::vector<int> mine_n(bins, 0);
    for (int k = 0; k < graph->node_count(); ++k) {
      const double t = graph->node_times_s[k];
      const int b = static_cast<int>(std::floor(t / options.bin_s));
      if (b < 0 || b >= bins) continue;
      const Pose2 truth = scenario->TruePoseAt(t);
      const Eigen::Vector2d truth_local = graph->frame.ToLocal(scenario->frame().ToGeo(truth.head<2>()));
      const Eigen::Vector2d forward(std::cos(truth.z()), std::sin(truth.z()));
      const Eigen::Vector2d left(-forward.y(), forward.x());
      auto error = [&](const Pose2& estimate) {
        const Eigen::Vector2d e = estimate.head<2>() - truth_local;
        return Eigen::Vector3d(e.dot(forward), e.dot(left), std::remainder(estimate.z() - truth.z(), 2 * M_PI));
      };
      const Eigen::Vector3d v = error(graph->initial_poses[k]);
      sum[b] += v;
      sum_sq[b] += v.cwiseProduct(v);
      ++samples[b];
      mine[0][b] += v;
      mine[1][b] += error(corrected[k]);
      ++mine_n[b];
    }
    for (int b = 0; b < bins; ++b) {
      if (mine_n[b] == 0) continue;
      for (int c = 0; c < 2; ++c) {
        const Eigen::Vector3d m = mine[c][b] / mine_n[b];
        passage_sum[c][b] += m;
        passage_sum_sq[c][b] += m.cwiseProduct(m);
      }
      ++passages_in[b];
    }
    if (progress) progress(i + 1);
  }

  std::vector<PoseBiasBin> out;
  for (int b = 0; b < bins; ++b) {
    if (passages_in[b] < 2) continue;
    PoseBiasBin bin;
    bin.start_s = b * options.bin_s;
    bin.samples = samples[b];
    const Eigen::Vector3d node_mean = sum[b] / samples[b];
    bin.sd = (sum_sq[b] / samples[b] - node_mean.cwiseProduct(node_mean)).cwiseMax(0.0).cwiseSqrt();
    const double n = passages_in[b];
    auto mean_and_se = [&](int c, Eigen::Vector3d* mean, Eigen::Vector3d* se) {
      *mean = passage_sum[c][b] / n;
      const Eigen::Vector3d var = (passage_sum_sq[c][b] / n - mean->cwiseProduct(*mean)).cwiseMax(0.0) * (n / (n - 1));
      *se = (var / n).cwiseSqrt();
    };
    mean_and_se(0, &bin.mean, &bin.mean_se);
    mean_and_se(1, &bin.corrected_mean, &bin.corrected_se);
    out.push_back(bin);
  }
  return out;
}

}  // namespace crowdmap
