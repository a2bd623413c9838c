#ifndef CROWDMAP_SERVER_STORAGE_COVARIANCE_PAGE_H_
#define CROWDMAP_SERVER_STORAGE_COVARIANCE_PAGE_H_

#include "absl/status/status.h"
#include "core/map/map_state.h"
#include "server/storage/map_store.h"

namespace crowdmap {

// Recovers the joint covariance of the page's landmarks from the map's information (a MapWindow
// with `window_hops`) and puts it in the page: every cross block, and the diagonal blocks as the
// landmarks' covariances, so that what is returned is one consistent matrix.
absl::Status AppendCrossCovariances(const MapReaderInterface& map, int window_hops, LandmarkPage* page);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_COVARIANCE_PAGE_H_
