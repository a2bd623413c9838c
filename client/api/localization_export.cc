#include "client/api/localization_export.h"

#include <cmath>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/strings/str_format.h"
#include "server/geojson.h"

namespace crowdmap {
namespace {

using Json = nlohmann::ordered_json;

Json Position(const ::mapservice::v1::LocalizedPose& p) {
  return Json::array({GeoJsonDegrees(p.lon_deg()), GeoJsonDegrees(p.lat_deg())});
}

double Cov(const ::mapservice::v1::LocalizedPose& p, int r, int c) {
  return p.covariance_size() == 9 ? p.covariance(3 * r + c) : std::nan("");
}

}  // namespace

std::string LocalizationToCsv(const ::mapservice::v1::LocalizePassageResponse& localization) {
  std::string out = "t_s,lat_deg,lon_deg,heading_rad,cov_ee,cov_en,cov_eh,cov_nn,cov_nh,cov_hh\n";
  for (const auto& p : localization.poses()) {
    absl::StrAppendFormat(&out, "%.3f,%.9f,%.9f,%.6f,%.6g,%.6g,%.6g,%.6g,%.6g,%.6g\n", p.t_s(), p.lat_deg(),
                          p.lon_deg(), p.heading_rad(), Cov(p, 0, 0), Cov(p, 0, 1), Cov(p, 0, 2), Cov(p, 1, 1),
                          Cov(p, 1, 2), Cov(p, 2, 2));
  }
  return out;
}

std::string LocalizationToGeoJson(const ::mapservice::v1::LocalizePassageResponse& localization) {
  Json track = Json::array();
  for (const auto& p : localization.poses()) track.push_back(Position(p));
  const std::vector<int64_t> landmarks_used(localization.landmarks_used().begin(), localization.landmarks_used().end());
  Json features = Json::array();
  features.push_back({{"type", "Feature"},
                      {"geometry", {{"type", "LineString"}, {"coordinates", track}}},
                      {"properties",
                       {{"map_version", localization.map_version()},
                        {"chi2", localization.chi2()},
                        {"dof", localization.dof()},
                        {"landmarks_used", landmarks_used},
                        {"detections_used", localization.detections_used()},
                        {"detections_rejected", localization.rejected_size()}}}});
  // A pose without covariance has null standard deviations.
  for (const auto& p : localization.poses()) {
    features.push_back({{"type", "Feature"},
                        {"geometry", {{"type", "Point"}, {"coordinates", Position(p)}}},
                        {"properties",
                         {{"t_s", p.t_s()},
                          {"heading_rad", p.heading_rad()},
                          {"sigma_east_m", std::sqrt(Cov(p, 0, 0))},
                          {"sigma_north_m", std::sqrt(Cov(p, 1, 1))},
                          {"sigma_heading_rad", std::sqrt(Cov(p, 2, 2))}}}});
  }
  const Json collection = {{"type", "FeatureCollection"}, {"features", features}};
  return collection.dump() + "\n";
}

}  // namespace crowdmap
