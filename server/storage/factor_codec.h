#ifndef CROWDMAP_SERVER_STORAGE_FACTOR_CODEC_H_
#define CROWDMAP_SERVER_STORAGE_FACTOR_CODEC_H_

#include <string>

#include "absl/status/statusor.h"
#include "core/map/map_state.h"
#include "server/storage/sqlite_db.h"

namespace crowdmap {

// A factor's numbers as stored: landmark ids as int64, the information's upper triangle row by row
// and the information vector as doubles, all in the machine's byte order (little-endian on every
// supported platform).
struct EncodedFactor {
  std::string landmark_ids;
  std::string information;
  std::string information_vector;
};

EncodedFactor EncodeFactor(const MapFactor& factor);
// DataLoss when the sizes do not agree or a number is not finite.
absl::StatusOr<MapFactor> DecodeFactor(int64_t id, std::string vehicle_id, std::string passage_id,
                                       const EncodedFactor& encoded);

// Inserts the factor's row into the factors table (in the caller's write transaction).
absl::Status InsertFactorRow(SqliteConnection* db, const MapFactor& factor);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_FACTOR_CODEC_H_
