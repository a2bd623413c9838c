#include "core/map/map_window.h"

#include <random>

#include <Eigen/Eigenvalues>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// A chain of `n` landmarks; factor k links landmarks k and k+1 with a random positive definite
// information, so the map's information is block tridiagonal.
MapState Chain(int n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  MapState map;
  for (int i = 0; i < n; ++i) {
    Landmark l;
    l.id = i + 1;
    l.anchor = {45.0, 4.0 + 1e-4 * i};
    l.position = l.anchor;
    map.PutLandmark(l);
  }
  for (int k = 0; k + 1 < n; ++k) {
    Eigen::MatrixXd a(6, 4);
    for (int r = 0; r < 6; ++r) {
      for (int c = 0; c < 4; ++c) a(r, c) = g(rng);
    }
    MapFactor f;
    f.id = k + 1;
    f.landmarks = {k + 1, k + 2};
    f.information = a.transpose() * a;
    f.information_vector = Eigen::Vector4d(g(rng), g(rng), g(rng), g(rng));
    map.PutFactor(f);
  }
  return map;
}

Eigen::MatrixXd DenseInformation(const MapState& map, int n, Eigen::VectorXd* vector) {
  Eigen::MatrixXd h = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  vector->setZero(2 * n);
  for (int i = 0; i < n; ++i) {
    vector->segment<2>(2 * i) = map.InformationVector(i + 1);
    for (int j = 0; j < n; ++j) h.block<2, 2>(2 * i, 2 * j) = map.Information(i + 1, j + 1).value;
  }
  return h;
}

TEST(MapWindow, WholeMapGivesTheExactEstimateAndCovariance) {
  const int n = 12;
  const MapState map = Chain(n, 1);
  Eigen::VectorXd eta;
  const Eigen::MatrixXd h = DenseInformation(map, n, &eta);
  const Eigen::MatrixXd cov = h.inverse();
  const Eigen::VectorXd mean = h.ldlt().solve(eta);
  absl::StatusOr<MapWindow> w = MapWindow::Build(map, {5}, MapWindowOptions{});
  ASSERT_TRUE(w.ok()) << w.status();
  EXPECT_TRUE(w->closed());
  ASSERT_EQ(w->landmarks().size(), static_cast<size_t>(n));
  EXPECT_EQ(w->landmarks().front(), 5) << "seeds first";
  const std::vector<Eigen::Matrix2d> marginals = w->Marginals();
  for (int k = 0; k < n; ++k) {
    const int i = w->landmarks()[k] - 1;
    EXPECT_LT((w->offsets().segment<2>(2 * k) - mean.segment<2>(2 * i)).cwiseAbs().maxCoeff(), 1e-9);
    EXPECT_LT((marginals[k] - cov.block<2, 2>(2 * i, 2 * i)).cwiseAbs().maxCoeff(), 1e-9);
  }
  absl::StatusOr<Eigen::MatrixXd> joint = w->Covariance({2, 11});
  ASSERT_TRUE(joint.ok());
  EXPECT_LT((joint->block<2, 2>(0, 2) - cov.block<2, 2>(2, 20)).cwiseAbs().maxCoeff(), 1e-9) << "far apart, exact";
}

// The smallest eigenvalue of a - b (symmetric).
double SmallestEigenvalueOfDifference(const Eigen::MatrixXd& a, const Eigen::MatrixXd& b) {
  return Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(a - b, Eigen::EigenvaluesOnly).eigenvalues()(0);
}

