#include "client/mapsim/passage_consistency.h"

#include <algorithm>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "core/map/map_state.h"
#include "core/sim/metrics.h"

namespace crowdmap {

absl::Status PassageConsistencyOptions::Validate() const {
  if (passages < 2) return absl::InvalidArgumentError(absl::StrCat("passages: must be >= 2, got ", passages));
  if (update.strategy == UpdateStrategy::kDecorrelated) {
    return absl::InvalidArgumentError("strategy: dc keeps no cross-covariances, so it has no joint NEES");
  }
  if (absl::Status s = scenario.Validate(); !s.ok()) return s;
  return update.Validate();
}

absl::StatusOr<PassageConsistency> RunPassageConsistency(const PassageConsistencyOptions& options,
                                                         const PassageConsistencyProgress& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options.scenario);
  if (!scenario.ok()) return scenario.status();
  const int dof = 2 * static_cast<int>(scenario->landmarks().size());

  PassageConsistency out;
  out.dof = dof;
  Eigen::VectorXd error_sum = Eigen::VectorXd::Zero(dof);
  Eigen::MatrixXd error_outer = Eigen::MatrixXd::Zero(dof, dof), cov_sum = Eigen::MatrixXd::Zero(dof, dof);
  Eigen::MatrixXd information_sum = Eigen::MatrixXd::Zero(dof, dof);
  Eigen::VectorXd weighted_error_sum = Eigen::VectorXd::Zero(dof);
  const int fifth = std::max(1, dof / 5);
  double own = 0.0, precise = 0.0, loose = 0.0;
  for (int i = 0; i < options.passages; ++i) {
    // A fresh updater and an empty map: every passage is the map's first.
    MapUpdater updater(options.update);
    MapState map;
    absl::StatusOr<PassageUpdate> update = updater.Compute(scenario->MakePassage(i), map);
    if (progress) progress(i + 1);
    if (!update.ok()) continue;
    map.Apply(update->delta);
    const StackedMapErrors stacked = StackMapErrors(map, scenario->landmarks());
    if (static_cast<int>(stacked.ids.size()) * 2 != dof) continue;
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(stacked.cov);
    if (eigen.info() != Eigen::Success || !(eigen.eigenvalues()(0) > 0.0)) continue;
    // chi2 per eigen-direction, in increasing eigenvalue order.
    const Eigen::ArrayXd chi2 =
        (eigen.eigenvectors().transpose() * stacked.errors).array().square() / eigen.eigenvalues().array();
    own += chi2.sum() / dof;
    precise += chi2.head(fifth).mean();
    loose += chi2.tail(fifth).mean();
    error_sum += stacked.errors;
    error_outer += stacked.errors * stacked.errors.transpose();
    cov_sum += stacked.cov;
    const Eigen::MatrixXd information = eigen.eigenvectors() * eigen.eigenvalues().cwiseInverse().asDiagonal() *
                                        eigen.eigenvectors().transpose();
    information_sum += information;
    weighted_error_sum += information * stacked.errors;
    ++out.passages_used;
  }
  const int n = out.passages_used;
  if (n < 2) return absl::FailedPreconditionError(absl::StrCat("only ", n, " passages mapped every landmark"));
  out.own_nees_per_dof = own / n;
  out.own_nees_most_precise_fifth = precise / n;
  out.own_nees_least_precise_fifth = loose / n;
  const Eigen::VectorXd mean_error = error_sum / n;
  const Eigen::MatrixXd spread = (error_outer - n * mean_error * mean_error.transpose()) / (n - 1);
  const Eigen::LLT<Eigen::MatrixXd> mean_cov((cov_sum / n).eval());
  if (mean_cov.info() != Eigen::Success) return absl::InternalError("the mean covariance is not positive definite");
  out.spread_nees_per_dof = mean_cov.solve(spread).trace() / dof;
  out.bias_nees_per_dof = mean_error.dot(mean_cov.solve(mean_error)) / dof;
  const Eigen::VectorXd fused = information_sum.ldlt().solve(weighted_error_sum);
  out.fused_nees_per_dof = fused.dot(information_sum * fused) / dof;
  for (int i = 0; i < dof / 2; ++i) out.fused_mean_error_en_m += fused.segment<2>(2 * i) / (dof / 2);
  return out;
}

}  // namespace crowdmap
