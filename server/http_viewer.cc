#include "server/http_viewer.h"

#include <algorithm>
#include <chrono>
#include <vector>

#include <civetweb.h>
#include <google/protobuf/util/json_util.h>
#include <spdlog/spdlog.h>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "server/geojson.h"
#include "server/http_thread_stacks.h"
#include "server/log_format.h"
#include "server/map_service.h"
#include "server/request_log.h"
#include "server/web_assets.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

constexpr int kRegionPage = 10000;
constexpr int kMaxPassages = 200;

HttpResponse Json(int code, std::string body) {
  HttpResponse r;
  r.code = code;
  r.body = std::move(body);
  return r;
}

HttpResponse Error(int code, const std::string& message) {
  return Json(code, JsonText({{"error", message}}) + "\n");
}

HttpResponse FromStatus(const absl::Status& status) {
  const std::string message(status.message());
  switch (status.code()) {
    case absl::StatusCode::kInvalidArgument: return Error(400, message);
    case absl::StatusCode::kUnauthenticated: {
      HttpResponse r = Error(401, message);
      r.headers["WWW-Authenticate"] = "Bearer realm=\"mapd\"";
      return r;
    }
    case absl::StatusCode::kPermissionDenied: return Error(403, message);
    case absl::StatusCode::kNotFound: return Error(404, message);
    case absl::StatusCode::kUnavailable: return Error(503, message);
    default: return Error(500, message);
  }
}

std::string ToJson(const google::protobuf::Message& message) {
  google::protobuf::util::JsonPrintOptions options;
  options.always_print_primitive_fields = true;
  options.preserve_proto_field_names = true;
  std::string text;
  (void)google::protobuf::util::MessageToJsonString(message, &text, options);
  return text + "\n";
}

// The value of `name` in a query string, URL-decoded; nullopt when absent.
std::optional<std::string> QueryValue(const std::string& query, const char* name) {
  std::vector<char> buffer(query.size() + 1);
  const int n = mg_get_var(query.data(), query.size(), name, buffer.data(), buffer.size());
  if (n < 0) return std::nullopt;
  return std::string(buffer.data(), static_cast<size_t>(n));
}

// "W,S,E,N" (degrees, as mapctl's --bbox), validated as the gRPC reads validate their box.
absl::StatusOr<BoundingBox> ParseBbox(const std::optional<std::string>& text) {
  if (!text.has_value()) return BoundingBox{-85.0, -180.0, 85.0, 180.0};
  const std::vector<std::string> parts = absl::StrSplit(*text, ',');
  double v[4];
  if (parts.size() != 4 || !absl::SimpleAtod(parts[0], &v[0]) || !absl::SimpleAtod(parts[1], &v[1]) ||
      !absl::SimpleAtod(parts[2], &v[2]) || !absl::SimpleAtod(parts[3], &v[3])) {
    return absl::InvalidArgumentError("bbox: expected W,S,E,N in degrees (min lon, min lat, max lon, max lat)");
  }
  pb::BoundingBox wire;
  wire.set_min_lon_deg(v[0]);
  wire.set_min_lat_deg(v[1]);
  wire.set_max_lon_deg(v[2]);
  wire.set_max_lat_deg(v[3]);
  return BoundingBoxFromProto(wire, "bbox");
}

// The page's Content-Security-Policy: scripts, styles and data from mapd only; images also from
// the basemap's origin when one is set ("{s}" subdomains as a wildcard).
std::string ContentSecurityPolicy(const std::string& basemap_url) {
  std::string images = "'self' data:";
  if (const size_t scheme = basemap_url.find("://"); scheme != std::string::npos) {
    const size_t path = basemap_url.find('/', scheme + 3);
    std::string origin = basemap_url.substr(0, path);
    if (const size_t s = origin.find("{s}"); s != std::string::npos) origin.replace(s, 3, "*");
    absl::StrAppend(&images, " ", origin);
  }
  return absl::StrCat("default-src 'self'; img-src ", images,
                      "; style-src 'self' 'unsafe-inline'; connect-src 'self'; frame-ancestors 'none'");
}

const char* ReasonPhrase(int code) {
  switch (code) {
    case 200: return "OK";
    case 400: return "Bad Request";
    case 401: return "Unauthorized";
    case 403: return "Forbidden";
    case 404: return "Not Found";
    case 405: return "Method Not Allowed";
    case 503: return "Service Unavailable";
    default: return "Internal Server Error";
  }
}

}  // namespace