// A window tells how its covariance relates to the exact one: exact when closed, conservative
// while only kept factors reach outside it, and possibly narrower once a factor that reaches
// outside is folded into the map's base (which the window then holds, as it is).
TEST(MapWindow, AWindowSaysWhetherItsCovarianceIsExactConservativeOrMayBeNarrower) {
  const int n = 12;
  MapState map = Chain(n, 4);
  Eigen::VectorXd eta;
  const Eigen::MatrixXd exact = DenseInformation(map, n, &eta).inverse();  // folding keeps it
  const std::vector<LandmarkId> ids = {4, 5, 6, 7, 8};
  const Eigen::MatrixXd exact_ids = exact.block(6, 6, 10, 10);
  MapWindowOptions two_links;
  two_links.hops = 2;
  const auto read = [&](CovarianceBound* bound) {  // landmarks 4..8, two links around 6
    absl::StatusOr<MapWindow> w = MapWindow::Build(map, {6}, two_links);
    EXPECT_TRUE(w.ok()) << w.status();
    if (!w.ok()) return Eigen::MatrixXd();
    EXPECT_EQ(w->landmarks().size(), ids.size());
    *bound = w->covariance_bound();
    absl::StatusOr<Eigen::MatrixXd> cov = w->Covariance(ids);
    EXPECT_TRUE(cov.ok()) << cov.status();
    return cov.ok() ? *cov : Eigen::MatrixXd();
  };

  absl::StatusOr<MapWindow> whole = MapWindow::Build(map, {6}, MapWindowOptions{});
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_EQ(whole->covariance_bound(), CovarianceBound::kExact);

  CovarianceBound bound = CovarianceBound::kExact;
  Eigen::MatrixXd cov = read(&bound);
  EXPECT_EQ(bound, CovarianceBound::kConservative) << "factors {3, 4} and {8, 9} reach outside, kept";
  EXPECT_GT(SmallestEigenvalueOfDifference(cov, exact_ids), -1e-9);

  map.FoldFactor(5);  // {5, 6}, inside the window
  cov = read(&bound);
  EXPECT_EQ(bound, CovarianceBound::kConservative) << "the base reaches no landmark outside";
  EXPECT_GT(SmallestEigenvalueOfDifference(cov, exact_ids), -1e-9);

  map.FoldFactor(8);  // {8, 9}: landmark 9 is outside
  cov = read(&bound);
  EXPECT_EQ(bound, CovarianceBound::kMayBeNarrower);
  EXPECT_LT(SmallestEigenvalueOfDifference(cov, exact_ids), -1e-6) << "held, 9 makes 8 look surer than it is";

  EXPECT_STREQ(CovarianceBoundName(bound), "may_be_narrower") << "as the read logs name it";
  EXPECT_STREQ(CovarianceBoundName(CovarianceBound::kConservative), "conservative");
  EXPECT_STREQ(CovarianceBoundName(CovarianceBound::kExact), "exact");

  // JointCovariance's window around all of 4..8 reaches 2..10, whose leaving factors are kept.
  CovarianceBound joint = CovarianceBound::kExact;
  ASSERT_TRUE(JointCovariance(map, ids, two_links, &joint).ok());
  EXPECT_EQ(joint, CovarianceBound::kConservative);
}

