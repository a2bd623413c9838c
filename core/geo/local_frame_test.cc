#include "core/geo/local_frame.h"

#include <cmath>

#include <Eigen/LU>
#include <GeographicLib/Geodesic.hpp>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

const LatLon kOrigin{48.7128, 2.1700};

// Geodesic distance (m) between two points on the WGS84 ellipsoid.
double GeodesicDistance(const LatLon& a, const LatLon& b) {
  double s12;
  GeographicLib::Geodesic::WGS84().Inverse(a.lat_deg, a.lon_deg, b.lat_deg, b.lon_deg, s12);
  return s12;
}

// The point at distance s_m and azimuth (clockwise from North) azi_deg from `a`, on the ellipsoid.
LatLon GeodesicDirect(const LatLon& a, double azi_deg, double s_m) {
  LatLon b;
  GeographicLib::Geodesic::WGS84().Direct(a.lat_deg, a.lon_deg, azi_deg, s_m, b.lat_deg, b.lon_deg);
  return b;
}

TEST(LocalFrame, OriginMapsToZero) {
  const LocalFrame frame(kOrigin);
  EXPECT_LT(frame.ToLocal(kOrigin).norm(), 1e-9);
  const LatLon back = frame.ToGeo(Eigen::Vector2d::Zero());
  EXPECT_LT(GeodesicDistance(back, kOrigin), 1e-9);
}

TEST(LocalFrame, ToGeoThenToLocalRoundTripsWithinMicrometresAtOneKilometre) {
  const LocalFrame frame(kOrigin);
  for (double azimuth = 0.0; azimuth < 2 * M_PI; azimuth += M_PI / 6) {
    const Eigen::Vector2d en = 1000.0 * Eigen::Vector2d(std::cos(azimuth), std::sin(azimuth));
    EXPECT_LT((frame.ToLocal(frame.ToGeo(en)) - en).norm(), 1e-6) << en.transpose();
  }
}

TEST(LocalFrame, ToGeoThenToLocalRoundTripsBelowAMillimetreAtFiveKilometres) {
  const LocalFrame frame(kOrigin);
  for (double azimuth = 0.0; azimuth < 2 * M_PI; azimuth += M_PI / 6) {
    const Eigen::Vector2d en = 5000.0 * Eigen::Vector2d(std::cos(azimuth), std::sin(azimuth));
    EXPECT_LT((frame.ToLocal(frame.ToGeo(en)) - en).norm(), 1e-3) << en.transpose();
  }
}

TEST(LocalFrame, ToLocalThenToGeoReturnsTheSamePointOnTheEllipsoid) {
  const LocalFrame frame(kOrigin);
  for (double azimuth_deg : {0.0, 45.0, 130.0, 250.0, 315.0}) {
    const LatLon p = GeodesicDirect(kOrigin, azimuth_deg, 5000.0);
    EXPECT_LT(GeodesicDistance(frame.ToGeo(frame.ToLocal(p)), p), 1e-3) << azimuth_deg;
  }
}

TEST(LocalFrame, RoundTripsAcrossTheAntimeridianAndInTheSouth) {
  for (const LatLon origin : {LatLon{-33.86, 151.21}, LatLon{10.0, 179.999}, LatLon{-60.0, -179.999}}) {
    const LocalFrame frame(origin);
    for (const Eigen::Vector2d& en : {Eigen::Vector2d(1000.0, 200.0), Eigen::Vector2d(-1000.0, -300.0)}) {
      const LatLon p = frame.ToGeo(en);
      EXPECT_GE(p.lon_deg, -180.0);
      EXPECT_LE(p.lon_deg, 180.0);
      EXPECT_LT((frame.ToLocal(p) - en).norm(), 1e-6) << origin.lat_deg << " " << origin.lon_deg;
    }
  }
}

TEST(LocalFrame, EnToLocalIsIdentityAtTheOrigin) {
  const LocalFrame frame(kOrigin);
  EXPECT_LT((frame.EnToLocal(kOrigin) - Eigen::Matrix2d::Identity()).norm(), 1e-12);
}

TEST(LocalFrame, EnToLocalMatchesFiniteDifferencesThreeKilometresAway) {
  const LocalFrame frame(kOrigin);
  const LatLon p = frame.ToGeo({3000.0, 0.0});
  const LocalFrame at_p(p);
  const double h = 1.0;  // m; curvature terms are O(h^2 / R^2), rounding O(1e-9 / h)
  Eigen::Matrix2d numeric;
  for (int k = 0; k < 2; ++k) {
    Eigen::Vector2d step = Eigen::Vector2d::Zero();
    step[k] = h;
    numeric.col(k) = (frame.ToLocal(at_p.ToGeo(step)) - frame.ToLocal(at_p.ToGeo(-step))) / (2 * h);
  }
  const Eigen::Matrix2d analytic = frame.EnToLocal(p);
  EXPECT_LT((analytic - numeric).cwiseAbs().maxCoeff(), 1e-7) << analytic << "\n" << numeric;
  // The map is a rotation by the meridian convergence, about dlon * sin(lat) (4.7e-4 rad here):
  // North at a point east of the origin leans West in the origin's frame.
  const double convergence = (p.lon_deg - kOrigin.lon_deg) * M_PI / 180.0 * std::sin(kOrigin.lat_deg * M_PI / 180.0);
  EXPECT_NEAR(analytic(0, 1), -convergence, 0.02 * convergence);
  EXPECT_NEAR(analytic(1, 0), convergence, 0.02 * convergence);
  // The 2x2 block of a 3D rotation: its determinant is the cosine of the tilt between the two
  // Up axes, 1 - (3 km / R)^2 / 2 = 1 - 1.1e-7.
  EXPECT_NEAR(analytic.determinant(), 1.0 - 0.5 * std::pow(3000.0 / 6.371e6, 2), 1e-9);
}

TEST(EastNorthOffset, AgreesWithTheGeodesicToAMillimetre) {
  for (const LatLon a : {kOrigin, LatLon{-33.86, 151.21}, LatLon{0.0, 0.0}}) {
    for (double azimuth_deg : {0.0, 30.0, 100.0, 200.0, 290.0}) {
      for (double s : {350.0, 2000.0}) {
        const LatLon b = GeodesicDirect(a, azimuth_deg, s);
        const double azimuth = azimuth_deg * M_PI / 180.0;
        const Eigen::Vector2d expected(s * std::sin(azimuth), s * std::cos(azimuth));
        const Eigen::Vector2d offset = EastNorthOffset(a, b);
        EXPECT_LT((offset - expected).norm(), 1e-3) << a.lat_deg << " azimuth " << azimuth_deg << " s " << s;
        EXPECT_NEAR(offset.norm(), GeodesicDistance(a, b), 1e-3);
      }
    }
  }
}

}  // namespace
}  // namespace crowdmap
