#ifndef CROWDMAP_SERVER_HTTP_VIEWER_H_
#define CROWDMAP_SERVER_HTTP_VIEWER_H_

#include <map>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/estimation/map_update_options.h"
#include "server/auth.h"
#include "server/map_worker.h"
#include "server/storage/map_store.h"

struct mg_context;
struct mg_connection;

namespace crowdmap {

struct HttpViewerOptions {
  std::string listen;       // host:port of the viewer (http://listen/); port 0 picks a free one
  // Optional XYZ basemap URL template ("https://tiles.example/{z}/{x}/{y}.png"); empty: no tiles,
  // the viewer needs no network beyond mapd.
  std::string basemap_url;
  int max_landmarks = 200000;  // largest /api/landmarks answer; beyond it the answer is cut
  int threads = 4;             // HTTP worker threads

  absl::Status Validate() const;
};

// The HTTP answer to one request, independent of the server library (tested without sockets).
struct HttpResponse {
  int code = 200;
  std::string content_type = "application/json";
  std::string body;
  std::map<std::string, std::string> headers;
};

// mapd's map viewer over HTTP (civetweb): a page (server/web/, Leaflet compiled in) and its JSON
// read endpoints, answered from the same store and wire conversions as the gRPC reads:
//   GET /api/config                  {"auth": bool, "basemap_url": "...", "server_version": "..."}
//   GET /api/info                    GetMapInfo's MapInfo as JSON (protobuf's JSON mapping)
//   GET /api/landmarks?bbox=W,S,E,N[&since_version=V]
//                                    GeoJSON of the landmarks in the box (all, or those changed
//                                    after V): the writer of `mapctl export --format geojson`
//   GET /api/passages?state=quarantined  ListPassages' answer as JSON, up to 200 passages
// With authentication on, every /api/ path but /api/config needs "Authorization: Bearer TOKEN"
// with a token of the auth file (401 without, 403 for a vehicle asking for passages); the page
// and its scripts carry no map data and are served to anyone.
class HttpViewer {
 public:
  // `store`, `auth` (null: authentication off) and `worker` (null: none; /api/info reports what it
  // owes) must outlive the viewer.
  static absl::StatusOr<std::unique_ptr<HttpViewer>> Start(const HttpViewerOptions& options, MapStoreInterface* store,
                                                           const Authenticator* auth, const MapUpdateOptions& update,
                                                           const MapWorker* worker);
  ~HttpViewer();  // stops serving; waits for requests in progress
  HttpViewer(const HttpViewer&) = delete;
  HttpViewer& operator=(const HttpViewer&) = delete;

  int port() const { return port_; }

  // Answers GET `path` with `query` (without '?') and the request's Authorization header.
  HttpResponse Handle(const std::string& path, const std::string& query, const std::string& authorization) const;

 private:
  HttpViewer() = default;
  static int OnRequest(mg_connection* conn, void* self);

  HttpResponse Api(const std::string& path, const std::string& query, const Principal& who) const;
  HttpResponse Landmarks(const std::string& query) const;
  HttpResponse Passages(const std::string& query, const Principal& who) const;
  HttpResponse Info() const;

  HttpViewerOptions options_;
  MapStoreInterface* store_ = nullptr;
  const Authenticator* auth_ = nullptr;
  MapUpdateOptions update_;
  const MapWorker* worker_ = nullptr;
  mg_context* server_ = nullptr;
  int port_ = 0;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_HTTP_VIEWER_H_
