#include "core/geo/local_frame.h"

#include <vector>

#include <GeographicLib/Geocentric.hpp>

namespace crowdmap {

LocalFrame::LocalFrame(const LatLon& origin)
    : origin_(origin),
      cartesian_(origin.lat_deg, origin.lon_deg, 0.0, GeographicLib::Geocentric::WGS84()) {}

Eigen::Vector2d LocalFrame::ToLocal(const LatLon& p) const {
  double x, y, z;
  cartesian_.Forward(p.lat_deg, p.lon_deg, 0.0, x, y, z);
  return {x, y};
}

LatLon LocalFrame::ToGeo(const Eigen::Vector2d& en) const {
  // The tangent plane drops below the ellipsoid with distance; find the plane height z at which
  // the point is on the ellipsoid. Two fixed-point steps reach micrometres at 100 km.
  double lat, lon, h, z = 0.0;
  for (int i = 0; i < 3; ++i) {
    cartesian_.Reverse(en.x(), en.y(), z, lat, lon, h);
    z -= h;
  }
  cartesian_.Reverse(en.x(), en.y(), z, lat, lon, h);
  return {lat, lon};
}

Eigen::Matrix2d LocalFrame::EnToLocal(const LatLon& p) const {
  double x, y, z;
  std::vector<double> m(9);
  // m is row-major and rotates East/North/Up at p into the local frame's axes.
  cartesian_.Forward(p.lat_deg, p.lon_deg, 0.0, x, y, z, m);
  Eigen::Matrix2d r;
  r << m[0], m[1], m[3], m[4];
  return r;
}

Eigen::Vector2d EastNorthOffset(const LatLon& a, const LatLon& b) {
  return LocalFrame(a).ToLocal(b);
}

}  // namespace crowdmap
