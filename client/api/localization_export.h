#ifndef CROWDMAP_CLIENT_API_LOCALIZATION_EXPORT_H_
#define CROWDMAP_CLIENT_API_LOCALIZATION_EXPORT_H_

#include <string>

#include "mapservice/v1/map_service.pb.h"

namespace crowdmap {

// One line per pose: t_s, lat_deg, lon_deg, heading_rad, then the upper triangle of the
// (East m, North m, heading rad) covariance: cov_ee, cov_en, cov_eh, cov_nn, cov_nh, cov_hh.
std::string LocalizationToCsv(const ::mapservice::v1::LocalizePassageResponse& localization);

// RFC 7946 FeatureCollection: the trajectory as a LineString (with the map version, chi-square,
// landmarks used and rejections as properties), then one Point per pose with its time, heading
// and standard deviations.
std::string LocalizationToGeoJson(const ::mapservice::v1::LocalizePassageResponse& localization);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_API_LOCALIZATION_EXPORT_H_