TEST(MapWindow, BoundedWindowIsConservativeAndConditionsOnTheRest) {
  const int n = 12;
  MapState map = Chain(n, 2);
  Eigen::VectorXd eta;
  const Eigen::MatrixXd h = DenseInformation(map, n, &eta);
  const Eigen::MatrixXd cov = h.inverse();
  MapWindowOptions options;
  options.hops = 2;
  absl::StatusOr<MapWindow> w = MapWindow::Build(map, {6}, options);
  ASSERT_TRUE(w.ok()) << w.status();
  EXPECT_FALSE(w->closed());
  EXPECT_EQ(w->landmarks().size(), 5u) << "landmarks 4..8";
  const std::vector<LandmarkId> ids = {4, 5, 6, 7, 8};
  absl::StatusOr<Eigen::MatrixXd> window_cov = w->Covariance(ids);
  ASSERT_TRUE(window_cov.ok());
  const Eigen::MatrixXd exact = cov.block(6, 6, 10, 10);
  // Never smaller than the exact marginal (the difference is positive semi-definite) ...
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> diff(*window_cov - exact);
  EXPECT_GT(diff.eigenvalues().minCoeff(), -1e-9);
  // ... and not equal to it: the window lost information.
  EXPECT_GT(diff.eigenvalues().maxCoeff(), 1e-6);
  // A covariance-only window (reads) gives the same covariance, and no estimate.
  MapWindowOptions covariance_only = options;
  covariance_only.estimate = false;
  absl::StatusOr<MapWindow> read = MapWindow::Build(map, {6}, covariance_only);
  ASSERT_TRUE(read.ok()) << read.status();
  absl::StatusOr<Eigen::MatrixXd> read_cov = read->Covariance(ids);
  ASSERT_TRUE(read_cov.ok());
  EXPECT_LT((*read_cov - *window_cov).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_EQ(read->offsets().size(), 0);
  // JointCovariance (reads) builds its window that way.
  absl::StatusOr<MapWindow> around_ids = MapWindow::Build(map, ids, options);
  ASSERT_TRUE(around_ids.ok());
  EXPECT_LT((*JointCovariance(map, ids, options) - *around_ids->Covariance(ids)).cwiseAbs().maxCoeff(), 1e-12);
  // With the rest held at the estimate the window is the conditional solve: with the rest at the
  // exact mean, the window's estimate is the exact mean.
  const Eigen::VectorXd mean = h.ldlt().solve(eta);
  MapState at_mean = map;
  for (int i = 0; i < n; ++i) {
    Landmark l = *map.FindLandmark(i + 1);
    l.position = LocalFrame(l.anchor).ToGeo(mean.segment<2>(2 * i));
    at_mean.PutLandmark(l);
  }
  absl::StatusOr<MapWindow> conditional = MapWindow::Build(at_mean, {6}, options);
  ASSERT_TRUE(conditional.ok());
  for (size_t k = 0; k < ids.size(); ++k) {
    const int i = conditional->landmarks()[k] - 1;
    EXPECT_LT((conditional->offsets().segment<2>(2 * k) - mean.segment<2>(2 * i)).cwiseAbs().maxCoeff(), 1e-6);
  }
}

// A factor that reaches outside the window and leaves a direction of the landmarks outside free
// (fewer rows than the dimensions it links, as a subgraph that saw them with one ray) enters a
// bounded window through its Schur complement with the pseudo-inverse.
TEST(MapWindow, AFactorSingularOutsideTheWindowEntersThroughItsPseudoInverseSchurComplement) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> g(0.0, 1.0);
  MapState map;
  for (int i = 0; i < 4; ++i) {
    Landmark l;
    l.id = i + 1;
    l.anchor = {45.0, 4.0 + 1e-4 * i};
    l.position = l.anchor;
    map.PutLandmark(l);
  }
  auto random_rows = [&](int rows, int cols) { return Eigen::MatrixXd::NullaryExpr(rows, cols, [&] { return g(rng); }); };
  auto add = [&](int64_t id, std::vector<LandmarkId> landmarks, const Eigen::MatrixXd& a) {
    MapFactor f;
    f.id = id;
    f.landmarks = std::move(landmarks);
    f.information = a.transpose() * a;
    f.information_vector = Eigen::VectorXd::NullaryExpr(a.cols(), [&] { return g(rng); });
    map.PutFactor(f);
  };
  const Eigen::MatrixXd a = random_rows(6, 4), b = random_rows(3, 6);  // b: rank 3 over 6 dims
  add(1, {1, 2}, a);
  add(2, {2, 3, 4}, b);
  add(3, {3}, random_rows(3, 2));
  add(4, {4}, random_rows(3, 2));
  MapWindowOptions options;
  options.hops = 1;
  absl::StatusOr<MapWindow> w = MapWindow::Build(map, {1}, options);
  ASSERT_TRUE(w.ok()) << w.status();
  ASSERT_EQ(w->landmarks(), (std::vector<LandmarkId>{1, 2}));
  const Eigen::MatrixXd info_b = b.transpose() * b;
  const Eigen::MatrixXd outside = info_b.bottomRightCorner(4, 4);
  ASSERT_LT(outside.fullPivLu().rank(), 4) << "the test needs a singular outside block";
  Eigen::MatrixXd expected = a.transpose() * a;
  expected.bottomRightCorner(2, 2) += info_b.topLeftCorner(2, 2) - info_b.topRightCorner(2, 4) *
                                                                       outside.completeOrthogonalDecomposition().pseudoInverse() *
                                                                       info_b.bottomLeftCorner(4, 2);
  absl::StatusOr<Eigen::MatrixXd> cov = w->Covariance({1, 2});
  ASSERT_TRUE(cov.ok()) << cov.status();
  EXPECT_LT((*cov - expected.inverse()).cwiseAbs().maxCoeff(), 1e-8 * expected.inverse().cwiseAbs().maxCoeff());
}

