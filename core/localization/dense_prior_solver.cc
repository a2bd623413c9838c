#include "core/localization/dense_prior_solver.h"

#include <algorithm>
#include <cmath>
#include <limits>

#if defined(__SSE2__)
#include <xmmintrin.h>
#endif

#include <Eigen/Cholesky>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/localization/pose_covariance.h"
#include "core/map/dense_kernels.h"

namespace crowdmap {
namespace {

using SparseMatrix = Eigen::SparseMatrix<double>;
using RowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Flushes subnormal numbers to zero while in scope. A^-1 B along a chain of a thousand poses decays
// below 1e-308 far from each landmark's poses, and arithmetic on subnormals is many times slower
// (it took most of the solve); what is flushed is below any tolerance.
class FlushSubnormals {
 public:
#if defined(__SSE2__)
  FlushSubnormals() : csr_(_mm_getcsr()) { _mm_setcsr(csr_ | kFlushToZero | kDenormalsAreZero); }
  ~FlushSubnormals() { _mm_setcsr(csr_); }

 private:
  static constexpr unsigned kFlushToZero = 0x8000, kDenormalsAreZero = 0x0040;
  unsigned csr_;
#endif
};

// Solves L L^T X = Y in place for many right-hand sides (the columns of `x`, Y on entry), L a
// sparse Cholesky factor: the substitutions run down L's columns and update whole rows of X,
// contiguous in memory (Eigen's sparse solves take one right-hand side at a time).
void SolveManyInPlace(const SparseMatrix& l, RowMatrix* x) {
  const FlushSubnormals flush;
  const int n = static_cast<int>(l.cols());
  for (int j = 0; j < n; ++j) {  // L Z = Y
    x->row(j) /= l.coeff(j, j);
    for (SparseMatrix::InnerIterator it(l, j); it; ++it) {
      if (it.row() > j) x->row(it.row()) -= it.value() * x->row(j);
    }
  }
  for (int j = n - 1; j >= 0; --j) {  // L^T X = Z
    for (SparseMatrix::InnerIterator it(l, j); it; ++it) {
      if (it.row() > j) x->row(j) -= it.value() * x->row(it.row());
    }
    x->row(j) /= l.coeff(j, j);
  }
}

// L^-1 for the lower triangle L of `factor` (CholeskyInPlace's), zero above the diagonal.
Eigen::MatrixXd LowerInverse(const Eigen::MatrixXd& factor) {
  Eigen::MatrixXd out = factor;
  LowerInverseInPlace(out);
  out.triangularView<Eigen::StrictlyUpper>().setZero();
  return out;
}

// The Gauss-Newton information at one point, poses eliminated: H = [A B; B^T C], C = D + prior
// information, factorised as A (sparse Cholesky, P A P^T = L L^T), W = A^-1 B and S = C - B^T W
// (dense Cholesky). The pose rows of B and W are kept in the factor's order (P B, P W): the large
// dense blocks are then built and solved in place, never permuted or copied (fresh pages cost
// more than the arithmetic on them here).
class Linearization {
 public:
  // `jacobian`: poses' columns first (np of them), then the landmarks'.
  absl::Status Factorize(const SparseMatrix& jacobian, int np, const Eigen::MatrixXd& prior_information) {
    const int nl = static_cast<int>(jacobian.cols()) - np;
    const SparseMatrix jp = jacobian.leftCols(np), jl = jacobian.rightCols(nl);
    const SparseMatrix jpt = jp.transpose();
    const SparseMatrix a = jpt * jp;
    a_llt_.compute(a);
    if (a_llt_.info() != Eigen::Success) {
      return absl::FailedPreconditionError("localization: the pose chain's information is rank deficient");
    }
    l_ = a_llt_.matrixL();
    pb_ = a_llt_.permutationP() * SparseMatrix(jpt * jl);
    pw_ = pb_;
    SolveManyInPlace(l_, &pw_);
    s_ = prior_information;
    s_ += SparseMatrix(jl.transpose() * jl);
    s_.noalias() -= pb_.transpose() * pw_;
    if (!CholeskyInPlace(s_)) {
      return absl::FailedPreconditionError("localization: the landmarks are not observable");
    }
    return absl::OkStatus();
  }

  // The Gauss-Newton step -H^-1 g.
  Eigen::VectorXd Step(const Eigen::VectorXd& gradient) const {
    const int np = static_cast<int>(pw_.rows()), nl = static_cast<int>(pw_.cols());
    const Eigen::VectorXd p_a_inv_gp = a_llt_.permutationP() * a_llt_.solve(gradient.head(np));
    Eigen::VectorXd step(np + nl);
    Eigen::VectorXd landmarks = pb_.transpose() * p_a_inv_gp - gradient.tail(nl);
    s_.triangularView<Eigen::Lower>().solveInPlace(landmarks);
    s_.triangularView<Eigen::Lower>().transpose().solveInPlace(landmarks);
    step.tail(nl) = landmarks;
    step.head(np) = a_llt_.permutationPinv() * (-p_a_inv_gp - pw_ * step.tail(nl));
    return step;
  }

