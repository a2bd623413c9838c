#include "core/estimation/graph_linearization.h"

#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Dense>
#include <gtest/gtest.h>

#include "core/estimation/factors.h"

namespace crowdmap {
namespace {

TEST(SelectedInverse, MatchesTheDenseInverseOnThePattern) {
  // A block-tridiagonal chain with a few long-range couplings, like a pose chain with loops.
  const int n = 60;
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::MatrixXd m = Eigen::MatrixXd::Zero(n, n);
  for (int i = 0; i < n; ++i) {
    for (int j = std::max(0, i - 4); j < i; ++j) m(i, j) = m(j, i) = u(rng);
  }
  for (int k = 0; k < 6; ++k) {
    const int i = static_cast<int>(rng() % n), j = static_cast<int>(rng() % n);
    if (i != j) m(i, j) = m(j, i) = u(rng);
  }
  m += (m.cwiseAbs().rowwise().sum().maxCoeff() + 1.0) * Eigen::MatrixXd::Identity(n, n);  // SPD
  const Eigen::SparseMatrix<double> a = m.sparseView();
  Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> llt(a);
  ASSERT_EQ(llt.info(), Eigen::Success);
  const SelectedInverse inverse(llt);
  const Eigen::MatrixXd dense = m.inverse();
  // A^-1 B for many columns at once, as Eigen's solve gives it.
  Eigen::MatrixXd b = Eigen::MatrixXd::Zero(n, 25);
  for (int c = 0; c < b.cols(); ++c) b(static_cast<int>(rng() % n), c) = u(rng);
  b.col(3).setConstant(1.0);
  EXPECT_LT((SolveManyColumns(llt, b) - llt.solve(b)).cwiseAbs().maxCoeff(), 1e-13 * dense.cwiseAbs().maxCoeff());
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      if (m(i, j) != 0.0) {
        EXPECT_NEAR(inverse(i, j), dense(i, j), 1e-12) << i << "," << j;
      }
    }
  }
}

// y = exp(theta) + noise, per coordinate: the least-squares estimate log(mean y) is biased by
// -sigma^2 / (2 n exp(2 theta)) to second order.
struct ExpResidual {
  ExpResidual(double y0, double y1, double sigma) : y0(y0), y1(y1), sigma(sigma) {}
  template <typename T>
  bool operator()(const T* theta, T* r) const {
    r[0] = (T(y0) - exp(theta[0])) / T(sigma);
    r[1] = (T(y1) - exp(theta[1])) / T(sigma);
    return true;
  }
  double y0, y1, sigma;
};

TEST(GraphLinearization, SecondOrderCorrectionRemovesTheBiasOfANonlinearEstimate) {
  const int n = 4, draws = 20000;
  const double sigma = 0.3;
  const Eigen::Vector2d truth(0.0, 0.5);
  std::mt19937_64 rng(11);
  std::normal_distribution<double> noise(0.0, sigma);
  Eigen::Vector2d sum_map = Eigen::Vector2d::Zero(), sum_corrected = Eigen::Vector2d::Zero();
  Eigen::Vector2d covariance_check = Eigen::Vector2d::Zero(), sum_shift_formula = Eigen::Vector2d::Zero();
  for (int k = 0; k < draws; ++k) {
    ceres::Problem problem;
    Eigen::Vector2d theta = truth;
    for (int i = 0; i < n; ++i) {
      problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ExpResidual, 2, 2>(new ExpResidual(
                                   std::exp(truth.x()) + noise(rng), std::exp(truth.y()) + noise(rng), sigma)),
                               nullptr, theta.data());
    }
    ceres::Solver::Options options;
    options.linear_solver_type = ceres::DENSE_QR;
    options.function_tolerance = 1e-14;
    options.parameter_tolerance = 1e-14;
    options.gradient_tolerance = 1e-16;
    ceres::Solver::Summary summary;
    ceres::Solve(options, &problem, &summary);
    ASSERT_TRUE(summary.IsSolutionUsable());
    sum_map += theta;
    absl::StatusOr<GraphLinearization> lin = GraphLinearization::Compute(&problem, {theta.data()});
    ASSERT_TRUE(lin.ok()) << lin.status();
    // Covariance: (J^T J)^-1 = sigma^2 / (n exp(2 theta)) per coordinate.
    covariance_check += (lin->landmark_covariance().diagonal().array() /
                         (sigma * sigma / (n * (2.0 * theta.array()).exp()))).matrix();
    // Box's formula at this estimate: the bias is -sigma^2 / (2 n exp(2 theta)).
    sum_shift_formula += (sigma * sigma / (2.0 * n)) * (-2.0 * theta.array()).exp().matrix();
    ASSERT_TRUE(lin->CorrectSecondOrderBias(&problem, nullptr).ok());
    sum_corrected += theta;
  }
  const Eigen::Vector2d bias_map = sum_map / draws - truth;
  const Eigen::Vector2d bias_corrected = sum_corrected / draws - truth;
  const Eigen::Vector2d expected = -(sigma * sigma / (2.0 * n)) * (-2.0 * truth.array()).exp().matrix();
  const Eigen::Vector2d standard_error = (sigma / std::sqrt(1.0 * n * draws)) * (-truth.array()).exp().matrix();
  const Eigen::Vector2d mean_shift = (sum_corrected - sum_map) / draws;
  for (int c = 0; c < 2; ++c) {
    EXPECT_NEAR(covariance_check[c] / draws, 1.0, 1e-12);
    // The correction is Box's formula (up to the finite differences' fourth-order term).
    EXPECT_NEAR(mean_shift[c], sum_shift_formula[c] / draws, 0.01 * std::abs(expected[c])) << c;
    EXPECT_NEAR(bias_map[c], expected[c], 3.0 * standard_error[c]) << c;   // the MAP is biased...
    EXPECT_GT(std::abs(bias_map[c]), 6.0 * standard_error[c]) << c;
    EXPECT_LT(std::abs(bias_corrected[c]), 3.0 * standard_error[c]) << c;  // ...the corrected one not
  }
}