// A side x side grid of landmarks; each factor links a random 3 x 3 patch of neighbours, as a
// subgraph links the landmarks it saw along a stretch of street. Large enough for the sparse
// (supernodal) factorisation.
MapState Grid(int side, int factors, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_int_distribution<int> corner(0, side - 3);
  MapState map;
  for (int i = 0; i < side * side; ++i) {
    Landmark l;
    l.id = i + 1;
    l.anchor = {45.0 + 1e-4 * (i / side), 4.0 + 1e-4 * (i % side)};
    l.position = l.anchor;
    map.PutLandmark(l);
  }
  auto add = [&](int64_t id, std::vector<LandmarkId> landmarks) {
    const int dims = 2 * static_cast<int>(landmarks.size());
    Eigen::MatrixXd a(dims + 2, dims);
    for (int r = 0; r < a.rows(); ++r) {
      for (int c = 0; c < dims; ++c) a(r, c) = g(rng);
    }
    MapFactor f;
    f.id = id;
    f.landmarks = std::move(landmarks);
    f.information = a.transpose() * a;
    f.information_vector = Eigen::VectorXd::NullaryExpr(dims, [&] { return g(rng); });
    map.PutFactor(f);
  };
  for (int k = 0; k < side * side; ++k) add(k + 1, {k + 1});  // every landmark observed
  for (int k = 0; k < factors; ++k) {
    const int r0 = corner(rng), c0 = corner(rng);
    std::vector<LandmarkId> patch;
    for (int r = r0; r < r0 + 3; ++r) {
      for (int c = c0; c < c0 + 3; ++c) patch.push_back(r * side + c + 1);
    }
    add(side * side + k + 1, patch);
  }
  return map;
}

TEST(MapWindow, CovarianceOfAnySubsetIsTheInverseBlock) {
  for (const int side : {6, 20}) {  // 72 and 800 dimensions: the dense and the supernodal factor
    const int n = side * side;
    const MapState map = Grid(side, n / 2, 7);
    Eigen::VectorXd eta;
    const Eigen::MatrixXd cov = DenseInformation(map, n, &eta).inverse();
    absl::StatusOr<MapWindow> w = MapWindow::Build(map, map.LandmarkIds(), MapWindowOptions{});
    ASSERT_TRUE(w.ok()) << w.status();
    // Neighbours, far apart, out of order and repeated.
    const std::vector<LandmarkId> ids = {5, 6, static_cast<LandmarkId>(n), 1, static_cast<LandmarkId>(n / 2), 6};
    absl::StatusOr<Eigen::MatrixXd> joint = w->Covariance(ids);
    ASSERT_TRUE(joint.ok()) << joint.status();
    ASSERT_EQ(joint->rows(), 12);
    for (size_t a = 0; a < ids.size(); ++a) {
      for (size_t b = 0; b < ids.size(); ++b) {
        const Eigen::Matrix2d expected = cov.block<2, 2>(2 * (ids[a] - 1), 2 * (ids[b] - 1));
        EXPECT_LT((joint->block<2, 2>(2 * a, 2 * b) - expected).cwiseAbs().maxCoeff(),
                  1e-9 * cov.diagonal().maxCoeff())
            << "side " << side << ", landmarks " << ids[a] << " and " << ids[b];
      }
    }
    EXPECT_EQ(w->Covariance({}).value().size(), 0);
    EXPECT_EQ(w->Covariance({static_cast<LandmarkId>(n + 1)}).status().code(), absl::StatusCode::kInvalidArgument);
    // The whole covariance, in the window's order.
    absl::StatusOr<Eigen::MatrixXd> full = w->FullCovariance();
    ASSERT_TRUE(full.ok()) << full.status();
    ASSERT_EQ(full->rows(), 2 * n);
    const std::vector<LandmarkId>& order = w->landmarks();
    for (int a = 0; a < n; ++a) {
      for (int b = 0; b < n; ++b) {
        const Eigen::Matrix2d expected = cov.block<2, 2>(2 * (order[a] - 1), 2 * (order[b] - 1));
        ASSERT_LT((full->block<2, 2>(2 * a, 2 * b) - expected).cwiseAbs().maxCoeff(), 1e-9 * cov.diagonal().maxCoeff())
            << "side " << side << ", landmarks " << order[a] << " and " << order[b];
      }
    }
    // Every landmark's marginal (the selected inverse on the factor's supernodes).
    const std::vector<Eigen::Matrix2d> marginals = w->Marginals();
    ASSERT_EQ(marginals.size(), static_cast<size_t>(n));
    for (int a = 0; a < n; ++a) {
      const Eigen::Matrix2d expected = cov.block<2, 2>(2 * (order[a] - 1), 2 * (order[a] - 1));
      ASSERT_LT((marginals[a] - expected).cwiseAbs().maxCoeff(), 1e-9 * cov.diagonal().maxCoeff())
          << "side " << side << ", landmark " << order[a];
    }
  }
}

