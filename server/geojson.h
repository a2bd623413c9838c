#ifndef CROWDMAP_SERVER_GEOJSON_H_
#define CROWDMAP_SERVER_GEOJSON_H_

#include <string>
#include <vector>

#include <Eigen/Core>

#include "mapservice/v1/map.pb.h"

namespace crowdmap {

// Axes of the 95% error ellipse (chi-square, 2 degrees of freedom) of an East/North covariance.
struct ErrorEllipse {
  double semi_major_m = 0.0;
  double semi_minor_m = 0.0;
  double azimuth_deg = 0.0;  // major axis, clockwise from North, in [0, 180)
};

ErrorEllipse ErrorEllipse95(const Eigen::Matrix2d& cov_en_m2);

// A GeoJSON position's coordinate, degrees rounded to 9 decimals (0.1 mm): more digits only make
// the text longer (RFC 7946 section 11.2).
double GeoJsonDegrees(double deg);

struct GeoJsonOptions {
  bool ellipses = false;    // add each landmark's 95% error ellipse as a Polygon feature
  int ellipse_points = 36;  // vertices per ellipse ring (>= 8)
};

// RFC 7946 FeatureCollection, on one line: one Point per landmark ([lon, lat]) with id,
// covariance, 95% ellipse, version and counts as properties; optionally the ellipses as
// counterclockwise Polygons. `removed_ids`, when given (a change list), are the collection's
// `removed_ids`: landmarks the map no longer holds.
std::string LandmarksToGeoJson(const std::vector<::mapservice::v1::Landmark>& landmarks, int64_t map_version,
                               const GeoJsonOptions& options, const std::vector<int64_t>* removed_ids = nullptr);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_GEOJSON_H_
