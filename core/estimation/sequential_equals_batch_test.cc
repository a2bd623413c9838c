// On a linear-Gaussian problem the sequential map update (CC prior from the marginal covariance,
// solve, the graph's factor added to the map's information, re-solve) is exact: passage by
// passage, in any order, it must give the same map, means and full covariance, as one batch solve
// over all passages; and taking one passage back must give the batch solve without it.
#include <algorithm>
#include <memory>
#include <optional>
#include <string>
#include <random>
#include <vector>

#include <Eigen/Eigenvalues>
#include <gtest/gtest.h>

#include "core/estimation/factors.h"
#include "core/estimation/graph_linearization.h"
#include "core/estimation/landmark_update.h"
#include "core/estimation/passage_exclusion.h"
#include "core/estimation/passage_prior.h"
#include "core/map/map_window.h"

namespace crowdmap {
namespace {

// Linear factor on two 2D blocks: S ((b - a) - measured).
struct DifferenceFactor {
  DifferenceFactor(const Eigen::Vector2d& measured, double sigma) : measured(measured), inv_sigma(1.0 / sigma) {}
  template <typename T>
  bool operator()(const T* a, const T* b, T* r) const {
    r[0] = (b[0] - a[0] - T(measured.x())) * T(inv_sigma);
    r[1] = (b[1] - a[1] - T(measured.y())) * T(inv_sigma);
    return true;
  }
  Eigen::Vector2d measured;
  double inv_sigma;
};

ceres::CostFunction* Difference(const Eigen::Vector2d& measured, double sigma) {
  return new ceres::AutoDiffCostFunction<DifferenceFactor, 2, 2, 2>(new DifferenceFactor(measured, sigma));
}

ceres::CostFunction* Absolute(const Eigen::Vector2d& measured, double sigma) {
  return new LandmarkPriorFactor(measured, Eigen::Matrix2d::Identity() / sigma);
}

// A passage of the toy problem: a short 2D track observed absolutely (GNSS-like), with relative
// odometry, and relative observations of a subset of the landmarks.
struct ToyPassage {
  std::vector<Eigen::Vector2d> fixes;     // noisy absolute positions of the poses
  std::vector<Eigen::Vector2d> odometry;  // noisy p[k+1] - p[k]
  struct Observation {
    int pose;
    int landmark;
    Eigen::Vector2d offset;  // noisy L - p
  };
  std::vector<Observation> observations;
};

constexpr double kFixSigma = 3.0, kOdometrySigma = 0.4, kObservationSigma = 0.5;
constexpr int kLandmarks = 7, kPassages = 6, kPoses = 6;

std::vector<Eigen::Vector2d> TrueLandmarks() {
  std::vector<Eigen::Vector2d> l;
  for (int i = 0; i < kLandmarks; ++i) l.emplace_back(8.0 * i - 20.0, (i % 2 ? 6.0 : -5.0));
  return l;
}

std::vector<ToyPassage> MakePassages() {
  std::mt19937_64 rng(42);
  std::normal_distribution<double> n(0.0, 1.0);
  auto noise = [&](double sigma) { return Eigen::Vector2d(sigma * n(rng), sigma * n(rng)); };
  const std::vector<Eigen::Vector2d> landmarks = TrueLandmarks();
  std::vector<ToyPassage> passages(kPassages);
  for (int j = 0; j < kPassages; ++j) {
    std::vector<Eigen::Vector2d> truth;
    for (int k = 0; k < kPoses; ++k) truth.emplace_back(-25.0 + 9.0 * k + j, 0.3 * j);
    ToyPassage& p = passages[j];
    for (int k = 0; k < kPoses; ++k) p.fixes.push_back(truth[k] + noise(kFixSigma));
    for (int k = 0; k + 1 < kPoses; ++k) p.odometry.push_back(truth[k + 1] - truth[k] + noise(kOdometrySigma));
    // Each passage sees three consecutive landmarks, so every update leaves correlated landmarks
    // outside its graph that must be conditioned.
    for (int s = 0; s < 3; ++s) {
      const int i = (2 * j + s) % kLandmarks;
      for (int k = s; k < kPoses; k += 2) {
        p.observations.push_back({k, i, landmarks[i] - truth[k] + noise(kObservationSigma)});
      }
    }
  }
  return passages;
}

void AddPassageFactors(const ToyPassage& p, std::vector<Eigen::Vector2d>* poses,
                       const std::function<double*(int)>& landmark, ceres::Problem* problem) {
  for (int k = 0; k < kPoses; ++k) problem->AddResidualBlock(Absolute(p.fixes[k], kFixSigma), nullptr, (*poses)[k].data());
  for (int k = 0; k + 1 < kPoses; ++k) {
    problem->AddResidualBlock(Difference(p.odometry[k], kOdometrySigma), nullptr, (*poses)[k].data(),
                              (*poses)[k + 1].data());
  }
  for (const auto& o : p.observations) {
    problem->AddResidualBlock(Difference(o.offset, kObservationSigma), nullptr, (*poses)[o.pose].data(),
                              landmark(o.landmark));
  }
}

void SolveExactly(ceres::Problem* problem) {
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_QR;
  options.function_tolerance = 1e-16;
  options.gradient_tolerance = 1e-16;
  options.parameter_tolerance = 1e-16;
  options.max_num_iterations = 200;
  ceres::Solver::Summary summary;
  ceres::Solve(options, problem, &summary);
  ASSERT_TRUE(summary.IsSolutionUsable()) << summary.FullReport();
}

struct JointEstimate {
  Eigen::VectorXd mean;  // 2 per landmark, local frame
  Eigen::MatrixXd cov;
};

JointEstimate BatchSolve(const std::vector<ToyPassage>& passages, int left_out = -1) {
  ceres::Problem problem;
  std::vector<Eigen::Vector2d> landmarks(kLandmarks, Eigen::Vector2d::Zero());
  std::vector<std::vector<Eigen::Vector2d>> poses(passages.size(), std::vector<Eigen::Vector2d>(kPoses, Eigen::Vector2d::Zero()));
  for (size_t j = 0; j < passages.size(); ++j) {
    if (static_cast<int>(j) == left_out) continue;
    AddPassageFactors(passages[j], &poses[j], [&](int i) { return landmarks[i].data(); }, &problem);
  }
  SolveExactly(&problem);
  ceres::Covariance::Options options;
  options.algorithm_type = ceres::DENSE_SVD;
  ceres::Covariance covariance(options);
  std::vector<const double*> blocks;
  for (const auto& l : landmarks) blocks.push_back(l.data());
  EXPECT_TRUE(covariance.Compute(blocks, &problem));
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> cov(2 * kLandmarks, 2 * kLandmarks);
  EXPECT_TRUE(covariance.GetCovarianceMatrix(blocks, cov.data()));
  JointEstimate e;
  e.mean.resize(2 * kLandmarks);
  for (int i = 0; i < kLandmarks; ++i) e.mean.segment<2>(2 * i) = landmarks[i];
  e.cov = cov;
  return e;
}

// At the equator the East/North frames of points within metres of the origin agree with the
// local frame to about 1e-11, so covariances can be compared across frames at 1e-8.
const LocalFrame& ToyFrame() {
  static const LocalFrame frame(LatLon{0.0, 0.0});
  return frame;
}

std::vector<int> InOrder() {
  std::vector<int> order;
  for (int j = 0; j < kPassages; ++j) order.push_back(j);
  return order;
}

// `group` consecutive passages (in `order`) share one overlay and one PassagePrior, as the
// subgraphs of one passage do in the map updater; 0: no PassagePrior, each update takes a window
// of the map for its prior and re-solves it after its factor (ResolveAround).
MapState SequentialSolve(const std::vector<ToyPassage>& passages, bool correlated,
                         const std::vector<int>& order = InOrder(), int group = 1) {
  MapState map;
  const size_t step = std::max(group, 1);
  for (size_t first = 0; first < order.size(); first += step) {
    const std::vector<int> members(order.begin() + first, order.begin() + std::min(first + step, order.size()));
    MapOverlay overlay(map);
    std::optional<PassagePrior> prior;
    if (group > 0 && correlated) {
      std::vector<LandmarkId> seen;
      for (int j : members) {
        for (const auto& o : passages[j].observations) seen.push_back(o.landmark);
      }
      absl::StatusOr<PassagePrior> built = PassagePrior::Build(overlay, seen, MapWindowOptions{});
      EXPECT_TRUE(built.ok()) << built.status();
      if (!built.ok()) return map;
      prior.emplace(std::move(*built));
    }
    for (int j : members) {
      const ToyPassage& p = passages[j];
      std::vector<LandmarkId> ids;
      for (const auto& o : p.observations) {
        if (std::find(ids.begin(), ids.end(), o.landmark) == ids.end()) ids.push_back(o.landmark);
      }
      LandmarkUpdate update(ToyFrame(), &overlay, ids);
      ceres::Problem problem;
      std::vector<Eigen::Vector2d> poses(p.fixes);
      AddPassageFactors(
          p, &poses,
          [&](int landmark) {
            const int i = static_cast<int>(std::find(ids.begin(), ids.end(), landmark) - ids.begin());
            return update.block(i);
          },
          &problem);
      LandmarkUpdateOptions options;
      options.correlated = correlated;
      options.passage_prior = prior ? &*prior : nullptr;
      options.vehicle_id = "toy";
      options.passage_id = "p" + std::to_string(j);
      EXPECT_TRUE(update.AddMapPrior(options, &problem).ok());
      SolveExactly(&problem);
      std::vector<double*> blocks;
      for (int i = 0; i < update.size(); ++i) blocks.push_back(update.block(i));
      absl::StatusOr<GraphLinearization> linearization = GraphLinearization::Compute(&problem, blocks);
      EXPECT_TRUE(linearization.ok()) << linearization.status();
      if (!linearization.ok()) return map;
      // Part of every update; on this linear problem the second-order bias is zero.
      EXPECT_TRUE(linearization->CorrectSecondOrderBias(&problem, nullptr).ok());
      absl::StatusOr<LandmarkUpdateStats> stats =
          update.Commit(linearization->landmark_covariance(), linearization->landmark_gradient(), options,
                        [](Landmark*) {});
      EXPECT_TRUE(stats.ok()) << stats.status();
    }
    if (prior) {
      absl::StatusOr<int> finished = prior->Finish(overlay.version(), &overlay);
      EXPECT_TRUE(finished.ok()) << finished.status();
    }
    map.Apply(overlay.TakeDelta());
  }
  return map;
}

// The map's estimate and joint covariance, from its information (a window over the whole map). A
// stored position is rewritten when the estimate moves by a micrometre or more: it is checked
// against the estimate at that tolerance.
JointEstimate FromMap(const MapState& map) {
  JointEstimate e;
  e.mean.resize(2 * kLandmarks);
  std::vector<LandmarkId> ids;
  for (int i = 0; i < kLandmarks; ++i) {
    EXPECT_NE(map.FindLandmark(i), nullptr);
    if (!map.FindLandmark(i)) return e;
    ids.push_back(i);
  }
  absl::StatusOr<MapWindow> window = MapWindow::Build(map, ids, MapWindowOptions{});
  EXPECT_TRUE(window.ok()) << window.status();
  if (!window.ok()) return e;
  for (int i = 0; i < kLandmarks; ++i) {
    const Landmark& l = *map.FindLandmark(i);
    e.mean.segment<2>(2 * i) = ToyFrame().ToLocal(LocalFrame(l.anchor).ToGeo(window->offsets().segment<2>(2 * i)));
    EXPECT_LT((ToyFrame().ToLocal(l.position) - e.mean.segment<2>(2 * i)).norm(), 1e-6) << i;
  }
  absl::StatusOr<Eigen::MatrixXd> cov = window->Covariance(ids);
  EXPECT_TRUE(cov.ok()) << cov.status();
  if (cov.ok()) e.cov = *cov;
  // A stored marginal is the joint covariance's diagonal block as of the last update that saw the
  // landmark: never smaller than today's.
  for (int i = 0; i < kLandmarks && cov.ok(); ++i) {
    const Eigen::Matrix2d stale = map.FindLandmark(i)->cov_en_m2 - cov->block<2, 2>(2 * i, 2 * i);
    EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(stale).eigenvalues().minCoeff(), -1e-10) << i;
  }
  return e;
}

TEST(SequentialUpdate, CorrelatedEqualsBatchOnALinearProblem) {
  const std::vector<ToyPassage> passages = MakePassages();
  const JointEstimate batch = BatchSolve(passages);
  // A window per update; a PassagePrior per update; one shared by 2 and by 3 updates (subgraphs of
  // one passage, the later ones seeing landmarks the earlier ones created).
  for (int group : {0, 1, 2, 3}) {
    SCOPED_TRACE(group);
    const MapState map = SequentialSolve(passages, /*correlated=*/true, InOrder(), group);
    const JointEstimate sequential = FromMap(map);
    // The last passage's landmarks have their marginal stored exactly.
    for (const auto& o : passages.back().observations) {
      EXPECT_LT((map.FindLandmark(o.landmark)->cov_en_m2 - batch.cov.block<2, 2>(2 * o.landmark, 2 * o.landmark))
                    .cwiseAbs()
                    .maxCoeff(),
                1e-8);
    }
    EXPECT_LT((sequential.mean - batch.mean).cwiseAbs().maxCoeff(), 1e-8)
        << "sequential\n" << sequential.mean.transpose() << "\nbatch\n" << batch.mean.transpose();
    EXPECT_LT((sequential.cov - batch.cov).cwiseAbs().maxCoeff(), 1e-8)
        << "difference\n" << (sequential.cov - batch.cov);
  }
}

TEST(SequentialUpdate, OrderOfThePassagesDoesNotChangeTheMap) {
  const std::vector<ToyPassage> passages = MakePassages();
  std::vector<int> reversed = InOrder(), interleaved;
  std::reverse(reversed.begin(), reversed.end());
  for (int j = 1; j < kPassages; j += 2) interleaved.push_back(j);
  for (int j = 0; j < kPassages; j += 2) interleaved.push_back(j);
  // Each order gives the batch solve (2e-10 apart when measured).
  const JointEstimate batch = BatchSolve(passages);
  for (const std::vector<int>& order : {InOrder(), reversed, interleaved}) {
    for (int group : {1, 2}) {
      const JointEstimate other = FromMap(SequentialSolve(passages, true, order, group));
      EXPECT_LT((other.mean - batch.mean).cwiseAbs().maxCoeff(), 1e-8) << group;
      EXPECT_LT((other.cov - batch.cov).cwiseAbs().maxCoeff(), 1e-8) << group;
    }
  }
}

TEST(SequentialUpdate, ExcludingAPassageGivesTheBatchSolveWithoutIt) {
  const std::vector<ToyPassage> passages = MakePassages();
  for (int left_out : {0, 3, kPassages - 1}) {
    MapState map = SequentialSolve(passages, true);
    const size_t factors = map.factor_count();
    MapUpdateOptions options;
    absl::StatusOr<PassageUpdate> exclusion =
        ComputePassageExclusion("toy", "p" + std::to_string(left_out), options, map);
    ASSERT_TRUE(exclusion.ok()) << exclusion.status();
    map.Apply(exclusion->delta);
    EXPECT_EQ(map.factor_count(), factors - 1);
    const JointEstimate batch = BatchSolve(passages, left_out);
    const JointEstimate excluded = FromMap(map);
    EXPECT_LT((excluded.mean - batch.mean).cwiseAbs().maxCoeff(), 1e-6) << "left out " << left_out;
    EXPECT_LT((excluded.cov - batch.cov).cwiseAbs().maxCoeff(), 1e-6) << "left out " << left_out;
  }
}

TEST(SequentialUpdate, ExcludingAnUnknownPassageIsNotFound) {
  const MapState map = SequentialSolve(MakePassages(), true);
  EXPECT_EQ(ComputePassageExclusion("toy", "nope", MapUpdateOptions{}, map).status().code(),
            absl::StatusCode::kNotFound);
}

TEST(SequentialUpdate, DecorrelatedDiffersFromBatchOnTheSameProblem) {
  // Control for the test above: dropping the cross-covariances (DC) is measurably not exact.
  const std::vector<ToyPassage> passages = MakePassages();
  const JointEstimate batch = BatchSolve(passages);
  const JointEstimate dc = FromMap(SequentialSolve(passages, /*correlated=*/false));
  EXPECT_GT((dc.mean - batch.mean).cwiseAbs().maxCoeff(), 1e-3);
}

}  // namespace
}  // namespace crowdmap