// An open window large enough for the supernodal factor, which works in a fill-reducing order of
// the landmarks of its own: with the rest of the map held at the exact mean its estimate is the
// exact mean (the solve, translated out of that order), its covariance is conservative, and a
// covariance-only read (a factorisation of its own) gives the covariance of the estimating window
// (its mean factor refactorised in the same order).
TEST(MapWindow, AnOpenSupernodalWindowIsTheConditionalMeanAndConservative) {
  const int side = 30, n = side * side;
  const MapState map = Grid(side, n, 11);
  Eigen::VectorXd eta;
  const Eigen::MatrixXd h = DenseInformation(map, n, &eta);
  const Eigen::LLT<Eigen::MatrixXd> llt(h);
  ASSERT_EQ(llt.info(), Eigen::Success);
  const Eigen::VectorXd mean = llt.solve(eta);
  MapState at_mean = map;
  for (int i = 0; i < n; ++i) {
    Landmark l = *map.FindLandmark(i + 1);
    l.position = LocalFrame(l.anchor).ToGeo(mean.segment<2>(2 * i));
    at_mean.PutLandmark(l);
  }
  MapWindowOptions options;
  options.hops = 5;
  const LandmarkId centre = (side / 2) * side + side / 2 + 1;
  absl::StatusOr<MapWindow> w = MapWindow::Build(at_mean, {centre}, options);
  ASSERT_TRUE(w.ok()) << w.status();
  EXPECT_FALSE(w->closed());
  const int m = static_cast<int>(w->landmarks().size());
  ASSERT_GT(2 * m, 600) << "the supernodal factor";
  ASSERT_LT(m, n);
  for (int k = 0; k < m; ++k) {
    const int i = static_cast<int>(w->landmarks()[k]) - 1;
    ASSERT_LT((w->offsets().segment<2>(2 * k) - mean.segment<2>(2 * i)).cwiseAbs().maxCoeff(), 1e-6)
        << "landmark " << i + 1;
  }
  // The seed and landmarks across the window, against the exact marginal (columns of h^-1).
  std::vector<LandmarkId> ids;
  for (int k = 0; k < m; k += m / 12) ids.push_back(w->landmarks()[k]);
  Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(2 * n, 2 * static_cast<int>(ids.size()));
  for (size_t k = 0; k < ids.size(); ++k) unit.block<2, 2>(2 * (ids[k] - 1), 2 * k).setIdentity();
  const Eigen::MatrixXd exact = unit.transpose() * llt.solve(unit);
  absl::StatusOr<Eigen::MatrixXd> cov = w->Covariance(ids);
  ASSERT_TRUE(cov.ok()) << cov.status();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> diff(*cov - exact);
  EXPECT_GT(diff.eigenvalues().minCoeff(), -1e-9 * exact.diagonal().maxCoeff());
  EXPECT_GT(diff.eigenvalues().maxCoeff(), 1e-6 * exact.diagonal().maxCoeff()) << "the window lost information";
  MapWindowOptions covariance_only = options;
  covariance_only.estimate = false;
  absl::StatusOr<MapWindow> read = MapWindow::Build(at_mean, {centre}, covariance_only);
  ASSERT_TRUE(read.ok()) << read.status();
  absl::StatusOr<Eigen::MatrixXd> read_cov = read->Covariance(ids);
  ASSERT_TRUE(read_cov.ok()) << read_cov.status();
  EXPECT_LT((*read_cov - *cov).cwiseAbs().maxCoeff(), 1e-10 * exact.diagonal().maxCoeff());
}

