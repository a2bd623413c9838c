#include "server/geojson.h"

#include <cmath>

#include "gtest/gtest.h"

namespace crowdmap {
namespace {

TEST(ErrorEllipse95, AxesAndAzimuthOfAnEastElongatedCovariance) {
  Eigen::Matrix2d cov;
  cov << 4.0, 0.0, 0.0, 1.0;
  const ErrorEllipse e = ErrorEllipse95(cov);
  EXPECT_NEAR(e.semi_major_m, std::sqrt(5.991464547 * 4.0), 1e-6);
  EXPECT_NEAR(e.semi_minor_m, std::sqrt(5.991464547), 1e-6);
  EXPECT_NEAR(e.azimuth_deg, 90.0, 1e-9);
}

TEST(ErrorEllipse95, AzimuthFollowsTheMajorAxisClockwiseFromNorth) {
  // Major axis along North-East (azimuth 45): covariance R diag(9, 1) R^T.
  const double c = std::cos(M_PI / 4), s = std::sin(M_PI / 4);
  Eigen::Matrix2d rot;
  rot << c, -s, s, c;
  const Eigen::Matrix2d cov = rot * Eigen::Vector2d(9.0, 1.0).asDiagonal() * rot.transpose();
  const ErrorEllipse e = ErrorEllipse95(cov);
  EXPECT_NEAR(e.azimuth_deg, 45.0, 1e-9);
  EXPECT_NEAR(e.semi_major_m / e.semi_minor_m, 3.0, 1e-9);
}

TEST(LandmarksToGeoJson, PointsInLonLatOrderAndCounterclockwiseEllipses) {
  ::mapservice::v1::Landmark l;
  l.set_id(7);
  l.set_lat_deg(48.5);
  l.set_lon_deg(2.25);
  l.mutable_cov_en_m2()->set_ee(4.0);
  l.mutable_cov_en_m2()->set_nn(1.0);
  l.set_version(3);
  GeoJsonOptions options;
  options.ellipses = true;
  options.ellipse_points = 16;
  const std::string text = LandmarksToGeoJson({l}, 3, options);
  EXPECT_NE(text.find("\"coordinates\": [2.250000000, 48.500000000]"), std::string::npos) << text;
  EXPECT_NE(text.find("\"version\": 3"), std::string::npos);
  // Shoelace area of the ring in (lon, lat): positive when counterclockwise.
  const size_t ring = text.find("\"Polygon\", \"coordinates\": [[[");
  ASSERT_NE(ring, std::string::npos);
  std::vector<std::pair<double, double>> pts;
  size_t p = text.find("[[[", ring) + 2;
  while (true) {
    double lon, lat;
    if (sscanf(text.c_str() + p, "[%lf, %lf]", &lon, &lat) != 2) break;
    pts.emplace_back(lon, lat);
    p = text.find(']', p) + 1;
    if (text[p] != ',') break;
    p += 2;
  }
  ASSERT_EQ(pts.size(), 17u);
  EXPECT_EQ(pts.front(), pts.back());
  double area = 0.0;
  for (size_t i = 0; i + 1 < pts.size(); ++i) area += pts[i].first * pts[i + 1].second - pts[i + 1].first * pts[i].second;
  EXPECT_GT(area, 0.0);
}

}  // namespace
}  // namespace crowdmap
