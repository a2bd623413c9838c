#include "core/estimation/graph_linearization.h"

#include <algorithm>
#include <chrono>

#include "core/estimation/factors.h"

namespace crowdmap {

SelectedInverse::SelectedInverse(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor)
    : perm_(factor.permutationP().indices()), l_(factor.matrixL()) {
  l_.makeCompressed();
  const int n = static_cast<int>(l_.cols());
  const int* outer = l_.outerIndexPtr();
  const int* inner = l_.innerIndexPtr();
  const double* lv = l_.valuePtr();
  values_.assign(l_.nonZeros(), 0.0);
  // Entry (row, col), row >= col, in column col (row indices sorted, the diagonal first).
  auto at = [&](int row, int col) -> double {
    const int* it = std::lower_bound(inner + outer[col], inner + outer[col + 1], row);
    return values_[it - inner];
  };
  // L^T Sigma = L^-1, columns from the last: for i >= j on the pattern of column j,
  //   Sigma_ij = (delta_ij / L_jj - sum_{k > j} L_kj Sigma_ki) / L_jj,
  // where every Sigma_ki needed lies on the pattern (a property of Cholesky fill).
  for (int j = n - 1; j >= 0; --j) {
    const int first = outer[j], last = outer[j + 1];
    const double ljj = lv[first];
    for (int q = last - 1; q >= first; --q) {
      const int i = inner[q];
      double s = i == j ? 1.0 / ljj : 0.0;
      for (int r = first + 1; r < last; ++r) {
        const int k = inner[r];
        s -= lv[r] * (k >= i ? at(k, i) : at(i, k));
      }
      values_[q] = s / ljj;
    }
  }
}

double SelectedInverse::operator()(int i, int j) const {
  int a = perm_[i], b = perm_[j];
  if (a < b) std::swap(a, b);
  const int* begin = l_.innerIndexPtr() + l_.outerIndexPtr()[b];
  const int* end = l_.innerIndexPtr() + l_.outerIndexPtr()[b + 1];
  const int* it = std::lower_bound(begin, end, a);
  return it != end && *it == a ? values_[it - l_.innerIndexPtr()] : 0.0;
}

absl::StatusOr<GraphLinearization> GraphLinearization::Compute(ceres::Problem* problem,
                                                                const std::vector<double*>& landmarks) {
  GraphLinearization g;
  std::vector<double*> all;
  problem->GetParameterBlocks(&all);
  for (double* block : all) {
    if (std::find(landmarks.begin(), landmarks.end(), block) != landmarks.end()) continue;
    g.offset_[block] = g.other_dim_;
    g.ordered_.push_back(block);
    g.other_dim_ += problem->ParameterBlockSize(block);
  }
  int dim = g.other_dim_;
  for (double* block : landmarks) {
    g.offset_[block] = dim;
    g.ordered_.push_back(block);
    dim += 2;
  }
  g.landmark_dim_ = dim - g.other_dim_;
  problem->GetResidualBlocks(&g.residuals_);

  ceres::Problem::EvaluateOptions evaluate;
  evaluate.parameter_blocks = g.ordered_;
  evaluate.residual_blocks = g.residuals_;
  evaluate.num_threads = 1;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(evaluate, nullptr, nullptr, nullptr, &crs)) {
    return absl::InternalError("graph linearization: the Jacobian could not be evaluated");
  }
  const Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>> jacobian(
      crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
      crs.values.data());
  g.jt_ = jacobian.transpose();
  const Eigen::SparseMatrix<double> h = g.jt_ * jacobian;
  const int nx = g.other_dim_, nl = g.landmark_dim_;
  g.b_ = h.topRightCorner(nx, nl);
  Eigen::MatrixXd schur = Eigen::MatrixXd(h.bottomRightCorner(nl, nl));
  if (nx > 0) {
    g.a_llt_ = std::make_unique<Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>>(h.topLeftCorner(nx, nx));
    if (g.a_llt_->info() != Eigen::Success) {
      return absl::InternalError("landmark covariance could not be computed (pose block rank deficient)");
    }
    g.w_ = g.a_llt_->solve(Eigen::MatrixXd(g.b_));
    schur -= g.b_.transpose() * g.w_;
  } else {
    g.w_ = Eigen::MatrixXd::Zero(0, nl);
  }
  g.s_llt_.compute(schur);
  if (g.s_llt_.info() != Eigen::Success) {
    return absl::InternalError("landmark covariance could not be computed (landmarks not observable)");
  }
  const Eigen::MatrixXd cov = g.s_llt_.solve(Eigen::MatrixXd::Identity(nl, nl));
  if (!cov.allFinite()) return absl::InternalError("landmark covariance is not finite");
  g.sigma_ll_ = 0.5 * (cov + cov.transpose());
  return g;
}

double GraphLinearization::Sigma(int u, int v) const {
  if (u >= other_dim_ && v >= other_dim_) return sigma_ll_(u - other_dim_, v - other_dim_);
  if (u >= other_dim_) std::swap(u, v);
  if (v >= other_dim_) return -w_sigma_(u, v - other_dim_);  // Sigma_xL = -A^-1 B Sigma_LL
  return (*a_inv_)(u, v) + w_sigma_.row(u).dot(w_.row(v));  // A^-1 + W Sigma_LL W^T
}

