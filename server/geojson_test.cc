#include "server/geojson.h"

#include <cmath>

#include <nlohmann/json.hpp>

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

TEST(GeoJsonDegrees, KeepsNineDecimals) {
  EXPECT_EQ(GeoJsonDegrees(48.1371541234567), 48.137154123);
  EXPECT_EQ(GeoJsonDegrees(-122.4000000004), -122.4);
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
  const nlohmann::json collection = nlohmann::json::parse(LandmarksToGeoJson({l}, 3, options));
  EXPECT_EQ(collection["type"], "FeatureCollection");
  EXPECT_EQ(collection["map_version"], 3);
  ASSERT_EQ(collection["features"].size(), 2u);
  const nlohmann::json& point = collection["features"][0];
  EXPECT_EQ(point["geometry"]["coordinates"], nlohmann::json::array({2.25, 48.5}));
  EXPECT_EQ(point["properties"]["version"], 3);
  EXPECT_EQ(point["properties"]["cov_en_m2"], nlohmann::json::array({{4.0, 0.0}, {0.0, 1.0}}));
  // Shoelace area of the ring in (lon, lat): positive when counterclockwise.
  const nlohmann::json& polygon = collection["features"][1]["geometry"];
  EXPECT_EQ(polygon["type"], "Polygon");
  const nlohmann::json& ring = polygon["coordinates"][0];
  ASSERT_EQ(ring.size(), 17u);
  EXPECT_EQ(ring.front(), ring.back());
  double area = 0.0;
  for (size_t i = 0; i + 1 < ring.size(); ++i) {
    area += ring[i][0].get<double>() * ring[i + 1][1].get<double>() - ring[i + 1][0].get<double>() * ring[i][1].get<double>();
  }
  EXPECT_GT(area, 0.0);
}

}  // namespace
}  // namespace crowdmap
