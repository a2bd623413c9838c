#include "core/map/dense_kernels.h"

#include <algorithm>
#include <thread>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// A symmetric positive definite n x n matrix.
Eigen::MatrixXd SpdMatrix(int n, int seed) {
  std::srand(seed);
  const Eigen::MatrixXd r = Eigen::MatrixXd::Random(n, n);
  return r * r.transpose() + n * Eigen::MatrixXd::Identity(n, n);
}

double RelativeError(const Eigen::MatrixXd& got, const Eigen::MatrixXd& want) {
  return (got - want).norm() / want.norm();
}

// Every kernel on a block inside a larger matrix (an outer stride that is not the block's rows),
// against Eigen's own result.
TEST(DenseKernels, MatchEigenOnBlocksOfLargerMatrices) {
  const int n = 70, m = 45;
  const Eigen::MatrixXd a = SpdMatrix(n, 1);
  const Eigen::LLT<Eigen::MatrixXd> llt(a);
  const Eigen::MatrixXd l = llt.matrixL();

  Eigen::MatrixXd big = Eigen::MatrixXd::Constant(n + 9, n + 4, 7.0);
  big.block(3, 2, n, n) = a;
  ASSERT_TRUE(CholeskyInPlace(big.block(3, 2, n, n)));
  const Eigen::MatrixXd factor = big.block(3, 2, n, n).triangularView<Eigen::Lower>();
  EXPECT_LT(RelativeError(factor, l), 1e-13);
  EXPECT_EQ(big(2, 2), 7.0);  // outside the block: untouched

  InverseFromCholeskyInPlace(big.block(3, 2, n, n));
  EXPECT_LT(RelativeError(big.block(3, 2, n, n), a.inverse()), 1e-12);

  Eigen::MatrixXd inverse = l;
  LowerInverseInPlace(inverse);
  const Eigen::MatrixXd lower_inverse = inverse.triangularView<Eigen::Lower>();
  EXPECT_LT(RelativeError(lower_inverse, l.inverse()), 1e-12);

  const Eigen::MatrixXd x = Eigen::MatrixXd::Random(n, m);
  Eigen::MatrixXd wide = Eigen::MatrixXd::Zero(n + 5, m + 3);
  wide.block(5, 3, n, m) = x;
  SolveLowerInPlace(l, wide.block(5, 3, n, m));
  EXPECT_LT(RelativeError(wide.block(5, 3, n, m), l.triangularView<Eigen::Lower>().solve(x)), 1e-12);

  Eigen::MatrixXd gram = Eigen::MatrixXd::Identity(m, m);
  AddGramLower(wide.block(5, 3, n, m), gram);
  const Eigen::MatrixXd solved = wide.block(5, 3, n, m);
  const Eigen::MatrixXd want = Eigen::MatrixXd::Identity(m, m) + solved.transpose() * solved;
  const Eigen::MatrixXd got = gram.selfadjointView<Eigen::Lower>();
  EXPECT_LT(RelativeError(got, want), 1e-13);

  Eigen::MatrixXd product;
  Multiply(a.topRows(30), wide.block(5, 3, n, m), &product);
  EXPECT_LT(RelativeError(product, a.topRows(30) * solved), 1e-13);
}

// The eigen-decomposition of an indefinite matrix in a block of a larger one: increasing
// eigenvalues as Eigen's, orthonormal eigenvectors that rebuild the matrix from its lower triangle
// alone.
TEST(DenseKernels, SymmetricEigenRebuildsTheMatrixFromItsLowerTriangle) {
  const int n = 60;
  const Eigen::MatrixXd spd = SpdMatrix(n, 3);
  const Eigen::MatrixXd a = spd - Eigen::MatrixXd::Identity(n, n) * spd.trace() / n;  // indefinite
  Eigen::MatrixXd big = Eigen::MatrixXd::Constant(n + 4, n + 6, 7.0);
  big.block(4, 6, n, n) = a.triangularView<Eigen::Lower>();  // the upper triangle zero: not read
  Eigen::VectorXd values;
  ASSERT_TRUE(SymmetricEigenInPlace(big.block(4, 6, n, n), &values));
  EXPECT_EQ(big(3, 6), 7.0);
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> expected(a);
  EXPECT_LT(RelativeError(values, expected.eigenvalues()), 1e-13);
  EXPECT_LT(values(0), 0.0);
  EXPECT_GT(values(n - 1), 0.0);
  const Eigen::MatrixXd v = big.block(4, 6, n, n);
  EXPECT_LT(RelativeError(v.transpose() * v, Eigen::MatrixXd::Identity(n, n)), 1e-13);
  EXPECT_LT(RelativeError(v * values.asDiagonal() * v.transpose(), a), 1e-13);
}

// A rank-deficient positive semi-definite matrix off by rounding: its negative eigenvalues are
// cleared and the rest kept; a matrix with one negative eigenvalue beyond the tolerance is kept as
// it was.
TEST(DenseKernels, OnlyNegativeEigenvaluesWithinTheToleranceAreCleared) {
  const int n = 40, rank = 30;
  std::srand(5);
  const Eigen::MatrixXd r = Eigen::MatrixXd::Random(n, rank);
  const Eigen::MatrixXd psd = r * r.transpose();
  const Eigen::MatrixXd e = 1e-12 * Eigen::MatrixXd::Random(n, n);
  Eigen::MatrixXd a = psd + e + e.transpose();
  ASSERT_LT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(a).eigenvalues()(0), -1e-13);
  ASSERT_TRUE(ClipSmallNegativeEigenvalues(&a, 1e-9));
  EXPECT_EQ(a, a.transpose());
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(a).eigenvalues()(0), -1e-12);
  EXPECT_LT(RelativeError(a, psd), 1e-12);

  Eigen::MatrixXd indefinite = psd - 1e-3 * Eigen::MatrixXd::Identity(n, n);
  const Eigen::MatrixXd before = indefinite;
  EXPECT_FALSE(ClipSmallNegativeEigenvalues(&indefinite, 1e-9));
  EXPECT_EQ(indefinite, before);
}

