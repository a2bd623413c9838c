#include "server/storage/factor_codec.h"

#include <cstring>

#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

template <typename T>
void Append(std::string* out, T value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}

template <typename T>
T Read(const std::string& in, size_t index) {
  T value;
  std::memcpy(&value, in.data() + index * sizeof(T), sizeof(T));
  return value;
}

}  // namespace

EncodedFactor EncodeFactor(const MapFactor& factor) {
  EncodedFactor out;
  const int n = 2 * static_cast<int>(factor.landmarks.size());
  for (LandmarkId id : factor.landmarks) Append<int64_t>(&out.landmark_ids, id);
  for (int r = 0; r < n; ++r) {
    for (int c = r; c < n; ++c) Append<double>(&out.information, factor.information(r, c));
    Append<double>(&out.information_vector, factor.information_vector(r));
  }
  return out;
}

absl::StatusOr<MapFactor> DecodeFactor(int64_t id, std::string vehicle_id, std::string passage_id,
                                       const EncodedFactor& encoded) {
  auto corrupt = [&](const char* what) {
    return absl::DataLossError(absl::StrCat("factor ", id, ": ", what));
  };
  if (encoded.landmark_ids.empty() || encoded.landmark_ids.size() % sizeof(int64_t) != 0) {
    return corrupt("landmark id list has a wrong size");
  }
  const size_t k = encoded.landmark_ids.size() / sizeof(int64_t);
  const size_t n = 2 * k;
  if (encoded.information.size() != n * (n + 1) / 2 * sizeof(double)) return corrupt("information has a wrong size");
  if (encoded.information_vector.size() != n * sizeof(double)) return corrupt("information vector has a wrong size");
  MapFactor f;
  f.id = id;
  f.vehicle_id = std::move(vehicle_id);
  f.passage_id = std::move(passage_id);
  for (size_t i = 0; i < k; ++i) f.landmarks.push_back(Read<int64_t>(encoded.landmark_ids, i));
  f.information.resize(n, n);
  f.information_vector.resize(n);
  size_t at = 0;
  for (size_t r = 0; r < n; ++r) {
    for (size_t c = r; c < n; ++c) f.information(r, c) = f.information(c, r) = Read<double>(encoded.information, at++);
    f.information_vector(r) = Read<double>(encoded.information_vector, r);
  }
  if (!f.information.allFinite() || !f.information_vector.allFinite()) return corrupt("non-finite numbers");
  return f;
}

absl::Status InsertFactorRow(SqliteConnection* db, const MapFactor& factor) {
  const EncodedFactor encoded = EncodeFactor(factor);
  auto stmt = db->Prepare(
      "INSERT INTO factors (id, vehicle_id, passage_id, landmark_ids, information, information_vector) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6)");
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, factor.id)
      .Bind(2, std::string_view(factor.vehicle_id))
      .Bind(3, std::string_view(factor.passage_id))
      .BindBlob(4, encoded.landmark_ids)
      .BindBlob(5, encoded.information)
      .BindBlob(6, encoded.information_vector);
  return stmt->Run();
}

}  // namespace crowdmap