// A map whose factor `factor` (or landmark `landmark`) is still named by a landmark's list (or
// link) but absent when read: what a worker reads when another worker's commit removes it between
// its reads. With `listed_whole`, the factor's landmarks can still be read and only the whole
// factor is gone.
class GoneMeanwhile : public MapState {
 public:
  GoneMeanwhile(const MapState& map, int64_t factor, LandmarkId landmark, bool listed_whole)
      : MapState(map), factor_(factor), landmark_(landmark), listed_whole_(listed_whole) {}
  const Landmark* FindLandmark(LandmarkId id) const override {
    return id == landmark_ ? nullptr : MapState::FindLandmark(id);
  }
  const MapFactor* FindFactor(int64_t id) const override { return id == factor_ ? nullptr : MapState::FindFactor(id); }
  bool AppendFactorLandmarks(int64_t id, std::vector<LandmarkId>* out) const override {
    const MapFactor* f = id == factor_ && !listed_whole_ ? nullptr : MapState::FindFactor(id);
    if (f == nullptr) return false;
    out->insert(out->end(), f->landmarks.begin(), f->landmarks.end());
    return true;
  }

 private:
  int64_t factor_;
  LandmarkId landmark_;
  bool listed_whole_;
};

// Landmark 5 with 1 link: the window {5, 4, 6}, whose factors 3 = {3, 4} and 6 = {6, 7} cross its
// edge. A crossing factor, or a landmark outside, gone meanwhile fails the window (the worker
// computes it again), whichever read finds it gone.
TEST(MapWindow, AFactorOrLandmarkGoneWhileTheWindowIsReadFailsIt) {
  const MapState chain = Chain(12, 3);
  MapWindowOptions options;
  options.hops = 1;
  const auto expect_gone = [&](const MapState& map, const std::string& what) {
    absl::StatusOr<MapWindow> w = MapWindow::Build(map, {5}, options);
    ASSERT_FALSE(w.ok()) << what;
    EXPECT_EQ(w.status().code(), absl::StatusCode::kAborted) << w.status();
    EXPECT_NE(w.status().message().find(what), std::string::npos) << w.status();
  };
  expect_gone(GoneMeanwhile(chain, 3, 0, /*listed_whole=*/true), "map factor 3");
  expect_gone(GoneMeanwhile(chain, 3, 0, /*listed_whole=*/false), "map factor 3");
  expect_gone(GoneMeanwhile(chain, 0, 7, false), "landmark 7");
  EXPECT_TRUE(MapWindow::Build(chain, {5}, options).ok());
}

TEST(MapWindow, UnknownSeedAndSingularInformationFailCleanly) {
  MapState map = Chain(3, 3);
  EXPECT_EQ(MapWindow::Build(map, {99}, {}).status().code(), absl::StatusCode::kNotFound);
  MapFactor flat;
  flat.id = 10;
  flat.landmarks = {1};
  flat.information = -100.0 * Eigen::Matrix2d::Identity();
  flat.information_vector = Eigen::Vector2d::Zero();
  map.PutFactor(flat);
  EXPECT_EQ(MapWindow::Build(map, {1}, {}).status().code(), absl::StatusCode::kFailedPrecondition);
  MapWindowOptions bad;
  bad.hops = -1;
  EXPECT_EQ(MapWindow::Build(map, {1}, bad).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap
