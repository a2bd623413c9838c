#include "core/geo/local_frame.h"

#include <GeographicLib/Geodesic.hpp>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

const LatLon kOrigin{48.7128, 2.1700};

TEST(LocalFrame, OriginMapsToZeroAndRoundTripsWithinMicrometres) {
  const LocalFrame frame(kOrigin);
  EXPECT_LT(frame.ToLocal(kOrigin).norm(), 1e-9);
  for (const Eigen::Vector2d en : {Eigen::Vector2d(1000.0, -700.0), Eigen::Vector2d(-5000.0, 4000.0)}) {
    const Eigen::Vector2d back = frame.ToLocal(frame.ToGeo(en));
    EXPECT_LT((back - en).norm(), 1e-6) << en.transpose();
  }
}

TEST(LocalFrame, EnToLocalIsIdentityAtTheOriginAndMatchesFiniteDifferencesAway) {
  const LocalFrame frame(kOrigin);
  EXPECT_TRUE(frame.EnToLocal(kOrigin).isApprox(Eigen::Matrix2d::Identity(), 1e-12));
  const LatLon p = frame.ToGeo({3000.0, 2000.0});
  const LocalFrame at_p(p);
  const double h = 1.0;
  Eigen::Matrix2d numeric;
  for (int k = 0; k < 2; ++k) {
    Eigen::Vector2d step = Eigen::Vector2d::Zero();
    step[k] = h;
    numeric.col(k) = (frame.ToLocal(at_p.ToGeo(step)) - frame.ToLocal(at_p.ToGeo(-step))) / (2 * h);
  }
  EXPECT_TRUE(frame.EnToLocal(p).isApprox(numeric, 1e-6)) << frame.EnToLocal(p) << "\n" << numeric;
  // 3 km east at 48.7 deg the meridians converge by about 4e-4 rad: not the identity.
  EXPECT_GT(std::abs(frame.EnToLocal(p)(0, 1)), 1e-4);
}

TEST(EastNorthOffset, AgreesWithTheGeodesicDistance) {
  const LocalFrame frame(kOrigin);
  const LatLon b = frame.ToGeo({350.0, -120.0});
  double distance;
  GeographicLib::Geodesic::WGS84().Inverse(kOrigin.lat_deg, kOrigin.lon_deg, b.lat_deg, b.lon_deg, distance);
  EXPECT_NEAR(EastNorthOffset(kOrigin, b).norm(), distance, 1e-3);
}

}  // namespace
}  // namespace crowdmap