// r = a0 y + a1 . l - b, whitened: a linear residual in a scalar y and a 2-D landmark l.
struct ScalarLandmarkResidual {
  ScalarLandmarkResidual(double a0, double a1x, double a1y, double b) : a0(a0), a1x(a1x), a1y(a1y), b(b) {}
  template <typename T>
  bool operator()(const T* y, const T* l, T* r) const {
    r[0] = T(a0) * y[0] + T(a1x) * l[0] + T(a1y) * l[1] - T(b);
    return true;
  }
  double a0, a1x, a1y, b;
};

TEST(GraphLinearization, ScalarMarginalSplitsIntoTheVarianceGivenTheLandmarksAndTheirShare) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double y = 0.0;
  std::vector<Eigen::Vector2d> landmarks(2, Eigen::Vector2d::Zero());
  ceres::Problem problem;
  // Dense information of (y, l0, l1), built alongside.
  Eigen::MatrixXd h = Eigen::MatrixXd::Zero(5, 5);
  for (int k = 0; k < 12; ++k) {
    const int i = k % 2;
    const Eigen::Vector3d a(u(rng), u(rng), u(rng));
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ScalarLandmarkResidual, 1, 1, 2>(
                                 new ScalarLandmarkResidual(a(0), a(1), a(2), u(rng))),
                             nullptr, &y, landmarks[i].data());
    Eigen::VectorXd row = Eigen::VectorXd::Zero(5);
    row(0) = a(0);
    row.segment<2>(1 + 2 * i) = a.tail<2>();
    h += row * row.transpose();
  }
  absl::StatusOr<GraphLinearization> lin =
      GraphLinearization::Compute(&problem, {landmarks[0].data(), landmarks[1].data()});
  ASSERT_TRUE(lin.ok()) << lin.status();
  const GraphLinearization::ScalarMarginal m = lin->MarginalVariance(&y);
  EXPECT_NEAR(m.given_landmarks, 1.0 / h(0, 0), 1e-12);
  EXPECT_NEAR(m.total(), h.inverse()(0, 0), 1e-12);
  EXPECT_GT(m.from_landmarks, 0.0);
}

// Two residuals on the scalar state and a landmark.
struct TwoRowResidual {
  explicit TwoRowResidual(const Eigen::Matrix<double, 2, 3>& a) : a(a) {}
  template <typename T>
  bool operator()(const T* y, const T* l, T* r) const {
    for (int i = 0; i < 2; ++i) r[i] = T(a(i, 0)) * y[0] + T(a(i, 1)) * l[0] + T(a(i, 2)) * l[1] - T(0.1 * i);
    return true;
  }
  Eigen::Matrix<double, 2, 3> a;
};

