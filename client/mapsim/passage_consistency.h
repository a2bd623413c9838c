#ifndef CROWDMAP_CLIENT_MAPSIM_PASSAGE_CONSISTENCY_H_
#define CROWDMAP_CLIENT_MAPSIM_PASSAGE_CONSISTENCY_H_

#include <functional>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/estimation/map_updater.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// What one passage claims to know about the landmarks, tested against the truth: many passages
// with independent noise, each applied alone to an empty map. A map that adds passages up can be
// consistent only if each passage's covariance describes its own error, so the mean joint NEES of
// the single-passage maps, each with its own covariance, should be 1. The NEES of the same errors
// against the covariance averaged over the passages tells apart a covariance that is too small on
// average (both above 1) from one whose shape follows the passage's own error, as the Laplace
// covariance of a nonlinear estimate does (own above 1, averaged not).
struct PassageConsistencyOptions {
  ScenarioOptions scenario;
  int passages = 300;
  MapUpdateOptions update;  // the strategy and its settings

  absl::Status Validate() const;
};

struct PassageConsistency {
  int passages_used = 0;  // passages that mapped every landmark (the others are not comparable)
  int dof = 0;            // 2 x landmarks
  double own_nees_per_dof = 0.0;     // mean over passages of e_k^T C_k^-1 e_k / dof
  double spread_nees_per_dof = 0.0;  // tr(Cbar^-1 S) / dof: the errors' spread S about their mean
                                     // against the mean covariance Cbar
  double bias_nees_per_dof = 0.0;    // b^T Cbar^-1 b / dof for the mean error b; about
                                     // 1 / passages_used without a bias
  // Mean own-covariance chi2 per direction along the fifth of the eigenvectors of each C_k with
  // the smallest eigenvalues (the best-known combinations, such as the relative positions of
  // nearby landmarks), and along the fifth with the largest.
  double own_nees_most_precise_fifth = 0.0;
  double own_nees_least_precise_fifth = 0.0;
  // The passages' maps combined by their information (sum of C_k^-1 e_k over sum of C_k^-1), each
  // linearised at its own estimate: its joint NEES per dof (1 when consistent), and its mean error
  // over the landmarks, East and North (m). Information that varies with the passage's own error
  // biases such a combination even when every passage alone is unbiased and consistent.
  double fused_nees_per_dof = 0.0;
  Eigen::Vector2d fused_mean_error_en_m = Eigen::Vector2d::Zero();
};

// Called after each passage with the number done.
using PassageConsistencyProgress = std::function<void(int done)>;

absl::StatusOr<PassageConsistency> RunPassageConsistency(const PassageConsistencyOptions& options,
                                                         const PassageConsistencyProgress& progress = nullptr);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_PASSAGE_CONSISTENCY_H_
