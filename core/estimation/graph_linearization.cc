#include "core/estimation/graph_linearization.h"

#include <algorithm>
#include <chrono>
#include <unordered_set>

#include "core/estimation/factors.h"
#include "core/map/dense_kernels.h"

namespace crowdmap {

absl::StatusOr<LandmarkInformation> EliminateToLandmarks(ceres::Problem* problem,
                                                         const std::vector<ceres::ResidualBlockId>& residuals,
                                                         const std::vector<double*>& landmarks) {
  std::vector<double*> ordered, blocks;
  std::unordered_map<const double*, bool> seen;
  for (double* block : landmarks) seen[block] = true;
  for (ceres::ResidualBlockId id : residuals) {
    problem->GetParameterBlocksForResidualBlock(id, &blocks);
    for (double* block : blocks) {
      if (seen.emplace(block, true).second) ordered.push_back(block);
    }
  }
  int nx = 0;
  for (double* block : ordered) nx += problem->ParameterBlockSize(block);
  int nl = 0;
  for (double* block : landmarks) nl += problem->ParameterBlockSize(block);
  ordered.insert(ordered.end(), landmarks.begin(), landmarks.end());

  ceres::Problem::EvaluateOptions evaluate;
  evaluate.parameter_blocks = ordered;
  evaluate.residual_blocks = residuals;
  evaluate.num_threads = 1;
  std::vector<double> r;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(evaluate, nullptr, &r, nullptr, &crs)) {
    return absl::InternalError("landmark information: the Jacobian could not be evaluated");
  }
  const Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>> jacobian(
      crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
      crs.values.data());
  const Eigen::SparseMatrix<double> jt = jacobian.transpose();
  const Eigen::SparseMatrix<double> h = jt * jacobian;
  const Eigen::VectorXd g = jt * Eigen::Map<const Eigen::VectorXd>(r.data(), static_cast<int>(r.size()));
  LandmarkInformation out;
  out.information = Eigen::MatrixXd(h.bottomRightCorner(nl, nl));
  out.gradient = g.tail(nl);
  if (nx > 0) {
    Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> a_llt(h.topLeftCorner(nx, nx));
    if (a_llt.info() != Eigen::Success) {
      return absl::InternalError("landmark information: the eliminated blocks are rank deficient");
    }
    const Eigen::MatrixXd b = Eigen::MatrixXd(h.topRightCorner(nx, nl));
    const Eigen::MatrixXd w = a_llt.solve(b);
    out.information -= b.transpose() * w;
    out.gradient -= w.transpose() * g.head(nx);
  }
  out.information = 0.5 * (out.information + out.information.transpose());
  return out;
}

absl::StatusOr<GraphLinearization> GraphLinearization::Compute(
    ceres::Problem* problem, const std::vector<double*>& landmarks,
    const std::vector<ceres::ResidualBlockId>& factor_leaves_out) {
  std::vector<ceres::ResidualBlockId> residuals;
  problem->GetResidualBlocks(&residuals);
  absl::StatusOr<GraphLinearization> g = ComputeOver(problem, landmarks, residuals);
  if (!g.ok() || factor_leaves_out.empty()) return g;
  if (factor_leaves_out.size() == 1) g->factor_ = g->WithoutScalarPrior(problem, factor_leaves_out[0]);
  if (!g->factor_) {
    const auto left_out = [&](ceres::ResidualBlockId id) {
      return std::find(factor_leaves_out.begin(), factor_leaves_out.end(), id) != factor_leaves_out.end();
    };
    residuals.erase(std::remove_if(residuals.begin(), residuals.end(), left_out), residuals.end());
    absl::StatusOr<GraphLinearization> without = ComputeOver(problem, landmarks, residuals);
    if (!without.ok()) return without.status();
    g->factor_ = LandmarkMarginal{without->sigma_ll_, without->landmark_gradient_};
  }
  return g;
}