absl::Status HttpViewerOptions::Validate() const {
  if (listen.empty() || listen.rfind(':') == std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat("http-listen: expected host:port, got '", listen, "'"));
  }
  if (!basemap_url.empty()) {
    const bool http = basemap_url.rfind("http://", 0) == 0 || basemap_url.rfind("https://", 0) == 0;
    if (!http || basemap_url.find("{z}") == std::string::npos || basemap_url.find("{x}") == std::string::npos ||
        basemap_url.find("{y}") == std::string::npos) {
      return absl::InvalidArgumentError(absl::StrCat(
          "viewer-basemap: expected an http(s) URL template with {z}, {x} and {y}, got '", basemap_url, "'"));
    }
  }
  if (max_landmarks < 1) return absl::InvalidArgumentError("max_landmarks: must be >= 1");
  if (threads < 1) return absl::InvalidArgumentError("threads: must be >= 1");
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<HttpViewer>> HttpViewer::Start(const HttpViewerOptions& options,
                                                              MapStoreInterface* store, const Authenticator* auth,
                                                              const MapUpdateOptions& update, const MapWorker* worker) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  std::unique_ptr<HttpViewer> viewer(new HttpViewer());
  viewer->options_ = options;
  viewer->store_ = store;
  viewer->auth_ = auth;
  viewer->update_ = update;
  viewer->worker_ = worker;

  mg_init_library(0);
  // civetweb wants "host:port" as "ip:port" (no brackets for IPv4; "[::1]:port" for IPv6).
  std::string ports = options.listen;
  if (ports.rfind("localhost:", 0) == 0) ports = "127.0.0.1" + ports.substr(9);
  const std::string threads = std::to_string(options.threads);
  const char* mg_options[] = {"listening_ports", ports.c_str(), "num_threads", threads.c_str(),
                              "enable_directory_listing", "no", nullptr};
  mg_callbacks callbacks{};
  callbacks.log_message = [](const mg_connection*, const char* message) {
    spdlog::warn("event=http_error error=\"{}\"", EscapeForLog(message));
    return 1;
  };
  viewer->server_ = mg_start(&callbacks, nullptr, mg_options);
  if (viewer->server_ == nullptr) {
    return absl::UnavailableError(absl::StrCat("http-listen: cannot bind ", options.listen, " (in use by another process?)"));
  }
  mg_set_request_handler(viewer->server_, "/", &HttpViewer::OnRequest, viewer.get());
  mg_server_port ports_info[4];
  const int n = mg_get_server_ports(viewer->server_, 4, ports_info);
  if (n < 1) return absl::UnavailableError(absl::StrCat("http-listen: no port bound for ", options.listen));
  viewer->port_ = ports_info[0].port;
  spdlog::info("event=http_viewer listen={} port={} auth={} basemap={} thread_stack_bytes={}", EscapeForLog(options.listen),
               viewer->port_, auth != nullptr, options.basemap_url.empty() ? "none" : EscapeForLog(options.basemap_url),
               HttpThreadStackBytes());
  return viewer;
}

HttpViewer::~HttpViewer() {
  if (server_ != nullptr) mg_stop(server_);
}

int HttpViewer::OnRequest(mg_connection* conn, void* self) {
  const auto start = std::chrono::steady_clock::now();
  const mg_request_info* info = mg_get_request_info(conn);
  const std::string method = info->request_method == nullptr ? "" : info->request_method;
  const std::string path = info->local_uri == nullptr ? "/" : info->local_uri;
  const std::string query = info->query_string == nullptr ? "" : info->query_string;
  const char* authorization = mg_get_header(conn, "Authorization");
  HttpResponse response;
  if (method != "GET" && method != "HEAD") {
    response = Error(405, "only GET is served");
    response.headers["Allow"] = "GET, HEAD";
  } else {
    response = static_cast<const HttpViewer*>(self)->Handle(path, query, authorization == nullptr ? "" : authorization);
  }
  std::string head = absl::StrCat("HTTP/1.1 ", response.code, " ", ReasonPhrase(response.code),
                                   "\r\nContent-Type: ", response.content_type,
                                   "\r\nContent-Length: ", response.body.size(),
                                   "\r\nCache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\n");
  for (const auto& [name, value] : response.headers) absl::StrAppend(&head, name, ": ", value, "\r\n");
  head += "\r\n";
  mg_write(conn, head.data(), head.size());
  if (method != "HEAD") mg_write(conn, response.body.data(), response.body.size());
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  const auto level = response.code < 400 ? spdlog::level::debug : spdlog::level::warn;
  spdlog::log(level, "http={} path={} code={} bytes={} ms={:.2f}", EscapeForLog(method), EscapeForLog(path),
              response.code, response.body.size(), ms);
  return response.code;
}

