#include "core/estimation/passage_prior.h"

#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// A random positive definite information over `dims` (plus a random information vector).
MapFactor RandomFactor(int64_t id, std::vector<LandmarkId> landmarks, std::mt19937_64* rng) {
  std::normal_distribution<double> g(0.0, 1.0);
  const int dims = 2 * static_cast<int>(landmarks.size());
  Eigen::MatrixXd a(dims + 2, dims);
  for (int r = 0; r < a.rows(); ++r) {
    for (int c = 0; c < dims; ++c) a(r, c) = g(*rng);
  }
  MapFactor f;
  f.id = id;
  f.landmarks = std::move(landmarks);
  f.information = a.transpose() * a;
  f.information_vector = Eigen::VectorXd::NullaryExpr(dims, [&] { return g(*rng); });
  return f;
}

Landmark At(LandmarkId id) {
  Landmark l;
  l.id = id;
  l.anchor = {45.0 + 1e-4 * static_cast<double>(id), 4.0};
  l.position = l.anchor;
  return l;
}

// A chain of 8 landmarks: one factor on each, one on each neighbouring pair.
MapState Chain(std::mt19937_64* rng) {
  MapState map;
  for (LandmarkId id = 1; id <= 8; ++id) map.PutLandmark(At(id));
  int64_t next = 1;
  for (LandmarkId id = 1; id <= 8; ++id) map.PutFactor(RandomFactor(next++, {id}, rng));
  for (LandmarkId id = 1; id < 8; ++id) map.PutFactor(RandomFactor(next++, {id, id + 1}, rng));
  // The records at the map's estimate, as a committed map keeps them.
  std::vector<LandmarkId> ids = map.LandmarkIds();
  const MapWindow window = *MapWindow::Build(map, ids, MapWindowOptions{});
  for (size_t k = 0; k < ids.size(); ++k) {
    Landmark l = *map.FindLandmark(ids[k]);
    l.position = LocalFrame(l.anchor).ToGeo(window.offsets().segment<2>(2 * k));
    map.PutLandmark(l);
  }
  return map;
}

TEST(PassagePrior, TracksTheSeenMapLandmarksOnly) {
  std::mt19937_64 rng(3);
  const MapState map = Chain(&rng);
  absl::StatusOr<PassagePrior> prior = PassagePrior::Build(map, {4, 5, 4, 99}, MapWindowOptions{});
  ASSERT_TRUE(prior.ok()) << prior.status();
  EXPECT_TRUE(prior->Tracks(4));
  EXPECT_TRUE(prior->Tracks(5));
  EXPECT_FALSE(prior->Tracks(99)) << "not in the map: left to the subgraphs to create";
  EXPECT_FALSE(prior->Tracks(1)) << "in the window, not seen";
  EXPECT_EQ(prior->Covariance({1}).status().code(), absl::StatusCode::kInvalidArgument);
  // The tracked covariance is the map's joint covariance of the seen landmarks.
  const Eigen::MatrixXd expected = *JointCovariance(map, {5, 4});
  EXPECT_LT((*prior->Covariance({5, 4}) - expected).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(PassagePrior, ConditioningTwoFactorsEqualsTheMapSolvedWithThem) {
  std::mt19937_64 rng(7);
  const MapState map = Chain(&rng);
  MapOverlay overlay(map);
  absl::StatusOr<PassagePrior> prior = PassagePrior::Build(overlay, {3, 4, 5, 6}, MapWindowOptions{});
  ASSERT_TRUE(prior.ok()) << prior.status();
  // Two subgraphs' factors: the first creates landmark 20, which the second sees again.
  overlay.PutLandmark(At(20));
  int touched = 0;
  const auto touch = [&](Landmark*) { ++touched; };
  for (const std::vector<LandmarkId>& landmarks : {std::vector<LandmarkId>{3, 4, 20}, std::vector<LandmarkId>{5, 6, 20}}) {
    const int64_t id = overlay.AddFactor(RandomFactor(0, landmarks, &rng));
    absl::StatusOr<int> conditioned = prior->Condition(*overlay.FindFactor(id), overlay.BumpVersion(), touch, &overlay);
    ASSERT_TRUE(conditioned.ok()) << conditioned.status();
  }
  EXPECT_EQ(touched, 6);
  absl::StatusOr<int> moved = prior->Finish(overlay.version(), &overlay);
  ASSERT_TRUE(moved.ok()) << moved.status();
  EXPECT_GT(*moved, 0) << "landmarks 1, 2, 7, 8 move through their correlation";

  MapState after = map;
  after.Apply(overlay.TakeDelta());
  const std::vector<LandmarkId> all = after.LandmarkIds();
  const MapWindow exact = *MapWindow::Build(after, all, MapWindowOptions{});
  for (size_t k = 0; k < all.size(); ++k) {
    EXPECT_LT((after.FindLandmark(all[k])->Offset() - exact.offsets().segment<2>(2 * k)).norm(), 1e-6) << all[k];
  }
  const std::vector<LandmarkId> tracked = {3, 4, 5, 6, 20};
  EXPECT_LT((*prior->Covariance(tracked) - *exact.Covariance(tracked)).cwiseAbs().maxCoeff(), 1e-9);
  // The records of the landmarks the factors touched hold their exact marginals.
  for (LandmarkId id : tracked) {
    EXPECT_LT((after.FindLandmark(id)->cov_en_m2 - *exact.Covariance({id})).cwiseAbs().maxCoeff(), 1e-9) << id;
  }
}

}  // namespace
}  // namespace crowdmap