  // The marginal variance of the dense part's entry i: (S^-1)_ii = |L^-1 e_i|^2.
  double DenseVariance(int i) const {
    Eigen::VectorXd unit = Eigen::VectorXd::Unit(s_.rows(), i);
    s_.triangularView<Eigen::Lower>().solveInPlace(unit);
    return unit.squaredNorm();
  }

  // Marginal covariance of each pose: (A^-1)_kk + (Z Z^T)_kk with Z = A^-1 B L^-T (S = L L^T).
  std::vector<Eigen::Matrix3d> PoseCovariances() const {
    const int np = static_cast<int>(pw_.rows()), nl = static_cast<int>(pw_.cols());
    std::vector<Eigen::Matrix3d> out = PoseBlocksOfInverse(a_llt_, np / 3);
    if (nl == 0) return out;
    const Eigen::MatrixXd l_inverse = LowerInverse(s_);
    RowMatrix pz = pb_ * l_inverse.transpose();
    SolveManyInPlace(l_, &pz);
    const Eigen::VectorXi& p = a_llt_.permutationP().indices();
    for (int k = 0; k < np / 3; ++k) {
      Eigen::Matrix<double, 3, Eigen::Dynamic> zk(3, nl);
      for (int i = 0; i < 3; ++i) zk.row(i) = pz.row(p[3 * k + i]);
      out[k].noalias() += zk * zk.transpose();
    }
    return out;
  }

 private:
  Eigen::SimplicialLLT<SparseMatrix> a_llt_;
  SparseMatrix l_;  // a_llt_'s factor
  SparseMatrix pb_;
  RowMatrix pw_;
  Eigen::MatrixXd s_;  // S, then its Cholesky factor L (lower triangle)
};

}  // namespace

absl::Status DensePriorSolverOptions::Validate() const {
  if (max_iterations < 1) return absl::InvalidArgumentError("max_iterations: must be >= 1");
  if (!(step_tolerance > 0.0)) return absl::InvalidArgumentError("step_tolerance: must be > 0");
  if (!(covariance_tolerance_m >= 0.0)) return absl::InvalidArgumentError("covariance_tolerance_m: must be >= 0");
  if (!(covariance_tolerance_rad >= 0.0)) return absl::InvalidArgumentError("covariance_tolerance_rad: must be >= 0");
  return absl::OkStatus();
}

std::string DensePriorSolution::Brief() const {
  return absl::StrFormat("cost=%.6g iterations=%d factorizations=%d", cost, iterations, factorizations);
}

absl::StatusOr<DensePriorSolution> SolveWithDensePrior(ceres::Problem* problem, std::vector<Pose2>* poses,
                                                       const std::vector<double*>& landmarks,
                                                       const DenseLandmarkPrior& prior,
                                                       const DensePriorSolverOptions& options,
                                                       const std::vector<double*>& angles) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const int np = 3 * static_cast<int>(poses->size()), nl = 2 * static_cast<int>(landmarks.size());
  const int nd = nl + static_cast<int>(angles.size());  // the dense part: landmarks, then angles
  if (prior.mean.size() != nl || prior.cov.rows() != nl || prior.cov.cols() != nl) {
    return absl::InvalidArgumentError(absl::StrCat("dense prior: mean and covariance must have ", nl, " entries"));
  }
  Eigen::MatrixXd prior_information = prior.cov;
  if (!CholeskyInPlace(prior_information)) {
    return absl::FailedPreconditionError("localization: the map covariance is not positive definite");
  }
  InverseFromCholeskyInPlace(prior_information);
  // The dense part's prior information: the angles' priors are in the problem.
  Eigen::MatrixXd dense_prior_information = Eigen::MatrixXd::Zero(nd, nd);
  dense_prior_information.topLeftCorner(nl, nl) = prior_information;

