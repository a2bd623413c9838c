#include "core/estimation/landmark_update.h"

#include <algorithm>
#include <chrono>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "absl/strings/str_cat.h"
#include "core/estimation/factors.h"

namespace crowdmap {
namespace {

double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

Eigen::Matrix2d Symmetrized(const Eigen::Matrix2d& m) { return 0.5 * (m + m.transpose()); }

}  // namespace

bool WithinCorrelationRadius(const Eigen::Vector2d& a, const Eigen::Vector2d& b, double radius_m) {
  return (a - b).squaredNorm() <= radius_m * radius_m;
}

LandmarkUpdate::LandmarkUpdate(const LocalFrame& frame, MapOverlay* map, std::vector<LandmarkId> ids)
    : frame_(frame), map_(map), ids_(std::move(ids)), in_map_(ids_.size()), positions_(ids_.size()) {
  for (size_t i = 0; i < ids_.size(); ++i) {
    const Landmark* lm = map_->FindLandmark(ids_[i]);
    in_map_[i] = lm != nullptr;
    positions_[i] = lm ? frame_.ToLocal(lm->position) : Eigen::Vector2d::Zero();
  }
}

Eigen::Matrix2d LandmarkUpdate::LocalCross(LandmarkId a, const Eigen::Matrix2d& ra, LandmarkId b,
                                           const Eigen::Matrix2d& rb) const {
  Eigen::Matrix2d cov;
  if (!map_->CrossCovariance(a, b, &cov)) return Eigen::Matrix2d::Zero();
  return ra * cov * rb.transpose();
}

absl::Status LandmarkUpdate::AddMapPrior(bool correlated, ceres::Problem* problem) {
  prior_index_.clear();
  to_local_.clear();
  for (int i = 0; i < size(); ++i) {
    if (in_map_[i]) prior_index_.push_back(i);
  }
  const int m = static_cast<int>(prior_index_.size());
  prior_mean_.resize(2 * m);
  prior_cov_.setZero(2 * m, 2 * m);
  for (int k = 0; k < m; ++k) {
    const Landmark* lm = map_->FindLandmark(ids_[prior_index_[k]]);
    to_local_.push_back(frame_.EnToLocal(lm->position));
    prior_mean_.segment<2>(2 * k) = positions_[prior_index_[k]];
    prior_cov_.block<2, 2>(2 * k, 2 * k) = to_local_[k] * lm->cov_en_m2 * to_local_[k].transpose();
  }
  if (m == 0) return absl::OkStatus();
  if (!correlated) {
    for (int k = 0; k < m; ++k) {
      const Eigen::Matrix2d cov = prior_cov_.block<2, 2>(2 * k, 2 * k);
      if (Eigen::LLT<Eigen::Matrix2d>(cov).info() != Eigen::Success) {
        return absl::FailedPreconditionError(absl::StrCat("landmark ", ids_[prior_index_[k]],
                                                          ": map covariance is not positive definite"));
      }
      problem->AddResidualBlock(new LandmarkPriorFactor(prior_mean_.segment<2>(2 * k), SqrtInformation(cov)), nullptr,
                                block(prior_index_[k]));
    }
    return absl::OkStatus();
  }
  for (int k = 0; k < m; ++k) {
    for (int l = k + 1; l < m; ++l) {
      const Eigen::Matrix2d c =
          LocalCross(ids_[prior_index_[k]], to_local_[k], ids_[prior_index_[l]], to_local_[l]);
      prior_cov_.block<2, 2>(2 * k, 2 * l) = c;
      prior_cov_.block<2, 2>(2 * l, 2 * k) = c.transpose();
    }
  }
  prior_llt_.compute(prior_cov_);
  if (prior_llt_.info() != Eigen::Success) {
    return absl::FailedPreconditionError(
        absl::StrCat("map covariance of the ", m, " landmarks in the graph is not positive definite"));
  }
  const Eigen::MatrixXd sqrt_info = prior_llt_.matrixL().solve(Eigen::MatrixXd::Identity(2 * m, 2 * m));
  std::vector<double*> blocks;
  for (int i : prior_index_) blocks.push_back(block(i));
  problem->AddResidualBlock(new LandmarkPriorFactor(prior_mean_, sqrt_info), nullptr, blocks);
  return absl::OkStatus();
}

void LandmarkUpdate::WriteLandmark(Landmark record, const Eigen::Vector2d& mean, const Eigen::Matrix2d& cov,
                                   int64_t version, Eigen::Matrix2d* from_local) {
  record.position = frame_.ToGeo(mean);
  *from_local = frame_.EnToLocal(record.position).inverse();
  record.cov_en_m2 = Symmetrized(*from_local * cov * from_local->transpose());
  record.version = version;
  map_->PutLandmark(record);
}

absl::StatusOr<LandmarkUpdateStats> LandmarkUpdate::Commit(const Eigen::MatrixXd& cov_ss,
                                                           const LandmarkUpdateOptions& options,
                                                           const std::function<void(Landmark*)>& touch) {
  LandmarkUpdateStats stats;
  const auto start = std::chrono::steady_clock::now();
  if (cov_ss.rows() != 2 * size() || cov_ss.cols() != 2 * size()) {
    return absl::InvalidArgumentError("landmark covariance: wrong size for the graph's landmarks");
  }
  const int n = size();
  const int m = static_cast<int>(prior_index_.size());
  stats.updated = m;
  stats.created = n - m;

  // Landmarks outside the graph correlated with its map landmarks (only CC keeps correlations).
  std::vector<LandmarkId> outside;
  if (options.correlated && m > 0) {
    for (int i : prior_index_) map_->AppendNeighbors(ids_[i], &outside);
    std::sort(outside.begin(), outside.end());
    outside.erase(std::unique(outside.begin(), outside.end()), outside.end());
    std::vector<LandmarkId> graph_ids = ids_;
    std::sort(graph_ids.begin(), graph_ids.end());
    outside.erase(std::remove_if(outside.begin(), outside.end(),
                                 [&](LandmarkId id) { return std::binary_search(graph_ids.begin(), graph_ids.end(), id); }),
                  outside.end());
  }
  const int u = static_cast<int>(outside.size());
  stats.conditioned = u;

  // Old state of U in the local frame, read before anything is written.
  std::vector<Landmark> u_records(u);
  std::vector<Eigen::Matrix2d> u_to_local(u);
  Eigen::VectorXd mean_u(2 * u);
  Eigen::MatrixXd cov_uo(2 * u, 2 * m), cov_uu(2 * u, 2 * u);
  std::vector<std::vector<bool>> uu_stored(u, std::vector<bool>(u, false));
  for (int a = 0; a < u; ++a) {
    u_records[a] = *map_->FindLandmark(outside[a]);
    u_to_local[a] = frame_.EnToLocal(u_records[a].position);
    mean_u.segment<2>(2 * a) = frame_.ToLocal(u_records[a].position);
    cov_uu.block<2, 2>(2 * a, 2 * a) = u_to_local[a] * u_records[a].cov_en_m2 * u_to_local[a].transpose();
    for (int k = 0; k < m; ++k) {
      cov_uo.block<2, 2>(2 * a, 2 * k) = LocalCross(outside[a], u_to_local[a], ids_[prior_index_[k]], to_local_[k]);
    }
  }
  for (int a = 0; a < u; ++a) {
    for (int b = a + 1; b < u; ++b) {
      Eigen::Matrix2d c;
      uu_stored[a][b] = map_->CrossCovariance(outside[a], outside[b], &c);
      const Eigen::Matrix2d local = uu_stored[a][b] ? Eigen::Matrix2d(u_to_local[a] * c * u_to_local[b].transpose())
                                                    : Eigen::Matrix2d::Zero();
      cov_uu.block<2, 2>(2 * a, 2 * b) = local;
      cov_uu.block<2, 2>(2 * b, 2 * a) = local.transpose();
    }
  }

  // Conditioning of U on the new estimate of O.
  Eigen::MatrixXd new_uu, new_us;
  Eigen::VectorXd new_mean_u;
  if (u > 0) {
    const Eigen::MatrixXd gain = prior_llt_.solve(cov_uo.transpose()).transpose();  // A = Sigma_UO Sigma_OO^-1
    Eigen::VectorXd delta_o(2 * m);
    Eigen::MatrixXd new_oo(2 * m, 2 * m), new_os(2 * m, 2 * n);
    for (int k = 0; k < m; ++k) {
      delta_o.segment<2>(2 * k) = positions_[prior_index_[k]] - prior_mean_.segment<2>(2 * k);
      new_os.middleRows<2>(2 * k) = cov_ss.middleRows<2>(2 * prior_index_[k]);
    }
    for (int l = 0; l < m; ++l) new_oo.middleCols<2>(2 * l) = new_os.middleCols<2>(2 * prior_index_[l]);
    new_mean_u = mean_u + gain * delta_o;
    new_us = gain * new_os;
    new_uu = cov_uu + gain * (new_oo - prior_cov_) * gain.transpose();
  }

  const int64_t version = map_->BumpVersion();
  std::vector<Eigen::Matrix2d> s_from_local(n), u_from_local(u);
  for (int i = 0; i < n; ++i) {
    const Landmark* old = map_->FindLandmark(ids_[i]);
    Landmark record = old ? *old : Landmark{};
    record.id = ids_[i];
    touch(&record);
    WriteLandmark(record, positions_[i], cov_ss.block<2, 2>(2 * i, 2 * i), version, &s_from_local[i]);
  }
  for (int a = 0; a < u; ++a) {
    WriteLandmark(u_records[a], new_mean_u.segment<2>(2 * a), new_uu.block<2, 2>(2 * a, 2 * a), version,
                  &u_from_local[a]);
  }
  if (!options.correlated) {
    stats.covariance_ms = MillisecondsSince(start);
    return stats;
  }

  // Cross blocks: kept where one was stored before or the pair lies within the radius.
  const double radius = options.correlation_radius_m;
  auto keep = [&](LandmarkId a, const Eigen::Vector2d& pa, LandmarkId b, const Eigen::Vector2d& pb) {
    Eigen::Matrix2d unused;
    return WithinCorrelationRadius(pa, pb, radius) || map_->CrossCovariance(a, b, &unused);
  };
  for (int i = 0; i < n; ++i) {
    for (int j = i + 1; j < n; ++j) {
      if (!keep(ids_[i], positions_[i], ids_[j], positions_[j])) continue;
      map_->PutCrossCovariance(ids_[i], ids_[j],
                               s_from_local[i] * cov_ss.block<2, 2>(2 * i, 2 * j) * s_from_local[j].transpose());
    }
  }
  for (int a = 0; a < u; ++a) {
    const Eigen::Vector2d pa = new_mean_u.segment<2>(2 * a);
    for (int i = 0; i < n; ++i) {
      if (!keep(outside[a], pa, ids_[i], positions_[i])) continue;
      map_->PutCrossCovariance(outside[a], ids_[i],
                               u_from_local[a] * new_us.block<2, 2>(2 * a, 2 * i) * s_from_local[i].transpose());
    }
    for (int b = a + 1; b < u; ++b) {
      if (!uu_stored[a][b] && !WithinCorrelationRadius(pa, new_mean_u.segment<2>(2 * b), radius)) continue;
      map_->PutCrossCovariance(outside[a], outside[b],
                               u_from_local[a] * new_uu.block<2, 2>(2 * a, 2 * b) * u_from_local[b].transpose());
    }
  }
  stats.covariance_ms = MillisecondsSince(start);
  return stats;
}

}  // namespace crowdmap
