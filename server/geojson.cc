#include "server/geojson.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>
#include <nlohmann/json.hpp>

#include "core/geo/local_frame.h"

namespace crowdmap {
namespace {

constexpr double kChi2Dof2P95 = 5.991464547107979;  // chi-square quantile, 2 dof, p = 0.95

using Json = nlohmann::ordered_json;

Json Position(const LatLon& p) { return Json::array({GeoJsonDegrees(p.lon_deg), GeoJsonDegrees(p.lat_deg)}); }

Eigen::Matrix2d Cov(const ::mapservice::v1::Landmark& l) {
  Eigen::Matrix2d c;
  c << l.cov_en_m2().ee(), l.cov_en_m2().en(), l.cov_en_m2().ne(), l.cov_en_m2().nn();
  return c;
}

Json EllipseRing(const LatLon& center, const Eigen::Matrix2d& cov, int points) {
  const ErrorEllipse e = ErrorEllipse95(cov);
  const double azimuth_rad = e.azimuth_deg * M_PI / 180.0;
  const Eigen::Vector2d major_dir(std::sin(azimuth_rad), std::cos(azimuth_rad));  // (East, North)
  const Eigen::Vector2d minor_dir(-major_dir.y(), major_dir.x());  // +90 deg: the ring runs counterclockwise
  const LocalFrame frame(center);
  Json ring = Json::array();
  for (int k = 0; k <= points; ++k) {
    const double t = 2.0 * M_PI * (k % points) / points;
    const Eigen::Vector2d en = e.semi_major_m * std::cos(t) * major_dir + e.semi_minor_m * std::sin(t) * minor_dir;
    ring.push_back(Position(frame.ToGeo(en)));
  }
  return ring;
}

}  // namespace

ErrorEllipse ErrorEllipse95(const Eigen::Matrix2d& cov_en_m2) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(0.5 * (cov_en_m2 + cov_en_m2.transpose()));
  ErrorEllipse e;
  e.semi_major_m = std::sqrt(kChi2Dof2P95 * std::max(0.0, eig.eigenvalues()(1)));
  e.semi_minor_m = std::sqrt(kChi2Dof2P95 * std::max(0.0, eig.eigenvalues()(0)));
  const Eigen::Vector2d major = eig.eigenvectors().col(1);  // (East, North)
  double azimuth = std::atan2(major.x(), major.y()) * 180.0 / M_PI;
  azimuth = std::fmod(azimuth + 360.0, 180.0);
  e.azimuth_deg = azimuth >= 180.0 ? 0.0 : azimuth;
  return e;
}

double GeoJsonDegrees(double deg) { return std::round(deg * 1e9) / 1e9; }

std::string LandmarksToGeoJson(const std::vector<::mapservice::v1::Landmark>& landmarks, int64_t map_version,
                               const GeoJsonOptions& options, const std::vector<int64_t>* removed_ids) {
  const int points = std::max(8, options.ellipse_points);
  Json features = Json::array();
  for (const ::mapservice::v1::Landmark& l : landmarks) {
    const LatLon position{l.lat_deg(), l.lon_deg()};
    const Eigen::Matrix2d cov = Cov(l);
    const ErrorEllipse e = ErrorEllipse95(cov);
    features.push_back({{"type", "Feature"},
                        {"id", l.id()},
                        {"geometry", {{"type", "Point"}, {"coordinates", Position(position)}}},
                        {"properties",
                         {{"id", l.id()},
                          {"kind", "landmark"},
                          {"cov_en_m2", Json::array({Json::array({cov(0, 0), cov(0, 1)}),
                                                     Json::array({cov(1, 0), cov(1, 1)})})},
                          {"sigma_east_m", std::sqrt(cov(0, 0))},
                          {"sigma_north_m", std::sqrt(cov(1, 1))},
                          {"ellipse95_semi_major_m", e.semi_major_m},
                          {"ellipse95_semi_minor_m", e.semi_minor_m},
                          {"ellipse95_azimuth_deg", e.azimuth_deg},
                          {"version", l.version()},
                          {"passages_seen", l.passages_seen()},
                          {"last_seen_unix_ms", l.last_seen_unix_ms()}}}});
    if (options.ellipses) {
      features.push_back(
          {{"type", "Feature"},
           {"geometry", {{"type", "Polygon"}, {"coordinates", Json::array({EllipseRing(position, cov, points)})}}},
           {"properties", {{"id", l.id()}, {"kind", "error_ellipse_95"}}}});
    }
  }
  Json collection = {{"type", "FeatureCollection"}, {"map_version", map_version}, {"features", features}};
  if (removed_ids != nullptr) collection["removed_ids"] = *removed_ids;
  return collection.dump() + "\n";
}

}  // namespace crowdmap