// Each block's redundancy is its rows' count minus its share of the hat matrix J H^-1 J^T, taken
// with the loss's weight; all of them together are the rows less the parameters.
TEST(GraphLinearization, RedundanciesAreTheResidualsLessTheirShareOfTheParameters) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double y = 0.2;
  std::vector<Eigen::Vector2d> landmarks(2, Eigen::Vector2d(0.3, -0.1));
  ceres::Problem::Options options;
  options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(options);
  ceres::ScaledLoss weight(nullptr, 0.25, ceres::DO_NOT_TAKE_OWNERSHIP);
  std::vector<Eigen::MatrixXd> rows;  // each block's weighted Jacobian over (y, l0, l1)
  std::vector<ceres::ResidualBlockId> ids;
  for (int k = 0; k < 9; ++k) {
    const int i = k % 2;
    const bool weighted = k % 3 == 0;
    Eigen::MatrixXd j = Eigen::MatrixXd::Zero(k < 6 ? 1 : 2, 5);
    if (k < 6) {
      const Eigen::Vector3d a(u(rng), u(rng), u(rng));
      ids.push_back(problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ScalarLandmarkResidual, 1, 1, 2>(
                                               new ScalarLandmarkResidual(a(0), a(1), a(2), u(rng))),
                                           weighted ? &weight : nullptr, &y, landmarks[i].data()));
      j(0, 0) = a(0);
      j.block<1, 2>(0, 1 + 2 * i) = a.tail<2>().transpose();
    } else {
      Eigen::Matrix<double, 2, 3> a;
      for (int c = 0; c < 6; ++c) a(c) = u(rng);
      ids.push_back(problem.AddResidualBlock(
          new ceres::AutoDiffCostFunction<TwoRowResidual, 2, 1, 2>(new TwoRowResidual(a)),
          weighted ? &weight : nullptr, &y, landmarks[i].data()));
      j.col(0) = a.col(0);
      j.block<2, 2>(0, 1 + 2 * i) = a.rightCols<2>();
    }
    if (weighted) j *= 0.5;  // sqrt(0.25)
    rows.push_back(j);
  }
  Eigen::MatrixXd h = Eigen::MatrixXd::Zero(5, 5);
  for (const Eigen::MatrixXd& j : rows) h += j.transpose() * j;
  const Eigen::MatrixXd sigma = h.inverse();

  absl::StatusOr<GraphLinearization> lin =
      GraphLinearization::Compute(&problem, {landmarks[0].data(), landmarks[1].data()});
  ASSERT_TRUE(lin.ok()) << lin.status();
  const std::unordered_map<ceres::ResidualBlockId, double> redundancies = lin->Redundancies();
  ASSERT_EQ(redundancies.size(), rows.size());
  double sum = 0.0, count = 0.0;
  for (size_t k = 0; k < rows.size(); ++k) {
    const double expected = rows[k].rows() - (rows[k] * sigma * rows[k].transpose()).trace();
    ASSERT_EQ(redundancies.count(ids[k]), 1u) << k;
    const double redundancy = redundancies.at(ids[k]);
    EXPECT_NEAR(redundancy, expected, 1e-12) << k;
    EXPECT_GT(redundancy, 0.0) << k;
    sum += redundancy;
    count += rows[k].rows();
  }
  EXPECT_NEAR(sum, count - 5.0, 1e-12);
}

// What the factor leaves out is as if the problem never had it, in both ways of taking it out: a
// prior on the scalar state (a rank-one downdate) and a residual on the state and a landmark (a
// second linearisation). The rest of the linearisation keeps the block.
TEST(GraphLinearization, TheFactorWithoutABlockIsAsIfTheProblemNeverHadIt) {
  for (const bool scalar_prior : {true, false}) {
    auto linearize = [&](bool with_block, bool leave_it_out) {
      std::mt19937 rng(11);
      std::uniform_real_distribution<double> u(-1.0, 1.0);
      double y = 0.3;
      std::vector<Eigen::Vector2d> landmarks(2, Eigen::Vector2d(0.1, -0.2));
      ceres::Problem problem;
      for (int k = 0; k < 12; ++k) {
        problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ScalarLandmarkResidual, 1, 1, 2>(
                                     new ScalarLandmarkResidual(u(rng), u(rng), u(rng), u(rng))),
                                 nullptr, &y, landmarks[k % 2].data());
      }
      std::vector<ceres::ResidualBlockId> left_out;
      if (with_block) {
        // Away from the state's value: it pulls.
        const ceres::ResidualBlockId block =
            scalar_prior ? problem.AddResidualBlock(ScalarPriorFactor::Create(-0.5, 0.2), nullptr, &y)
                         : problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ScalarLandmarkResidual, 1, 1, 2>(
                                                        new ScalarLandmarkResidual(3.0, 1.0, 0.0, 0.7)),
                                                    nullptr, &y, landmarks[0].data());
        if (leave_it_out) left_out.push_back(block);
      }
      absl::StatusOr<GraphLinearization> lin =
          GraphLinearization::Compute(&problem, {landmarks[0].data(), landmarks[1].data()}, left_out);
      EXPECT_TRUE(lin.ok()) << lin.status();
      return lin;
    };
    const absl::StatusOr<GraphLinearization> never = linearize(false, false);
    const absl::StatusOr<GraphLinearization> left_out = linearize(true, true);
    const absl::StatusOr<GraphLinearization> kept = linearize(true, false);
    ASSERT_TRUE(never.ok() && left_out.ok() && kept.ok());
    const double tolerance = 1e-12 * never->landmark_covariance().cwiseAbs().maxCoeff();
    EXPECT_LT((left_out->factor_covariance() - never->landmark_covariance()).cwiseAbs().maxCoeff(), tolerance)
        << scalar_prior;
    EXPECT_LT((left_out->factor_gradient() - never->landmark_gradient()).cwiseAbs().maxCoeff(), 1e-12)
        << scalar_prior;
    // The rest keeps it: the same as the linearisation that leaves nothing out.
    EXPECT_EQ(left_out->landmark_covariance(), kept->landmark_covariance()) << scalar_prior;
    EXPECT_EQ(kept->factor_covariance(), kept->landmark_covariance()) << scalar_prior;
    EXPECT_GT((kept->landmark_covariance() - never->landmark_covariance()).cwiseAbs().maxCoeff(), 1e-3)
        << scalar_prior;
    EXPECT_GT((kept->landmark_gradient() - never->landmark_gradient()).cwiseAbs().maxCoeff(), 1e-3) << scalar_prior;
  }
}

// Two scalar states and a landmark, a residual on all three.
struct ChainResidual {
  ChainResidual(double a, double b, double c, double d, double y) : a(a), b(b), c(c), d(d), y(y) {}
  template <typename T>
  bool operator()(const T* x0, const T* x1, const T* l, T* r) const {
    r[0] = T(a) * x0[0] + T(b) * x1[0] + T(c) * l[0] + T(d) * l[1] - T(y);
    return true;
  }
  double a, b, c, d, y;
};

// The same problem, its states stored at addresses in the opposite order: bit for bit the same
// linearisation (the blocks' order comes from the residuals, not from their addresses, which
// differ from run to run).
TEST(GraphLinearization, DoesNotDependOnWhereTheStatesAreStored) {
  const int n = 40;
  auto linearize = [&](bool reversed) {
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> u(0.5, 1.5);
    std::vector<double> storage(n, 0.0);
    std::vector<Eigen::Vector2d> landmarks(3, Eigen::Vector2d::Zero());
    auto state = [&](int k) { return &storage[reversed ? n - 1 - k : k]; };
    ceres::Problem problem;
    for (int k = 0; k + 1 < n; ++k) {
      for (int l = 0; l < 3; ++l) {
        if ((k + l) % 2 != 0) continue;
        problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ChainResidual, 1, 1, 1, 2>(
                                     new ChainResidual(u(rng), -u(rng), u(rng), u(rng), u(rng))),
                                 nullptr, state(k), state(k + 1), landmarks[l].data());
      }
    }
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ChainResidual, 1, 1, 1, 2>(
                                 new ChainResidual(1.0, 0.0, 0.0, 0.0, 0.0)),
                             nullptr, state(0), state(1), landmarks[0].data());
    for (int l = 0; l < 3; ++l) {
      for (int k = 0; k < 2; ++k) {
        problem.AddResidualBlock(new ceres::AutoDiffCostFunction<ChainResidual, 1, 1, 1, 2>(
                                     new ChainResidual(0.0, 0.0, k == 0 ? 1.0 : 0.0, k == 1 ? 1.0 : 0.0, 0.0)),
                                 nullptr, state(0), state(1), landmarks[l].data());
      }
    }
    std::vector<double*> landmark_blocks;
    for (Eigen::Vector2d& l : landmarks) landmark_blocks.push_back(l.data());
    absl::StatusOr<GraphLinearization> lin = GraphLinearization::Compute(&problem, landmark_blocks);
    EXPECT_TRUE(lin.ok()) << lin.status();
    return lin.ok() ? lin->landmark_covariance() : Eigen::MatrixXd();
  };
  const Eigen::MatrixXd forward = linearize(false), backward = linearize(true);
  ASSERT_EQ(forward.rows(), 6);
  EXPECT_TRUE(forward == backward) << (forward - backward).cwiseAbs().maxCoeff();
}

}  // namespace
}  // namespace crowdmap
