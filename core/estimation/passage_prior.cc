#include "core/estimation/passage_prior.h"

#include <unordered_set>

#include "absl/strings/str_cat.h"
#include "core/map/dense_kernels.h"

namespace crowdmap {
namespace {

Eigen::MatrixXd Symmetrized(const Eigen::MatrixXd& m) { return 0.5 * (m + m.transpose()); }

// The rows (2 per landmark) of `positions` (landmark indices).
std::vector<int> Rows(const std::vector<int>& positions) {
  std::vector<int> rows;
  rows.reserve(2 * positions.size());
  for (int p : positions) {
    rows.push_back(2 * p);
    rows.push_back(2 * p + 1);
  }
  return rows;
}

}  // namespace

PassagePrior::PassagePrior(MapWindow window, int seen) : window_(std::move(window)), seen_(seen) {}

absl::StatusOr<PassagePrior> PassagePrior::Build(const MapReaderInterface& map, const std::vector<LandmarkId>& ids,
                                                 const MapWindowOptions& window_options) {
  std::vector<LandmarkId> seen;
  std::unordered_set<LandmarkId> unique;
  for (LandmarkId id : ids) {
    if (map.FindLandmark(id) != nullptr && unique.insert(id).second) seen.push_back(id);
  }
  absl::StatusOr<MapWindow> window = MapWindow::Build(map, seen, window_options);
  if (!window.ok()) return window.status();
  absl::StatusOr<Eigen::MatrixXd> covariance = window->Covariance(seen);
  if (!covariance.ok()) return covariance.status();
  const int p = static_cast<int>(seen.size());
  PassagePrior prior(std::move(*window), p);
  prior.ids_ = seen;
  for (int k = 0; k < p; ++k) prior.index_.emplace(seen[k], k);
  prior.mean_ = prior.window_.offsets().head(2 * p);
  prior.covariance_ = Symmetrized(*covariance);
  prior.seen_covariance_.compute(prior.covariance_);
  if (p > 0 && prior.seen_covariance_.info() != Eigen::Success) {
    return absl::FailedPreconditionError(
        absl::StrCat("map covariance of the ", p, " landmarks the passage sees is not positive definite"));
  }
  return prior;
}

absl::StatusOr<Eigen::MatrixXd> PassagePrior::Covariance(const std::vector<LandmarkId>& ids) const {
  std::vector<int> positions;
  for (LandmarkId id : ids) {
    const auto it = index_.find(id);
    if (it == index_.end()) return absl::InvalidArgumentError(absl::StrCat("landmark ", id, ": not tracked"));
    positions.push_back(it->second);
  }
  const std::vector<int> rows = Rows(positions);
  return Eigen::MatrixXd(covariance_(rows, rows));
}

absl::StatusOr<int> PassagePrior::Condition(const MapFactor& factor, int64_t version,
                                            const std::function<void(Landmark*)>& touch, MapOverlay* map) {
  const int s = static_cast<int>(factor.landmarks.size());
  // The factor's landmarks: the tracked ones O (their place in the factor and in T), the new ones.
  std::vector<int> in_factor, in_tracked, fresh;
  for (int i = 0; i < s; ++i) {
    const auto it = index_.find(factor.landmarks[i]);
    if (it == index_.end()) {
      fresh.push_back(i);
    } else {
      in_factor.push_back(i);
      in_tracked.push_back(it->second);
    }
  }
  const std::vector<int> o_rows = Rows(in_tracked), o_in_s = Rows(in_factor);
  const int o = static_cast<int>(o_rows.size());

  // S's posterior: the factor plus the map's marginal on O, whose Cholesky factor L_O (lower)
  // serves the conditioning of T below too.
  Eigen::MatrixXd l_o = covariance_(o_rows, o_rows);
  if (!CholeskyInPlace(l_o)) return absl::InternalError("map covariance of the graph is not positive definite");
  const Eigen::VectorXd mean_o = mean_(o_rows);
  Eigen::MatrixXd information = factor.information;
  Eigen::VectorXd vector = factor.information_vector;
  if (o > 0) {
    Eigen::MatrixXd prior_information = l_o;
    InverseFromCholeskyInPlace(prior_information);
    information(o_in_s, o_in_s) += prior_information;
    vector(o_in_s) += prior_information * mean_o;
  }
  const Eigen::LLT<Eigen::MatrixXd> llt(Symmetrized(information));
  if (llt.info() != Eigen::Success) return absl::InternalError("graph landmark information is not positive definite");
  const Eigen::VectorXd mean_s = llt.solve(vector);
  const Eigen::MatrixXd cov_s = Symmetrized(llt.solve(Eigen::MatrixXd::Identity(2 * s, 2 * s)));
  if (!mean_s.allFinite() || !cov_s.allFinite()) return absl::InternalError("graph landmark estimate is not finite");

  // T given O keeps its conditional, Sigma_TO Sigma_OO^-1 = Y^T L_O^-1 with Y = L_O^-1 Sigma_OT:
  //   mean_T += Y^T L_O^-1 (mean'_O - mean_O),
  //   Sigma_TT -= Y^T (I - L_O^-1 Sigma'_OO L_O^-T) Y,  Sigma'_TS = Y^T L_O^-1 Sigma'_OS.
  // The products over T (t x t and t x 2s) are BLAS's (dense_kernels.h).
  const int t = static_cast<int>(mean_.size());
  Eigen::MatrixXd cross = Eigen::MatrixXd::Zero(t, 2 * s);  // Sigma'_TS
  if (o > 0) {
    Eigen::MatrixXd y = covariance_(o_rows, Eigen::all);
    SolveLowerInPlace(l_o, y);
    const Eigen::MatrixXd y_t = y.transpose();
    Eigen::VectorXd shift = mean_s(o_in_s) - mean_o;
    SolveLowerInPlace(l_o, shift);
    mean_ += y_t * shift;
    Eigen::MatrixXd half = cov_s(o_in_s, o_in_s);  // L_O^-1 Sigma'_OO, then its L_O^-1 (.)^T
    SolveLowerInPlace(l_o, half);
    Eigen::MatrixXd kept = half.transpose();
    SolveLowerInPlace(l_o, kept);
    kept = Eigen::MatrixXd::Identity(o, o) - Symmetrized(kept);
    Eigen::MatrixXd kept_y, shrink;
    Multiply(kept, y, &kept_y);
    Multiply(y_t, kept_y, &shrink);
    covariance_ = Symmetrized(covariance_ - shrink);
    Eigen::MatrixXd to_s = cov_s(o_in_s, Eigen::all);
    SolveLowerInPlace(l_o, to_s);
    Multiply(y_t, to_s, &cross);
  }
  // New landmarks join T; S's own rows are its posterior.
  const int added = static_cast<int>(fresh.size());
  ids_.reserve(ids_.size() + added);
  std::vector<int> s_in_tracked(s);
  for (size_t k = 0; k < in_factor.size(); ++k) s_in_tracked[in_factor[k]] = in_tracked[k];
  for (int i : fresh) {
    s_in_tracked[i] = static_cast<int>(ids_.size());
    index_.emplace(factor.landmarks[i], s_in_tracked[i]);
    ids_.push_back(factor.landmarks[i]);
  }
  const int grown = t + 2 * added;
  mean_.conservativeResize(grown);
  covariance_.conservativeResize(grown, grown);
  const std::vector<int> s_rows = Rows(s_in_tracked);
  covariance_(Eigen::seqN(0, t), s_rows) = cross;
  covariance_(s_rows, Eigen::seqN(0, t)) = cross.transpose();
  covariance_(s_rows, s_rows) = cov_s;
  mean_(s_rows) = mean_s;

  std::vector<bool> in_s(ids_.size(), false);
  for (int k : s_in_tracked) in_s[k] = true;
  int conditioned = 0;
  for (size_t k = 0; k < ids_.size(); ++k) {
    const int r = static_cast<int>(2 * k);
    absl::StatusOr<Landmark> found = LandmarkStillThere(*map, ids_[k]);
    if (!found.ok()) return found.status();
    Landmark& record = *found;
    // Against the stored estimate: a bounded window's own solve may have moved it already.
    if (!in_s[k] && (mean_.segment<2>(r) - record.Offset()).norm() < kMinWrittenChangeM) continue;
    record.position = LocalFrame(record.anchor).ToGeo(mean_.segment<2>(r));
    record.cov_en_m2 = covariance_.block<2, 2>(r, r);
    record.version = version;
    if (in_s[k]) {
      touch(&record);
    } else {
      ++conditioned;
    }
    map->PutLandmark(record);
  }
  return conditioned;
}

absl::StatusOr<int> PassagePrior::Finish(int64_t version, MapOverlay* map) const {
  const std::vector<LandmarkId>& window_ids = window_.landmarks();
  if (window_ids.size() == static_cast<size_t>(seen_)) return 0;
  const Eigen::VectorXd change = mean_.head(2 * seen_) - window_.offsets().head(2 * seen_);
  const std::vector<LandmarkId> seen(ids_.begin(), ids_.begin() + seen_);
  absl::StatusOr<Eigen::VectorXd> moved = window_.CovarianceTimes(seen, seen_covariance_.solve(change));
  if (!moved.ok()) return moved.status();
  int conditioned = 0;
  for (size_t w = seen_; w < window_ids.size(); ++w) {
    const Eigen::Vector2d offset = window_.offsets().segment<2>(2 * w) + moved->segment<2>(2 * w);
    absl::StatusOr<Landmark> found = LandmarkStillThere(*map, window_ids[w]);
    if (!found.ok()) return found.status();
    Landmark& record = *found;
    if ((offset - record.Offset()).norm() < kMinWrittenChangeM) continue;
    record.position = LocalFrame(record.anchor).ToGeo(offset);
    record.version = version;
    map->PutLandmark(record);
    ++conditioned;
  }
  return conditioned;
}

}  // namespace crowdmap