std::optional<GraphLinearization::LandmarkMarginal> GraphLinearization::WithoutScalarPrior(
    ceres::Problem* problem, ceres::ResidualBlockId prior) const {
  std::vector<double*> blocks;
  problem->GetParameterBlocksForResidualBlock(prior, &blocks);
  if (blocks.size() != 1 || problem->ParameterBlockSize(blocks[0]) != 1) return std::nullopt;
  if (problem->GetCostFunctionForResidualBlock(prior)->num_residuals() != 1) return std::nullopt;
  const auto at = offset_.find(blocks[0]);
  if (at == offset_.end() || at->second >= other_dim_) return std::nullopt;
  const int u = at->second;
  // The prior's share of H and of the gradient: p at (u, u), q at u.
  double residual = 0.0, derivative = 0.0;
  double* jacobians[] = {&derivative};
  if (!problem->EvaluateResidualBlock(prior, /*apply_loss_function=*/true, nullptr, &residual, jacobians)) {
    return std::nullopt;
  }
  const double p = derivative * derivative, q = derivative * residual;
  // A' = A - p e e^T:  A'^-1 = A^-1 + k A^-1 e e^T A^-1,  k = p / (1 - p a),  a = (A^-1)_uu.
  Eigen::VectorXd unit = Eigen::VectorXd::Zero(other_dim_);
  unit(u) = 1.0;
  const Eigen::VectorXd a_inv_e = a_llt_->solve(unit);
  const double a = a_inv_e(u), h = a_inv_e.dot(other_gradient_);
  constexpr double kMinRemaining = 1e-9;  // of the information, what the rest must keep
  if (!(1.0 - p * a > kMinRemaining)) return std::nullopt;
  const double k = p / (1.0 - p * a);
  // S' = S - k w w^T (w: row u of A^-1 B), inverted by Sherman-Morrison again.
  const Eigen::VectorXd w = w_.row(u).transpose();
  const Eigen::VectorXd sigma_w = sigma_ll_ * w;
  const double t = w.dot(sigma_w);
  if (!(1.0 - k * t > kMinRemaining)) return std::nullopt;
  LandmarkMarginal out;
  out.covariance = sigma_ll_ + (k / (1.0 - k * t)) * sigma_w * sigma_w.transpose();
  out.covariance = 0.5 * (out.covariance + out.covariance.transpose()).eval();
  // gradient' = g_L - W'^T (g_x - q e), W' = A'^-1 B.
  out.gradient = landmark_gradient_ + (q - k * (h - q * a)) * w;
  if (!out.covariance.allFinite() || !out.gradient.allFinite()) return std::nullopt;
  return out;
}

namespace {

// `id`'s cost when it is a LandmarkPriorFactor on landmarks of `landmarks` alone, else nullptr.
const LandmarkPriorFactor* LandmarkPriorOn(ceres::Problem* problem, ceres::ResidualBlockId id,
                                           const std::unordered_set<const double*>& landmarks,
                                           std::vector<double*>* blocks) {
  const auto* prior = dynamic_cast<const LandmarkPriorFactor*>(problem->GetCostFunctionForResidualBlock(id));
  if (prior == nullptr) return nullptr;
  problem->GetParameterBlocksForResidualBlock(id, blocks);
  for (const double* block : *blocks) {
    if (landmarks.count(block) == 0) return nullptr;
  }
  return prior;
}

}  // namespace

