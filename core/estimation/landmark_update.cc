#include "core/estimation/landmark_update.h"

#include <algorithm>
#include <chrono>

#include <Eigen/Cholesky>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"
#include "core/estimation/passage_prior.h"
#include "core/map/dense_kernels.h"

namespace crowdmap {
namespace {

double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

Eigen::MatrixXd Symmetrized(const Eigen::MatrixXd& m) { return 0.5 * (m + m.transpose()); }

// A factor's information, posterior - prior, is positive semi-definite, but the difference of
// two matrices some hundred times larger than it (a mature map's prior) leaves rounding errors of
// either sign along the directions the passage hardly informs (with the camera yaw estimated, the
// landmarks' common turn about the vehicle). Eigenvalues below zero by no more than the rounding
// of `posterior` are set to zero; a larger negative one is left for the map invariants to refuse.
Eigen::MatrixXd WithoutRoundingNegatives(const Eigen::MatrixXd& information, const Eigen::MatrixXd& posterior) {
  if (information.rows() == 0 || Eigen::LDLT<Eigen::MatrixXd>(information).isPositive()) return information;
  const double rounding = 1e-10 * posterior.cwiseAbs().maxCoeff() * static_cast<double>(information.rows());
  Eigen::MatrixXd clipped = information;
  return ClipSmallNegativeEigenvalues(&clipped, rounding) ? clipped : information;
}

// Derivative of the graph's local coordinates with respect to a landmark's offset from its anchor
// (East/North at the anchor), at `offset`: the tangent frames at the anchor and at the landmark
// differ by a rotation of offset / earth radius, so EnToLocal alone is off by about 1e-6 per metre.
// Central differences of the exact map, with 100 m steps: the truncation error (step / earth
// radius)^2 and the rounding (1e-9 m / step) both stay near 1e-10.
Eigen::Matrix2d OffsetToLocal(const LocalFrame& frame, const LatLon& anchor, const Eigen::Vector2d& offset) {
  const LocalFrame at_anchor(anchor);
  Eigen::Matrix2d t;
  for (int k = 0; k < 2; ++k) {
    const Eigen::Vector2d step = 100.0 * Eigen::Vector2d::Unit(k);
    t.col(k) = (frame.ToLocal(at_anchor.ToGeo(offset + step)) - frame.ToLocal(at_anchor.ToGeo(offset - step))) / 200.0;
  }
  return t;
}

}  // namespace

LandmarkUpdate::LandmarkUpdate(const LocalFrame& frame, MapOverlay* map, std::vector<LandmarkId> ids)
    : frame_(frame), map_(map), ids_(std::move(ids)), in_map_(ids_.size()), positions_(ids_.size()) {
  for (size_t i = 0; i < ids_.size(); ++i) {
    const Landmark* lm = map_->FindLandmark(ids_[i]);
    in_map_[i] = lm != nullptr;
    positions_[i] = lm ? frame_.ToLocal(lm->position) : Eigen::Vector2d::Zero();
  }
}

absl::Status LandmarkUpdate::AddMapPrior(const LandmarkUpdateOptions& options, ceres::Problem* problem) {
  prior_index_.clear();
  std::vector<LandmarkId> prior_ids;
  for (int i = 0; i < size(); ++i) {
    if (!in_map_[i]) continue;
    prior_index_.push_back(i);
    prior_ids.push_back(ids_[i]);
  }
  const int m = static_cast<int>(prior_index_.size());
  prior_mean_.resize(2 * m);
  prior_information_.setZero(2 * m, 2 * m);
  prior_marginals_.assign(m, Eigen::Matrix2d::Identity());
  if (m == 0) return absl::OkStatus();
  std::vector<Eigen::Matrix2d> to_local(m);
  for (int k = 0; k < m; ++k) {
    const Landmark* lm = map_->FindLandmark(prior_ids[k]);
    to_local[k] = OffsetToLocal(frame_, lm->anchor, lm->Offset());
    prior_mean_.segment<2>(2 * k) = positions_[prior_index_[k]];
  }
  if (!options.correlated) {
    for (int k = 0; k < m; ++k) {
      const Eigen::Matrix2d cov = to_local[k] * map_->FindLandmark(prior_ids[k])->cov_en_m2 * to_local[k].transpose();
      prior_marginals_[k] = cov;
      Eigen::LLT<Eigen::Matrix2d> llt(cov);
      if (llt.info() != Eigen::Success) {
        return absl::FailedPreconditionError(absl::StrCat("landmark ", prior_ids[k],
                                                          ": map covariance is not positive definite"));
      }
      prior_information_.block<2, 2>(2 * k, 2 * k) = llt.solve(Eigen::Matrix2d::Identity());
      problem->AddResidualBlock(new LandmarkPriorFactor(prior_mean_.segment<2>(2 * k), SqrtInformation(cov)), nullptr,
                                block(prior_index_[k]));
    }
    return absl::OkStatus();
  }
  absl::StatusOr<Eigen::MatrixXd> anchored = options.passage_prior ? options.passage_prior->Covariance(prior_ids)
                                                                    : JointCovariance(*map_, prior_ids, options.window);
  if (!anchored.ok()) return anchored.status();
  Eigen::MatrixXd cov(2 * m, 2 * m);
  for (int k = 0; k < m; ++k) {
    for (int l = 0; l < m; ++l) {
      cov.block<2, 2>(2 * k, 2 * l) = to_local[k] * anchored->block<2, 2>(2 * k, 2 * l) * to_local[l].transpose();
    }
  }
  for (int k = 0; k < m; ++k) prior_marginals_[k] = cov.block<2, 2>(2 * k, 2 * k);
  Eigen::LLT<Eigen::MatrixXd> llt(Symmetrized(cov));
  if (llt.info() != Eigen::Success) {
    return absl::FailedPreconditionError(
        absl::StrCat("map covariance of the ", m, " landmarks in the graph is not positive definite"));
  }
  prior_information_ = Symmetrized(llt.solve(Eigen::MatrixXd::Identity(2 * m, 2 * m)));
  const Eigen::MatrixXd sqrt_info = llt.matrixL().solve(Eigen::MatrixXd::Identity(2 * m, 2 * m));
  std::vector<double*> blocks;
  for (int i : prior_index_) blocks.push_back(block(i));
  problem->AddResidualBlock(new LandmarkPriorFactor(prior_mean_, sqrt_info), nullptr, blocks);
  return absl::OkStatus();
}

double LandmarkUpdate::PriorShiftMahalanobis2(int i) const {
  const auto it = std::find(prior_index_.begin(), prior_index_.end(), i);
  if (it == prior_index_.end()) return 0.0;
  const int k = static_cast<int>(it - prior_index_.begin());
  const Eigen::Vector2d shift = positions_[i] - prior_mean_.segment<2>(2 * k);
  return shift.dot(prior_marginals_[k].ldlt().solve(shift));
}

absl::StatusOr<LandmarkUpdateStats> LandmarkUpdate::Commit(const Eigen::MatrixXd& cov_ss,
                                                           const Eigen::VectorXd& gradient_ss,
                                                           const LandmarkUpdateOptions& options,
                                                           const std::function<void(Landmark*)>& touch) {
  LandmarkUpdateStats stats;
  const auto start = std::chrono::steady_clock::now();
  const int n = size();
  if (cov_ss.rows() != 2 * n || cov_ss.cols() != 2 * n || gradient_ss.size() != 2 * n) {
    return absl::InvalidArgumentError("landmark covariance: wrong size for the graph's landmarks");
  }
  const int m = static_cast<int>(prior_index_.size());
  stats.updated = m;
  stats.created = n - m;

  Eigen::VectorXd x(2 * n);
  for (int i = 0; i < n; ++i) x.segment<2>(2 * i) = positions_[i];
  Eigen::MatrixXd prior = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  Eigen::VectorXd prior_vector = Eigen::VectorXd::Zero(2 * n);
  for (int k = 0; k < m; ++k) {
    const int i = prior_index_[k];
    prior_vector.segment<2>(2 * i) = (prior_information_ * prior_mean_).segment<2>(2 * k);
    for (int l = 0; l < m; ++l) {
      prior.block<2, 2>(2 * i, 2 * prior_index_[l]) = prior_information_.block<2, 2>(2 * k, 2 * l);
    }
  }
  auto make_factor = [&](std::vector<LandmarkId> landmarks) {
    MapFactor f;
    f.vehicle_id = options.vehicle_id;
    f.passage_id = options.passage_id;
    f.landmarks = std::move(landmarks);
    return f;
  };
  // The remaining gradient enters only while the step it implies (the next Gauss-Newton step,
  // cov_ss g) stays within the posterior's own uncertainty (squared Mahalanobis length below 1),
  // where the quadratic model of the cost can be trusted: it removes what a solve stopped short of
  // its optimum leaves in the factor, and leaves alone a solve stopped far from one.
  const Eigen::VectorXd gradient =
      gradient_ss.dot(cov_ss * gradient_ss) < 1.0 ? gradient_ss : Eigen::VectorXd::Zero(2 * n);
  if (options.correlated) {
    // The inverse of cov_ss, so that prior + factor gives back exactly the stored marginals.
    Eigen::LLT<Eigen::MatrixXd> llt(Symmetrized(cov_ss));
    if (llt.info() != Eigen::Success) return absl::InternalError("graph landmark covariance is not positive definite");
    const Eigen::MatrixXd information = Symmetrized(llt.solve(Eigen::MatrixXd::Identity(2 * n, 2 * n)));
    MapFactor f = make_factor(ids_);
    f.information = WithoutRoundingNegatives(Symmetrized(information - prior), information);
    f.information_vector = information * x - prior_vector - gradient;
    const int64_t factor_id = AddLocalFactor(frame_, x, std::move(f), map_);
    if (options.passage_prior) {
      absl::StatusOr<int> conditioned =
          options.passage_prior->Condition(*map_->FindFactor(factor_id), map_->BumpVersion(), touch, map_);
      if (!conditioned.ok()) return conditioned.status();
      stats.conditioned = *conditioned;
      stats.covariance_ms = MillisecondsSince(start);
      return stats;
    }
  } else {
    for (int i = 0; i < n; ++i) {
      const Eigen::Matrix2d information = cov_ss.block<2, 2>(2 * i, 2 * i).inverse();
      MapFactor f = make_factor({ids_[i]});
      f.information = Symmetrized(information - prior.block<2, 2>(2 * i, 2 * i));
      f.information_vector = information * positions_[i] - prior_vector.segment<2>(2 * i) - gradient.segment<2>(2 * i);
      AddLocalFactor(frame_, positions_[i], std::move(f), map_);
    }
  }
  const int64_t version = map_->BumpVersion();
  MapWindowOptions window = options.window;
  if (!options.correlated) window.hops = 1;  // DC factors link no landmarks
  // The graph's posterior is the seeds' new marginal: exact when its prior was (the map's
  // marginal), otherwise no smaller than the exact one.
  MarginalRefresh refresh;
  for (int i = 0; i < n; ++i) {
    const Landmark* lm = map_->FindLandmark(ids_[i]);  // written by AddLocalFactor: anchored
    const Eigen::Matrix2d from_local = OffsetToLocal(frame_, lm->anchor, EastNorthOffset(lm->anchor, frame_.ToGeo(positions_[i]))).inverse();
    refresh.seeds.push_back(from_local * cov_ss.block<2, 2>(2 * i, 2 * i) * from_local.transpose());
  }
  absl::StatusOr<int> conditioned = ResolveAround(ids_, refresh, window, version, touch, map_);
  if (!conditioned.ok()) return conditioned.status();
  stats.conditioned = *conditioned;
  stats.covariance_ms = MillisecondsSince(start);
  return stats;
}

int64_t AddLocalFactor(const LocalFrame& frame, const Eigen::VectorXd& local, MapFactor factor, MapOverlay* map) {
  const int k = static_cast<int>(factor.landmarks.size());
  // local = T (d - d') + x' around the solution, T block diagonal: each landmark's offset to the
  // local frame.
  std::vector<Eigen::Matrix2d> t(k);
  Eigen::VectorXd offsets(2 * k);
  for (int i = 0; i < k; ++i) {
    const LatLon position = frame.ToGeo(local.segment<2>(2 * i));
    const Landmark* known = map->FindLandmark(factor.landmarks[i]);
    Landmark record;
    if (known == nullptr) {
      record.id = factor.landmarks[i];
      record.anchor = position;
      record.position = position;
      map->PutLandmark(record);
    }
    const LatLon anchor = known ? known->anchor : position;
    offsets.segment<2>(2 * i) = EastNorthOffset(anchor, position);
    t[i] = OffsetToLocal(frame, anchor, offsets.segment<2>(2 * i));
  }
  const Eigen::VectorXd gradient = factor.information_vector - factor.information * local;
  for (int i = 0; i < k; ++i) {
    factor.information_vector.segment<2>(2 * i) = t[i].transpose() * gradient.segment<2>(2 * i);
    for (int j = 0; j < k; ++j) {
      factor.information.block<2, 2>(2 * i, 2 * j) = t[i].transpose() * factor.information.block<2, 2>(2 * i, 2 * j) * t[j];
    }
  }
  factor.information = Symmetrized(factor.information);
  factor.information_vector += factor.information * offsets;
  return map->AddFactor(std::move(factor));
}

absl::StatusOr<int> ResolveAround(const std::vector<LandmarkId>& seeds, const MarginalRefresh& refresh,
                                  const MapWindowOptions& window_options, int64_t version,
                                  const std::function<void(Landmark*)>& touch, MapOverlay* map) {
  absl::StatusOr<MapWindow> window = MapWindow::Build(*map, seeds, window_options);
  if (!window.ok()) return window.status();
  const std::vector<LandmarkId>& ids = window->landmarks();
  const size_t seed_count = seeds.size();
  std::vector<Eigen::Matrix2d> marginals = refresh.seeds;
  if (refresh.others) {
    marginals = window->Marginals();
  } else if (marginals.size() != seed_count) {
    absl::StatusOr<Eigen::MatrixXd> cov = window->Covariance(seeds);
    if (!cov.ok()) return cov.status();
    marginals.clear();
    for (size_t i = 0; i < seed_count; ++i) marginals.push_back(cov->block<2, 2>(2 * i, 2 * i));
  }
  int conditioned = 0;
  for (size_t i = 0; i < ids.size(); ++i) {
    absl::StatusOr<Landmark> found = LandmarkStillThere(*map, ids[i]);
    if (!found.ok()) return found.status();
    Landmark& record = *found;
    const Eigen::Vector2d offset = window->offsets().segment<2>(2 * i);
    const bool seed = i < seed_count;
    const bool refreshed = i < marginals.size();
    if (!seed && !refreshed && (offset - record.Offset()).norm() < kMinWrittenChangeM) continue;
    record.position = LocalFrame(record.anchor).ToGeo(offset);
    if (refreshed) record.cov_en_m2 = 0.5 * (marginals[i] + marginals[i].transpose());
    record.version = version;
    if (seed) {
      touch(&record);
    } else {
      ++conditioned;
    }
    map->PutLandmark(record);
  }
  return conditioned;
}

}  // namespace crowdmap