  ceres::Problem::EvaluateOptions evaluate;
  for (Pose2& p : *poses) evaluate.parameter_blocks.push_back(p.data());
  for (double* l : landmarks) evaluate.parameter_blocks.push_back(l);
  for (double* a : angles) evaluate.parameter_blocks.push_back(a);
  evaluate.num_threads = 1;
  auto state = [&]() {
    Eigen::VectorXd x(np + nd);
    for (int k = 0; k < np / 3; ++k) x.segment<3>(3 * k) = (*poses)[k];
    for (int k = 0; k < nl / 2; ++k) x.segment<2>(np + 2 * k) = Eigen::Map<const Eigen::Vector2d>(landmarks[k]);
    for (size_t k = 0; k < angles.size(); ++k) x[np + nl + k] = *angles[k];
    return x;
  };
  auto set_state = [&](const Eigen::VectorXd& x) {
    for (int k = 0; k < np / 3; ++k) (*poses)[k] = x.segment<3>(3 * k);
    for (int k = 0; k < nl / 2; ++k) {
      Eigen::Map<Eigen::Vector2d> landmark(landmarks[k]);
      landmark = x.segment<2>(np + 2 * k);
    }
    for (size_t k = 0; k < angles.size(); ++k) *angles[k] = x[np + nl + k];
  };
  // Cost and gradient at the current state, prior included; the Jacobian when asked.
  auto evaluate_at = [&](double* cost, Eigen::VectorXd* gradient, SparseMatrix* jacobian) -> absl::Status {
    std::vector<double> g;
    ceres::CRSMatrix crs;
    if (!problem->Evaluate(evaluate, cost, nullptr, gradient ? &g : nullptr, jacobian ? &crs : nullptr)) {
      return absl::InternalError("localization: the residuals could not be evaluated");
    }
    const Eigen::VectorXd offset = state().segment(np, nl) - prior.mean;
    const Eigen::VectorXd prior_gradient = prior_information * offset;
    *cost += 0.5 * offset.dot(prior_gradient);
    if (gradient) {
      *gradient = Eigen::Map<const Eigen::VectorXd>(g.data(), np + nd);
      gradient->segment(np, nl) += prior_gradient;
    }
    if (jacobian) {
      *jacobian = Eigen::Map<const Eigen::SparseMatrix<double, Eigen::RowMajor>>(
          crs.num_rows, crs.num_cols, static_cast<int>(crs.values.size()), crs.rows.data(), crs.cols.data(),
          crs.values.data());
    }
    return absl::OkStatus();
  };

  DensePriorSolution out;
  Linearization linearization;
  double cost = 0.0;
  Eigen::VectorXd gradient;
  if (absl::Status s = evaluate_at(&cost, &gradient, nullptr); !s.ok()) return s;
  bool relinearize = true;
  bool fresh = false;  // the linearisation is at the current state
  Eigen::VectorXd linearized_at;
  // Whether the linearisation counts as taken at the current state.
  auto near = [&]() {
    const Eigen::VectorXd moved = (state() - linearized_at).cwiseAbs();
    for (int i = 0; i < np + nd; ++i) {
      const bool angle = (i < np && i % 3 == 2) || i >= np + nl;
      if (moved[i] > (angle ? options.covariance_tolerance_rad : options.covariance_tolerance_m)) return false;
    }
    return true;
  };
  double previous_step = 0.0;
  for (; out.iterations < options.max_iterations; ++out.iterations) {
    if (relinearize) {
      SparseMatrix jacobian;
      if (absl::Status s = evaluate_at(&cost, &gradient, &jacobian); !s.ok()) return s;
      if (absl::Status s = linearization.Factorize(jacobian, np, dense_prior_information); !s.ok()) return s;
      ++out.factorizations;
      linearized_at = state();
      relinearize = false;
      fresh = true;
    }
    const Eigen::VectorXd step = linearization.Step(gradient);
    const double step_size = step.lpNorm<Eigen::Infinity>();
    const bool converged = step_size <= options.step_tolerance;
    if (!fresh) {
      const bool here = near();
      if (converged && here) break;
      // A chord step that has converged (the covariance wants the information here), or that
      // converges slowly from a linearisation elsewhere (or very slowly): linearise here.
      const double rate = step_size / previous_step;
      relinearize = converged || rate > 0.5 || (rate > 0.25 && !here);
    }
    if (relinearize) continue;
    // The step, halved while it increases the cost (from a fresh linearisation; a stale one is
    // renewed instead).
    const Eigen::VectorXd x = state();
    double new_cost = 0.0;
    Eigen::VectorXd new_gradient;
    bool decreased = false;
    double scale = 1.0;
    for (int halving = 0; halving < 30 && !decreased; ++halving, scale *= 0.5) {
      set_state(x + scale * step);
      // A step that takes a landmark behind a camera cannot be evaluated: as if the cost rose.
      if (!evaluate_at(&new_cost, &new_gradient, nullptr).ok()) new_cost = std::numeric_limits<double>::infinity();
      decreased = std::isfinite(new_cost) && (new_cost <= cost + 1e-12 * std::abs(cost) || converged);
      if (!fresh) break;
    }
    if (!decreased) {
      set_state(x);
      // Measurements no pose sequence fits well enough for a descent from here: detections reported
      // under other landmarks' ids, for one; the input's doing, not the server's.
      if (fresh) {
        return absl::FailedPreconditionError(
            "localization: no Gauss-Newton step decreases the cost (detections: do they name the landmarks they "
            "saw?)");
      }
      relinearize = true;
      continue;
    }
    cost = new_cost;
    gradient = std::move(new_gradient);
    if (fresh && converged) break;
    fresh = false;
    previous_step = step_size;
  }
  out.cost = cost;
  out.pose_covariances = linearization.PoseCovariances();
  for (size_t k = 0; k < angles.size(); ++k) out.angle_variances.push_back(linearization.DenseVariance(nl + k));
  return out;
}

}  // namespace crowdmap
