#ifndef CROWDMAP_SERVER_STORAGE_MAP_READS_H_
#define CROWDMAP_SERVER_STORAGE_MAP_READS_H_

#include "absl/status/status.h"
#include "core/map/map_state.h"
#include "core/map/map_window.h"
#include "server/storage/map_store.h"

namespace crowdmap {

// Recovers the joint covariance of the page's landmarks from the map's information (a MapWindow
// with `window_hops`) and puts it in the page (LandmarkPage::covariance, and its diagonal blocks as
// the landmarks' covariances, so that what is returned is one consistent matrix).
absl::Status AppendCrossCovariances(const MapReaderInterface& map, int window_hops, LandmarkPage* page);
// The same from a window that holds every landmark of the page (e.g. one over the whole map).
absl::Status AppendCrossCovariances(const MapWindow& window, LandmarkPage* page);
// The same from the whole covariance of such a window (MapWindow::Covariance of all its landmarks,
// 2 rows and columns per landmark in the window's order): a copy of its rows and columns.
absl::Status AppendCrossCovariances(const MapWindow& window, const Eigen::MatrixXd& window_covariance,
                                    LandmarkPage* page);

// Landmark `id` of `map` and the passages whose factors it is in. NotFound when it is not mapped.
absl::StatusOr<LandmarkProvenance> ProvenanceOf(const MapReaderInterface& map, LandmarkId id);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_MAP_READS_H_
