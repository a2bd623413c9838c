#ifndef CROWDMAP_SERVER_METRICS_H_
#define CROWDMAP_SERVER_METRICS_H_

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>

#include <grpcpp/support/server_interceptor.h>
#include <grpcpp/support/status.h>

#include "absl/status/statusor.h"
#include "server/map_worker.h"
#include "server/storage/map_store.h"

namespace prometheus {
class Collectable;
class Exposer;
class Registry;
class Counter;
class Gauge;
class Histogram;
template <typename T>
class Family;
}  // namespace prometheus

namespace crowdmap {

// mapd's Prometheus metrics (prometheus-cpp), served as text on http://<listen>/metrics:
// - mapd_rpc_duration_seconds{service,method,code}: every RPC (a gRPC server interceptor);
// - mapd_passage_{apply,solve,covariance,commit}_seconds: the worker's steps per applied passage;
// - mapd_upload_bytes_total, mapd_uploads_total{outcome}: accepted uploads (serialized passage bytes);
// - mapd_covariance_reads_total{bound}: reads with covariances (GetTile, QueryRegion) by how their
//   covariance relates to the exact one (exact, conservative, may_be_narrower);
// - mapd_queue_depth, mapd_passages{state}, mapd_map_landmarks, mapd_map_factors, mapd_map_version:
//   read from the store's row counts at each scrape;
// - mapd_relinearizations_due: re-linearisations the worker owes (WatchWorker), at each scrape;
// - mapd_build_info{version} 1.
// Thread-safe.
class StoreCollector;  // metrics.cc

class ServerMetrics {
 public:
  // Serves the metrics on `listen` (host:port; port 0 picks a free one). The store is read at
  // each scrape and must outlive the returned object.
  static absl::StatusOr<std::unique_ptr<ServerMetrics>> Start(const std::string& listen,
                                                              MapStoreInterface* store);
  ~ServerMetrics();
  ServerMetrics(const ServerMetrics&) = delete;
  ServerMetrics& operator=(const ServerMetrics&) = delete;

  // The port the HTTP endpoint listens on.
  int port() const { return port_; }

  // `full_method` as gRPC names it ("/mapservice.v1.MapService/GetTile"). Methods the server does
  // not serve are counted as method="unknown" (a client cannot add label values).
  void ObserveRpc(std::string_view full_method, grpc::StatusCode code, double seconds);
  void ObserveUpload(size_t bytes, bool duplicate);
  void ObserveApplied(const AppliedPassageTimings& timings);
  void ObserveRelinearized(bool committed);
  void ObserveCovarianceRead(CovarianceBound bound);
  // The worker whose owed re-linearisations each scrape reports (mapd_relinearizations_due); null:
  // none from then on. Once this returns, no scrape reads the previous one.
  void WatchWorker(const MapWorker* worker);

  // Creates the interceptor that times every RPC; to be handed to the gRPC server builder.
  std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> InterceptorFactory();

 private:
  ServerMetrics() = default;

  std::shared_ptr<prometheus::Registry> registry_;
  std::shared_ptr<StoreCollector> store_collector_;
  std::unique_ptr<prometheus::Exposer> exposer_;
  int port_ = 0;
  prometheus::Family<prometheus::Histogram>* rpc_duration_ = nullptr;
  prometheus::Histogram* apply_ = nullptr;
  prometheus::Histogram* solve_ = nullptr;
  prometheus::Histogram* covariance_ = nullptr;
  prometheus::Histogram* commit_ = nullptr;
  prometheus::Counter* recomputed_ = nullptr;
  prometheus::Counter* inflated_[1 + kPassageSensors] = {};  // by test: the whole subgraph's, then each sensor's
  prometheus::Counter* relinearized_ = nullptr;
  prometheus::Counter* relinearizations_refused_ = nullptr;
  prometheus::Counter* upload_bytes_ = nullptr;
  prometheus::Counter* uploads_new_ = nullptr;
  prometheus::Counter* uploads_duplicate_ = nullptr;
  prometheus::Counter* covariance_reads_[3] = {};  // by CovarianceBound
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_METRICS_H_
