#include "client/api/localization_export.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"

namespace crowdmap {
namespace {

std::string Coord(const ::mapservice::v1::LocalizedPose& p) {
  return absl::StrFormat("[%.9f, %.9f]", p.lon_deg(), p.lat_deg());
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
  std::vector<std::string> coords, features;
  for (const auto& p : localization.poses()) coords.push_back(Coord(p));
  features.push_back(absl::StrFormat(
      R"({"type": "Feature", "geometry": {"type": "LineString", "coordinates": [%s]}, "properties": )"
      R"({"map_version": %d, "chi2": %.6g, "dof": %d, "landmarks_used": [%s], "detections_used": %d, )"
      R"("detections_rejected": %d}})",
      absl::StrJoin(coords, ", "), localization.map_version(), localization.chi2(), localization.dof(),
      absl::StrJoin(localization.landmarks_used(), ", "), localization.detections_used(), localization.rejected_size()));
  for (const auto& p : localization.poses()) {
    features.push_back(absl::StrFormat(
        R"({"type": "Feature", "geometry": {"type": "Point", "coordinates": %s}, "properties": )"
        R"({"t_s": %.3f, "heading_rad": %.6f, "sigma_east_m": %.4g, "sigma_north_m": %.4g, "sigma_heading_rad": %.4g}})",
        Coord(p), p.t_s(), p.heading_rad(), std::sqrt(Cov(p, 0, 0)), std::sqrt(Cov(p, 1, 1)), std::sqrt(Cov(p, 2, 2))));
  }
  return absl::StrCat(R"({"type": "FeatureCollection", "features": [)", "\n", absl::StrJoin(features, ",\n"), "\n]}\n");
}

}  // namespace crowdmap