absl::StatusOr<GraphLinearization> GraphLinearization::ComputeOver(ceres::Problem* problem,
                                                                    const std::vector<double*>& landmarks,
                                                                    std::vector<ceres::ResidualBlockId> residual_blocks) {
  GraphLinearization g;
  // Priors on the landmarks alone (the map's CC prior: one block, dense over every map landmark
  // of the graph) are linear and add to the landmarks' dense block only, so they are added there
  // directly: as rows of the sparse Jacobian, their share of J^T J cost more than all the other
  // residuals' (Eigen's sparse product). The Jacobian's rows are the other residuals'.
  const std::unordered_set<const double*> landmark_set(landmarks.begin(), landmarks.end());
  std::vector<std::pair<const LandmarkPriorFactor*, std::vector<double*>>> dense_priors;
  std::vector<double*> prior_blocks;
  for (ceres::ResidualBlockId id : residual_blocks) {
    if (const LandmarkPriorFactor* prior = LandmarkPriorOn(problem, id, landmark_set, &prior_blocks)) {
      dense_priors.emplace_back(prior, prior_blocks);
    } else {
      g.residuals_.push_back(id);
    }
  }
  // The other blocks in the order the residuals first use them (the order they were added in),
  // then any no residual uses. Not GetParameterBlocks' order: that is by address, which differs
  // from run to run (a pose vector on the heap, a yaw state on the stack), and with it the
  // rounding of the sparse factorisation below.
  std::vector<double*> all, blocks;
  for (ceres::ResidualBlockId id : residual_blocks) {
    problem->GetParameterBlocksForResidualBlock(id, &blocks);
    all.insert(all.end(), blocks.begin(), blocks.end());
  }
  std::vector<double*> unused;
  problem->GetParameterBlocks(&unused);
  all.insert(all.end(), unused.begin(), unused.end());
  std::unordered_set<const double*> placed(landmarks.begin(), landmarks.end());
  for (double* block : all) {
    if (!placed.insert(block).second) continue;
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

  ceres::Problem::EvaluateOptions evaluate;
  evaluate.parameter_blocks = g.ordered_;
  evaluate.residual_blocks = g.residuals_;
  evaluate.num_threads = 1;
  ceres::CRSMatrix crs;
  std::vector<double> residuals;
  if (!problem->Evaluate(evaluate, nullptr, &residuals, nullptr, &crs)) {
    return absl::InternalError("graph linearization: the Jacobian could not be evaluated");
  }
  const Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>> jacobian(
      crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
      crs.values.data());
  g.jt_ = jacobian.transpose();
  g.residual_rows_.reserve(g.residuals_.size());
  for (int k = 0, row = 0; k < static_cast<int>(g.residuals_.size()); ++k) {
    g.residual_rows_.push_back(row);
    row += problem->GetCostFunctionForResidualBlock(g.residuals_[k])->num_residuals();
  }
  const Eigen::SparseMatrix<double> h = g.jt_ * jacobian;
  const int nx = g.other_dim_, nl = g.landmark_dim_;
  g.b_ = h.topRightCorner(nx, nl);
  Eigen::MatrixXd schur = Eigen::MatrixXd(h.bottomRightCorner(nl, nl));
  // The gradient J^T r; with the other blocks eliminated below, zero at an exact optimum.
  Eigen::VectorXd gradient =
      g.jt_ * Eigen::Map<const Eigen::VectorXd>(residuals.data(), static_cast<int>(residuals.size()));
  for (const auto& [prior, prior_blocks] : dense_priors) {
    // Residual S (x - mean): information S^T S, gradient S^T r, at the landmarks' columns.
    std::vector<int> columns;
    Eigen::VectorXd x(prior->mean().size());
    for (size_t k = 0; k < prior_blocks.size(); ++k) {
      const int at = g.offset_.at(prior_blocks[k]) - nx;
      columns.push_back(at);
      columns.push_back(at + 1);
      x.segment<2>(2 * static_cast<int>(k)) = Eigen::Map<const Eigen::Vector2d>(prior_blocks[k]);
    }
    const Eigen::MatrixXd& s = prior->sqrt_info();
    Eigen::MatrixXd lower = Eigen::MatrixXd::Zero(s.cols(), s.cols());
    AddGramLower(s, lower);
    const Eigen::MatrixXd information = lower.selfadjointView<Eigen::Lower>();
    schur(columns, columns) += information;
    gradient.tail(nl)(columns) += s.transpose() * (s * (x - prior->mean()));
  }
  if (nx > 0) {
    g.a_llt_ = std::make_unique<Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>>(h.topLeftCorner(nx, nx));
    if (g.a_llt_->info() != Eigen::Success) {
      return absl::InternalError("landmark covariance could not be computed (pose block rank deficient)");
    }
    g.w_ = SolveManyColumns(*g.a_llt_, Eigen::MatrixXd(g.b_));
    schur -= g.b_.transpose() * g.w_;
  } else {
    g.w_ = Eigen::MatrixXd::Zero(0, nl);
  }
  g.other_gradient_ = gradient.head(nx);
  g.landmark_gradient_ = gradient.tail(nl) - g.w_.transpose() * g.other_gradient_;
  g.s_llt_.compute(schur);
  if (g.s_llt_.info() != Eigen::Success) {
    // A property of the passage's data (a subgraph whose fixes or rays do not pin its landmarks
    // down), not a fault to retry: the service quarantines the passage.
    return absl::FailedPreconditionError(
        "landmark covariance could not be computed: the (sub)graph's measurements do not determine its landmarks");
  }
  const Eigen::MatrixXd cov = g.s_llt_.solve(Eigen::MatrixXd::Identity(nl, nl));
  if (!cov.allFinite()) return absl::InternalError("landmark covariance is not finite");
  g.sigma_ll_ = 0.5 * (cov + cov.transpose());
  return g;
}

GraphLinearization::ScalarMarginal GraphLinearization::MarginalVariance(const double* block) const {
  const int u = offset_.at(block);
  Eigen::VectorXd unit = Eigen::VectorXd::Zero(other_dim_);
  unit(u) = 1.0;
  ScalarMarginal m;
  m.given_landmarks = a_llt_->solve(unit)(u);
  m.from_landmarks = w_.row(u).dot(sigma_ll_ * w_.row(u).transpose());
  return m;
}

double GraphLinearization::Sigma(int u, int v) const {
  if (u >= other_dim_ && v >= other_dim_) return sigma_ll_(u - other_dim_, v - other_dim_);
  if (u >= other_dim_) std::swap(u, v);
  if (v >= other_dim_) return -w_sigma_(u, v - other_dim_);  // Sigma_xL = -A^-1 B Sigma_LL
  return (*a_inv_)(u, v) + w_sigma_.row(u).dot(w_.row(v));  // A^-1 + W Sigma_LL W^T
}

void GraphLinearization::PrepareSigma() {
  if (sigma_ready_) return;
  if (other_dim_ > 0) a_inv_ = std::make_unique<SelectedInverse>(*a_llt_);
  w_sigma_ = w_ * sigma_ll_;
  sigma_ready_ = true;
}

Eigen::MatrixXd GraphLinearization::SigmaOver(const std::vector<int>& columns) const {
  const int n = static_cast<int>(columns.size());
  Eigen::MatrixXd cov(n, n);
  for (int u = 0; u < n; ++u) {
    for (int v = 0; v <= u; ++v) cov(u, v) = cov(v, u) = Sigma(columns[u], columns[v]);
  }
  return cov;
}

std::unordered_map<ceres::ResidualBlockId, double> GraphLinearization::Redundancies() {
  PrepareSigma();
  std::unordered_map<ceres::ResidualBlockId, double> out;
  out.reserve(residual_rows_.size());
  std::vector<int> columns;
  for (size_t k = 0; k < residual_rows_.size(); ++k) {
    const int first = residual_rows_[k], rows = (k + 1 < residual_rows_.size() ? residual_rows_[k + 1]
                                                                                : static_cast<int>(jt_.cols())) - first;
    // The block's columns: the union of its rows' non-zeros (each row of J is a column of J^T).
    columns.clear();
    for (int r = first; r < first + rows; ++r) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(jt_, r); it; ++it) {
        columns.push_back(static_cast<int>(it.row()));
      }
    }
    std::sort(columns.begin(), columns.end());
    columns.erase(std::unique(columns.begin(), columns.end()), columns.end());
    Eigen::MatrixXd j = Eigen::MatrixXd::Zero(rows, static_cast<int>(columns.size()));
    for (int r = 0; r < rows; ++r) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(jt_, first + r); it; ++it) {
        j(r, std::lower_bound(columns.begin(), columns.end(), static_cast<int>(it.row())) - columns.begin()) =
            it.value();
      }
    }
    // tr(J_k Sigma J_k^T): the part of the block's residuals the estimate absorbs.
    out.emplace(residuals_[k], rows - (j * SigmaOver(columns)).cwiseProduct(j).sum());
  }
  return out;
}

absl::Status GraphLinearization::CorrectSecondOrderBias(ceres::Problem* problem, BiasCorrectionStats* stats) {
  const auto start = std::chrono::steady_clock::now();
  PrepareSigma();

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
    Eigen::LLT<Eigen::MatrixXd> root(SigmaOver(index));
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