absl::Status GraphLinearization::CorrectSecondOrderBias(ceres::Problem* problem, BiasCorrectionStats* stats) {
  const auto start = std::chrono::steady_clock::now();
  if (other_dim_ > 0) a_inv_ = std::make_unique<SelectedInverse>(*a_llt_);
  w_sigma_ = w_ * sigma_ll_;

  // d_k = tr(Sigma_k d2r_k) for every residual, by central differences along the Cholesky
  // columns of Sigma_k. The cost functions are evaluated directly on perturbed copies of their
  // parameters; the loss (a constant weight here: trivial or scaled) scales the residuals.
  Eigen::VectorXd d = Eigen::VectorXd::Zero(jt_.cols());
  int row = 0;
  std::vector<double*> blocks;
  std::vector<int> index;
  std::vector<std::vector<double>> values;
  std::vector<const double*> pointers;
  for (ceres::ResidualBlockId id : residuals_) {
    const ceres::CostFunction* cost = problem->GetCostFunctionForResidualBlock(id);
    const int nr = cost->num_residuals();
    if (dynamic_cast<const LandmarkPriorFactor*>(cost) != nullptr) {  // linear
      row += nr;
      continue;
    }
    problem->GetParameterBlocksForResidualBlock(id, &blocks);
    index.clear();
    values.resize(blocks.size());
    pointers.resize(blocks.size());
    for (size_t k = 0; k < blocks.size(); ++k) {
      const int size = problem->ParameterBlockSize(blocks[k]);
      values[k].assign(blocks[k], blocks[k] + size);
      pointers[k] = values[k].data();
      for (int c = 0; c < size; ++c) index.push_back(offset_.at(blocks[k]) + c);
    }
    const int nv = static_cast<int>(index.size());
    Eigen::MatrixXd cov(nv, nv);
    for (int u = 0; u < nv; ++u) {
      for (int v = 0; v <= u; ++v) cov(u, v) = cov(v, u) = Sigma(index[u], index[v]);
    }
    Eigen::LLT<Eigen::MatrixXd> root(cov);
    if (root.info() != Eigen::Success) {
      return absl::InternalError("bias correction: a covariance block is not positive definite");
    }
    const Eigen::MatrixXd l = root.matrixL();
    Eigen::VectorXd r0(nr), rp(nr), rm(nr), sum(nr);
    auto shift = [&](int column, double step) {
      int u = 0;
      for (auto& v : values) {
        for (double& x : v) x += step * l(u++, column);
      }
    };
    if (!cost->Evaluate(pointers.data(), r0.data(), nullptr)) {
      return absl::InternalError("bias correction: a residual could not be evaluated at the solution");
    }
    // Steps of one standard deviation (sigma points); where the residual is not defined there
    // (e.g. a landmark behind the camera) steps 10 and 100 times smaller; else the block is left
    // out. The second difference is exact for quadratic residuals at any step.
    bool ok = false;
    for (double h = 1.0; !ok && h >= 1e-2; h *= 0.1) {
      ok = true;
      sum.setZero();
      for (int j = 0; ok && j < nv; ++j) {
        shift(j, h);
        ok = cost->Evaluate(pointers.data(), rp.data(), nullptr);
        shift(j, -2.0 * h);
        ok = ok && cost->Evaluate(pointers.data(), rm.data(), nullptr);
        shift(j, h);
        sum += (rp + rm - 2.0 * r0) / (h * h);
      }
    }
    if (ok) {
      d.segment(row, nr) = sum;
    } else if (stats != nullptr) {
      ++stats->skipped_residual_blocks;
    }
    if (const ceres::LossFunction* loss = problem->GetLossFunctionForResidualBlock(id); loss != nullptr) {
      double rho[3];
      loss->Evaluate(r0.squaredNorm(), rho);
      d.segment(row, nr) *= std::sqrt(rho[1]);
    }
    row += nr;
  }

  // b = -1/2 H^-1 J^T d through the block elimination: bL = S^-1 (gL - W^T gx), bx = A^-1 (gx - B bL).
  const Eigen::VectorXd g = jt_ * d;
  const Eigen::VectorXd gx = g.head(other_dim_), gl = g.tail(landmark_dim_);
  const Eigen::VectorXd bl = s_llt_.solve(gl - w_.transpose() * gx);
  Eigen::VectorXd bx;
  if (other_dim_ > 0) bx = a_llt_->solve(gx - b_ * bl);
  for (double* block : ordered_) {
    const int o = offset_.at(block);
    for (int c = 0; c < problem->ParameterBlockSize(block); ++c) {
      block[c] += 0.5 * (o >= other_dim_ ? bl(o - other_dim_ + c) : bx(o + c));  // estimate - b
    }
  }
  if (stats != nullptr) {
    stats->max_landmark_shift_m = 0.0;
    for (int i = 0; i + 1 < landmark_dim_; i += 2) {
      stats->max_landmark_shift_m = std::max(stats->max_landmark_shift_m, 0.5 * bl.segment<2>(i).norm());
    }
    stats->ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  }
  return absl::OkStatus();
}

}  // namespace crowdmap