HttpResponse HttpViewer::Handle(const std::string& path, const std::string& query,
                                const std::string& authorization) const {
  if (path.rfind("/api/", 0) != 0) {
    const std::string file = path == "/" ? "/index.html" : path;
    for (const WebAsset& asset : WebAssets()) {
      if (asset.url_path != file) continue;
      HttpResponse r;
      r.content_type = std::string(asset.content_type);
      r.body = std::string(asset.body);
      r.headers["Content-Security-Policy"] = ContentSecurityPolicy(options_.basemap_url);
      return r;
    }
    return Error(404, absl::StrCat("no such page: ", path));
  }
  if (path == "/api/config") {
    return Json(200, JsonText({{"auth", auth_ != nullptr},
                               {"basemap_url", options_.basemap_url},
                               {"server_version", CROWDMAP_VERSION}}) +
                         "\n");
  }
  Principal who{"anonymous", Role::kAdmin, "none"};
  if (auth_ != nullptr) {
    if (authorization.empty()) {
      return FromStatus(absl::UnauthenticatedError("authentication is on: send 'Authorization: Bearer TOKEN'"));
    }
    absl::StatusOr<Principal> found = auth_->AuthenticateBearer(authorization);
    if (!found.ok()) return FromStatus(found.status());
    who = *found;
  }
  return Api(path, query, who);
}

HttpResponse HttpViewer::Api(const std::string& path, const std::string& query, const Principal& who) const {
  if (path == "/api/info") return Info();
  if (path == "/api/landmarks") return Landmarks(query);
  if (path == "/api/passages") return Passages(query, who);
  return Error(404, absl::StrCat("no such endpoint: ", path));
}

HttpResponse HttpViewer::Info() const {
  pb::MapInfo info;
  if (absl::Status s = ReadMapInfo(*store_, update_, worker_, &info); !s.ok()) return FromStatus(s);
  return Json(200, ToJson(info));
}

HttpResponse HttpViewer::Landmarks(const std::string& query) const {
  absl::StatusOr<BoundingBox> box = ParseBbox(QueryValue(query, "bbox"));
  if (!box.ok()) return FromStatus(box.status());
  std::vector<pb::Landmark> landmarks;
  int64_t version = 0;
  bool truncated = false;
  std::optional<std::vector<int64_t>> removed;  // a change list's removed landmarks
  if (std::optional<std::string> since = QueryValue(query, "since_version"); since.has_value()) {
    int64_t since_version = 0;
    if (!absl::SimpleAtoi(*since, &since_version) || since_version < 0) {
      return Error(400, "since_version: expected an integer >= 0");
    }
    absl::StatusOr<LandmarkPage> page = store_->ChangedLandmarks(*box, since_version);
    if (!page.ok()) return FromStatus(page.status());
    version = page->map_version;
    for (const Landmark& l : page->landmarks) LandmarkToProto(l, &landmarks.emplace_back());
    removed.emplace(page->removed.begin(), page->removed.end());
  } else {
    // Pages may come from successive map versions: the answer reports the oldest, so that a
    // client polling with since_version=<it> misses no change.
    LandmarkId after = 0;
    version = -1;
    for (;;) {
      absl::StatusOr<LandmarkPage> page = store_->QueryRegion(*box, after, kRegionPage, /*include_cross=*/false);
      if (!page.ok()) return FromStatus(page.status());
      version = version < 0 ? page->map_version : std::min(version, page->map_version);
      for (const Landmark& l : page->landmarks) LandmarkToProto(l, &landmarks.emplace_back());
      if (!page->more || page->landmarks.empty()) break;
      if (static_cast<int>(landmarks.size()) >= options_.max_landmarks) {
        truncated = true;
        break;
      }
      after = page->landmarks.back().id;
    }
  }
  if (static_cast<int>(landmarks.size()) > options_.max_landmarks) {
    landmarks.resize(options_.max_landmarks);
    truncated = true;
  }
  HttpResponse r =
      Json(200, LandmarksToGeoJson(landmarks, version, GeoJsonOptions{}, removed ? &*removed : nullptr));
  r.content_type = "application/geo+json";
  r.headers["X-Map-Version"] = std::to_string(version);
  if (truncated) r.headers["X-Truncated"] = std::to_string(options_.max_landmarks);
  return r;
}

HttpResponse HttpViewer::Passages(const std::string& query, const Principal& who) const {
  // Which vehicles drove where is passage data: operators and admins only, as for ListPassages.
  if (!who.MayReadAllPassages()) {
    return Error(403, absl::StrCat("role ", RoleName(who.role), ": the list of passages needs role operator"));
  }
  PassageQuery passages;
  passages.limit = kMaxPassages;
  const std::string state = QueryValue(query, "state").value_or("quarantined");
  bool known = false;
  for (int s = 1; s < kPassageStateCount; ++s) {
    if (state == PassageStateName(static_cast<PassageState>(s))) {
      passages.state = static_cast<PassageState>(s);
      known = true;
    }
  }
  if (!known) return Error(400, absl::StrCat("state: unknown passage state '", state, "'"));
  absl::StatusOr<std::vector<StoredPassage>> records = store_->ListPassages(passages);
  if (!records.ok()) return FromStatus(records.status());
  pb::ListPassagesResponse response;
  for (const StoredPassage& record : *records) StoredPassageToProto(record, response.add_passages());
  return Json(200, ToJson(response));
}

}  // namespace crowdmap
