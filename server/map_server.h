#ifndef CROWDMAP_SERVER_MAP_SERVER_H_
#define CROWDMAP_SERVER_MAP_SERVER_H_

#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>

#include <grpcpp/server.h>

#include "absl/status/statusor.h"
#include "server/auth.h"
#include "server/http_viewer.h"
#include "server/map_service.h"
#include "server/map_worker.h"
#include "server/metrics.h"
#include "server/quotas.h"
#include "server/storage/map_store.h"
#include "server/upload_committer.h"
#include "server/version_notifier.h"

namespace crowdmap {

struct MapServerOptions {
  std::string listen = "127.0.0.1:50051";  // host:port; port 0 picks a free one
  std::string db_path = "./var/map.db";
  // true: a missing database (and its directory) or an empty file is created as a new map;
  // false: refused with FailedPrecondition naming the path (mapd's default, unless --create).
  bool create_db = true;
  MapWorkerOptions worker;
  // Links of the window a read's covariances come from (QueryRegion, GetTile and the other reads
  // with covariances); -1: worker.update.window_hops, as the updates use. 0 is the whole map
  // (exact); fewer links than the updates' make reads faster and their covariances wider (still
  // conservative).
  int read_window_hops = -1;
  int64_t max_queue = 10000;  // passages queued or processing before uploads get RESOURCE_EXHAUSTED
  int max_message_mb = 4;     // gRPC receive limit per message
  int max_passage_mb = 64;    // largest accepted passage (chunked uploads)
  bool start_worker = true;   // false: accept and queue uploads, apply nothing
  std::string metrics_listen;  // host:port of the Prometheus endpoint (/metrics); empty = none
  std::string http_listen;     // host:port of the map viewer (server/http_viewer.h); empty = none
  std::string viewer_basemap;  // the viewer's optional XYZ basemap URL template; empty = no tiles
  SecurityOptions security;   // TLS, authentication, roles (server/auth.h)
  LimitOptions limits;        // quotas, streams, bytes in flight, threads (server/quotas.h)

  absl::Status Validate() const;
};

// Process-wide settings for a long-running server, called once at the start of main():
// - glibc malloc keeps freed memory (up to 256 MiB) and serves blocks up to 32 MiB from its heaps
//   instead of returning them to the kernel after every solve; each return (munmap/madvise) flushes
//   the TLB of every core and stalls the request threads running there;
// - absl::Mutex deadlock detection (enabled in Debian's build) is switched off.
void TuneProcessForServing();

// The map service process: store, upload committer, worker and gRPC server (with health checking
// and reflection), started together and shut down in order.
class MapServer {
 public:
  static absl::StatusOr<std::unique_ptr<MapServer>> Start(const MapServerOptions& options);
  ~MapServer();
  MapServer(const MapServer&) = delete;
  MapServer& operator=(const MapServer&) = delete;

  int port() const { return port_; }
  // The Prometheus endpoint's port; 0 without metrics_listen.
  int metrics_port() const { return metrics_ == nullptr ? 0 : metrics_->port(); }
  ServerMetrics* metrics() { return metrics_.get(); }
  // The map viewer's HTTP port; 0 without http_listen.
  int http_port() const { return http_ == nullptr ? 0 : http_->port(); }
  // "host:port" a client on this machine can dial.
  std::string address() const;
  MapStoreInterface* store() { return store_.get(); }
  // Reads the auth file again (SIGHUP); FailedPrecondition when authentication is off. On an
  // error the identities loaded before stay in force.
  absl::Status ReloadAuth();
  bool auth_enabled() const { return auth_ != nullptr; }
  // Chunked uploads open now (admitted under the stream caps).
  int open_uploads() const { return streams_->open_uploads(); }
  // The cap on calls that read covariances (reads with them, localisations): tests hold places.
  ConcurrentCalls* covariance_reads() { return covariance_reads_.get(); }

  // Health NOT_SERVING, refuse uploads, finish the passage being applied, end streams, stop gRPC
  // (in-flight calls get `grace`; gRPC also waits that long for idle client connections to
  // close, so keep it short: uploads are refused by then and reads take milliseconds). Idempotent.
  void Shutdown(std::chrono::milliseconds grace = std::chrono::milliseconds(1000));

 private:
  MapServer() = default;

  // The database's exclusive lock (LockDatabase), released last: first of the members.
  struct DatabaseLock {
    int fd = -1;
    ~DatabaseLock();
  };
  DatabaseLock lock_;
  MapServerOptions options_;
  std::unique_ptr<MapStoreInterface> store_;
  std::unique_ptr<ServerMetrics> metrics_;  // reads store_; used by the worker and gRPC
  VersionNotifier notifier_;
  std::unique_ptr<UploadCommitter> committer_;
  std::unique_ptr<MapWorker> worker_;
  std::unique_ptr<Authenticator> auth_;
  std::unique_ptr<HttpViewer> http_;  // reads store_, checks tokens with auth_
  std::unique_ptr<VehicleQuotas> quotas_;
  std::unique_ptr<InflightBytes> inflight_;
  std::unique_ptr<StreamLimiter> streams_;
  std::unique_ptr<ConcurrentCalls> covariance_reads_;
  MapServiceContext context_;
  std::unique_ptr<MapService> service_;
  std::unique_ptr<grpc::Server> server_;
  int port_ = 0;
  std::mutex shutdown_mu_;
  bool shut_down_ = false;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAP_SERVER_H_
