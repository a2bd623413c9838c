#ifndef CROWDMAP_CORE_GEO_LOCAL_FRAME_H_
#define CROWDMAP_CORE_GEO_LOCAL_FRAME_H_

#include <Eigen/Core>
#include <GeographicLib/LocalCartesian.hpp>

namespace crowdmap {

// A WGS84 position in degrees.
struct LatLon {
  double lat_deg = 0.0;
  double lon_deg = 0.0;
};

// Local East/North tangent frame (metres) around an origin on the WGS84 ellipsoid. All points are
// taken on the ellipsoid (height 0); the estimation is 2D in this plane.
class LocalFrame {
 public:
  explicit LocalFrame(const LatLon& origin);

  const LatLon& origin() const { return origin_; }

  // East/North coordinates (m) of a point on the ellipsoid.
  Eigen::Vector2d ToLocal(const LatLon& p) const;

  // The point on the ellipsoid whose East/North coordinates are `en` (the tangent-plane height is
  // chosen so that the result lies on the ellipsoid, not above it).
  LatLon ToGeo(const Eigen::Vector2d& en) const;

  // Maps East/North components at `p` into this frame's axes (derivative of ToLocal with respect
  // to East/North displacements at p). Identity at the origin.
  Eigen::Matrix2d EnToLocal(const LatLon& p) const;

 private:
  LatLon origin_;
  GeographicLib::LocalCartesian cartesian_;
};

// East/North offset (m) from `a` to `b`, in the tangent frame at `a`.
Eigen::Vector2d EastNorthOffset(const LatLon& a, const LatLon& b);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_GEO_LOCAL_FRAME_H_