TEST(DenseKernels, CholeskyRefusesAMatrixThatIsNotPositiveDefinite) {
  Eigen::MatrixXd a = SpdMatrix(12, 2);
  a(5, 5) = -1.0;
  EXPECT_FALSE(CholeskyInPlace(a));
}

// A positive semi-definite matrix of rank 7 (14 x 14): the pivoted Cholesky stops after 7 pivots,
// and its first 7 columns reproduce the matrix in the pivots' order.
TEST(DenseKernels, PivotedCholeskyFindsTheRankOfASemiDefiniteMatrix) {
  const int n = 14, rank = 7;
  std::srand(3);
  const Eigen::MatrixXd r = Eigen::MatrixXd::Random(n, rank);
  const Eigen::MatrixXd a = r * r.transpose();
  Eigen::MatrixXd l = a;
  std::vector<int> pivot;
  ASSERT_EQ(PivotedCholeskyInPlace(l, 1e-12 * a.diagonal().maxCoeff(), &pivot), rank);
  ASSERT_EQ(pivot.size(), static_cast<size_t>(n));
  std::vector<int> sorted = pivot;
  std::sort(sorted.begin(), sorted.end());
  for (int i = 0; i < n; ++i) EXPECT_EQ(sorted[i], i);  // a permutation, from 0
  const Eigen::MatrixXd factor = l.leftCols(rank).triangularView<Eigen::Lower>();
  const Eigen::MatrixXd permuted = a(pivot, pivot);
  EXPECT_LT(RelativeError(factor * factor.transpose(), permuted), 1e-12);
  // Pivots come largest first.
  for (int i = 1; i < rank; ++i) EXPECT_GE(l(i - 1, i - 1), l(i, i) * (1.0 - 1e-12));

  // Positive definite: every pivot is taken.
  Eigen::MatrixXd full = SpdMatrix(9, 4);
  EXPECT_EQ(PivotedCholeskyInPlace(full, 0.0, &pivot), 9);
}

TEST(DenseKernels, GramProductCanBeSubtracted) {
  const Eigen::MatrixXd x = Eigen::MatrixXd::Random(6, 4);
  Eigen::MatrixXd c = SpdMatrix(4, 5);
  const Eigen::MatrixXd want = c - x.transpose() * x;
  AddGramLower(x, c, -1.0);
  const Eigen::MatrixXd got = c.selfadjointView<Eigen::Lower>();
  EXPECT_LT(RelativeError(got, want), 1e-13);
}

// The service calls these kernels from several threads at once (the worker's update beside the
// readers' covariance reads). Debian's single-threaded OpenBLAS (libopenblas0-serial) shares its
// work buffers between callers without a lock and then returns wrong results, which the map's
// updates and reads showed as "not positive definite" under write load; the BLAS the setup
// installs must give every thread its own.
TEST(DenseKernels, ThreadsCallingAtOnceGetTheirOwnResults) {
  constexpr int kThreads = 4, kRounds = 1000, n = 96;
  std::vector<int> wrong(kThreads, 0);
  std::vector<Eigen::MatrixXd> matrices;
  for (int t = 0; t < kThreads; ++t) matrices.push_back(SpdMatrix(n, 10 + t));
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([t, &wrong, &matrices] {
      const Eigen::MatrixXd& a = matrices[t];
      const Eigen::MatrixXd want = Eigen::LLT<Eigen::MatrixXd>(a).matrixL();
      const Eigen::MatrixXd product_want = a * a;
      for (int round = 0; round < kRounds; ++round) {
        Eigen::MatrixXd l = a;
        if (!CholeskyInPlace(l) ||
            RelativeError(Eigen::MatrixXd(l.triangularView<Eigen::Lower>()), want) > 1e-12) {
          ++wrong[t];
        }
        Eigen::MatrixXd product;
        Multiply(a, a, &product);
        if (RelativeError(product, product_want) > 1e-13) ++wrong[t];
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  for (int t = 0; t < kThreads; ++t) EXPECT_EQ(wrong[t], 0) << "thread " << t;
}

TEST(DenseKernels, EmptyMatricesAreNoOps) {
  Eigen::MatrixXd empty(0, 0), rows(4, 0), product;
  EXPECT_TRUE(CholeskyInPlace(empty));
  InverseFromCholeskyInPlace(empty);
  LowerInverseInPlace(empty);
  SolveLowerInPlace(Eigen::MatrixXd::Identity(4, 4), rows);
  AddGramLower(rows, empty);
  std::vector<int> pivot;
  EXPECT_EQ(PivotedCholeskyInPlace(empty, 0.0, &pivot), 0);
  Multiply(Eigen::MatrixXd(3, 0), Eigen::MatrixXd(0, 2), &product);
  EXPECT_EQ(product, Eigen::MatrixXd::Zero(3, 2));
}

}  // namespace
}  // namespace crowdmap
