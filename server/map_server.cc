#include "server/map_server.h"

#include <fcntl.h>
#include <malloc.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/impl/server_builder_option.h>
#include <grpcpp/resource_quota.h>
#include <grpcpp/security/server_credentials.h>
#include <grpc/impl/codegen/grpc_types.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "core/map/sparse_threads.h"
#include "server/storage/cached_map_store.h"

namespace crowdmap {

absl::Status MapServerOptions::Validate() const {
  if (listen.empty()) return absl::InvalidArgumentError("listen: must not be empty");
  if (db_path.empty()) return absl::InvalidArgumentError("db: must not be empty");
  if (!http_listen.empty()) {
    HttpViewerOptions viewer{http_listen, viewer_basemap};
    if (absl::Status s = viewer.Validate(); !s.ok()) return s;
  } else if (!viewer_basemap.empty()) {
    return absl::InvalidArgumentError("viewer-basemap: needs http-listen (the viewer is off)");
  }
  if (!metrics_listen.empty() && metrics_listen.rfind(':') == std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat("metrics-listen: expected host:port, got '", metrics_listen, "'"));
  }
  if (read_window_hops < -1) {
    return absl::InvalidArgumentError(absl::StrCat("read_window_hops: must be >= -1, got ", read_window_hops));
  }
  if (max_queue < 0) return absl::InvalidArgumentError(absl::StrCat("max_queue: must be >= 0, got ", max_queue));
  if (max_message_mb < 1 || max_message_mb > 2047) {
    return absl::InvalidArgumentError(absl::StrCat("max_message_mb: must lie in [1, 2047], got ", max_message_mb));
  }
  // At most 512: a stored upload must stay under SQLite's length limit (1,000,000,000 bytes).
  if (max_passage_mb < 1 || max_passage_mb > 512) {
    return absl::InvalidArgumentError(absl::StrCat("max_passage_mb: must lie in [1, 512], got ", max_passage_mb));
  }
  if (absl::Status s = security.Validate(); !s.ok()) return s;
  if (absl::Status s = limits.Validate(max_passage_mb); !s.ok()) return s;
  return worker.Validate();
}

namespace {

// The writer's yields come about every 0.1 ms of a commit (some 65 cross-covariance rows; a
// passage's commit at 100 landmarks writes 4950 of them in about 8 ms).
constexpr int kWriteYieldVmSteps = 4000;

// Takes server reflection out of a builder: linking the reflection library registers it for every
// server of the process.
class WithoutReflection : public grpc::ServerBuilderOption {
 public:
  void UpdateArguments(grpc::ChannelArguments*) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override {
    plugins->erase(std::remove_if(plugins->begin(), plugins->end(),
                                  [](const auto& p) { return p->name().find("reflection") != std::string::npos; }),
                   plugins->end());
  }
};

}  // namespace

// An exclusive lock on `<db>.lock`, held as long as the returned descriptor is open: a second mapd
// on the same database would apply passages beside the first.
absl::StatusOr<int> LockDatabase(const std::string& db_path) {
  const std::string path = db_path + ".lock";
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) return absl::FailedPreconditionError(absl::StrCat("db: cannot open the lock file ", path));
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    ::close(fd);
    return absl::FailedPreconditionError(
        absl::StrCat("db: ", db_path, " is in use by another mapd (", path, " is locked); stop it first"));
  }
  return fd;
}

// Refuses, unless `create`, a database that does not exist yet or is an empty file: a mistyped
// --db would otherwise start an empty map silently.
absl::Status CheckDatabasePath(const std::string& db_path, bool create) {
  const std::filesystem::path path(db_path);
  const std::filesystem::path dir = path.parent_path();
  std::error_code ec;
  if (!dir.empty() && !std::filesystem::is_directory(dir, ec)) {
    if (!create) {
      return absl::FailedPreconditionError(absl::StrCat("db: the directory ", dir.string(), " of ", db_path,
                                                        " does not exist; check --db, or pass --create to create a new map there"));
    }
    std::filesystem::create_directories(dir, ec);
    if (ec) return absl::FailedPreconditionError(absl::StrCat("db: cannot create ", dir.string(), ": ", ec.message()));
  }
  if (create) return absl::OkStatus();
  if (!std::filesystem::exists(path, ec)) {
    return absl::FailedPreconditionError(absl::StrCat(
        "db: ", db_path, " does not exist; check --db, or pass --create to create a new, empty map there"));
  }
  if (std::filesystem::is_regular_file(path, ec) && std::filesystem::file_size(path, ec) == 0 && !ec) {
    return absl::FailedPreconditionError(absl::StrCat(
        "db: ", db_path, " is an empty file (0 bytes), not a map; check --db, or pass --create to create a new map in it"));
  }
  return absl::OkStatus();
}

void TuneProcessForServing() {
  mallopt(M_TRIM_THRESHOLD, 256 << 20);
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  absl::SetMutexDeadlockDetectionMode(absl::OnDeadlockCycle::kIgnore);
}

absl::StatusOr<std::unique_ptr<MapServer>> MapServer::Start(const MapServerOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (absl::Status s = CheckBlasIsSafeForConcurrentCalls(); !s.ok()) return s;
  std::unique_ptr<MapServer> server(new MapServer());
  server->options_ = options;

  if (absl::Status s = CheckDatabasePath(options.db_path, options.create_db); !s.ok()) return s;
  absl::StatusOr<int> lock = LockDatabase(options.db_path);
  if (!lock.ok()) return lock.status();
  server->lock_.fd = *lock;
  SqliteMapStoreOptions store_options;
  if (options.worker.yield) store_options.write_yield_vm_steps = kWriteYieldVmSteps;
  const int read_window_hops =
      options.read_window_hops >= 0 ? options.read_window_hops : options.worker.update.window_hops;
  store_options.covariance_window_hops = read_window_hops;
  auto sqlite = CreateSqliteMapStore(options.db_path, store_options);
  if (!sqlite.ok()) return sqlite.status();
  // Map reads are served from memory; SQLite stays the source of truth.
  auto store = CachedMapStore::Create(std::move(*sqlite), read_window_hops);
  if (!store.ok()) return store.status();
  // Watchers learn of a version once map reads show it.
  (*store)->SetPublishedCallback([n = &server->notifier_](int64_t version) { n->Publish(version); });
  server->store_ = std::move(*store);
  MapWorkerOptions worker_options = options.worker;
  if (!options.metrics_listen.empty()) {
    auto metrics = ServerMetrics::Start(options.metrics_listen, server->store_.get());
    if (!metrics.ok()) return metrics.status();
    server->metrics_ = std::move(*metrics);
    worker_options.on_applied = [m = server->metrics_.get()](const AppliedPassageTimings& t) { m->ObserveApplied(t); };
    worker_options.on_relinearized = [m = server->metrics_.get()](bool committed) { m->ObserveRelinearized(committed); };
  }
  server->committer_ = std::make_unique<UploadCommitter>(server->store_.get(), options.max_queue);
  server->store_->ReadCommittedMap([&](const MapState& map) { server->notifier_.Publish(map.version()); });
  auto worker = MapWorker::Create(server->store_.get(), worker_options);
  if (!worker.ok()) return worker.status();
  server->worker_ = std::move(*worker);
  if (server->metrics_ != nullptr) server->metrics_->WatchWorker(server->worker_.get());

  // The viewer serves the map and the vehicles' routes: listening beyond loopback, it needs the
  // identities as the gRPC port does.
  const bool grpc_open = AuthEnabled(options.security, options.listen);
  const bool http_open = !options.http_listen.empty() && AuthEnabled(options.security, options.http_listen);
  const bool auth_on = grpc_open || http_open;
  if (auth_on) {
    if (options.security.auth_file.empty() && options.security.tls_client_ca.empty()) {
      const std::string open_on = grpc_open ? options.listen : options.http_listen;
      return absl::FailedPreconditionError(absl::StrCat(
          "--auth: on (", options.security.auth == "auto" ? "mapd listens on " + open_on + ", not loopback" : "asked for",
          ") but no client could authenticate: give --auth-file (tokens, certificate names) and/or --tls-client-ca, "
          "or --auth off to serve without authentication"));
    }
    auto auth = Authenticator::Create(options.security.auth_file);
    if (!auth.ok()) return auth.status();
    server->auth_ = std::move(*auth);
  }
  if (!options.http_listen.empty()) {
    auto http = HttpViewer::Start(HttpViewerOptions{options.http_listen, options.viewer_basemap}, server->store_.get(),
                                  server->auth_.get(), options.worker.update, server->worker_.get());
    if (!http.ok()) return http.status();
    server->http_ = std::move(*http);
    if (auth_on && !IsLoopbackListen(options.http_listen)) {
      spdlog::warn("event=plaintext_tokens http_listen={} (the map viewer is plain HTTP: its bearer tokens cross the "
                   "network in clear; keep it on loopback behind a TLS proxy)", options.http_listen);
    }
  }
  auto credentials = MakeServerCredentials(options.security);
  if (!credentials.ok()) return credentials.status();
  server->quotas_ = std::make_unique<VehicleQuotas>(options.limits);
  server->inflight_ = std::make_unique<InflightBytes>(static_cast<int64_t>(options.limits.max_inflight_mb) << 20);
  server->streams_ = std::make_unique<StreamLimiter>(options.limits);
  server->covariance_reads_ = std::make_unique<ConcurrentCalls>(
      options.limits.max_covariance_reads, "reads with covariances", "--max-covariance-reads");

  MapServiceContext& context = server->context_;
  context.auth = server->auth_.get();
  context.quotas = server->quotas_.get();
  context.inflight = server->inflight_.get();
  context.streams = server->streams_.get();
  context.covariance_reads = server->covariance_reads_.get();
  context.store = server->store_.get();
  context.committer = server->committer_.get();
  context.worker = server->worker_.get();
  context.notifier = &server->notifier_;
  context.metrics = server->metrics_.get();
  context.limits.max_passage_bytes = static_cast<size_t>(options.max_passage_mb) << 20;
  context.update = options.worker.update;
  server->service_ = std::make_unique<MapService>(&context);

  grpc::EnableDefaultHealthCheckService(true);
  const bool reflection = ReflectionEnabled(options.security, options.listen);
  if (reflection) grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  if (!reflection) builder.SetOption(std::make_unique<WithoutReflection>());
  builder.AddListeningPort(options.listen, *credentials, &server->port_);
  // Each synchronous call holds one of these threads; beyond them gRPC answers RESOURCE_EXHAUSTED.
  grpc::ResourceQuota quota("mapd");
  quota.SetMaxThreads(options.limits.max_threads);
  builder.SetResourceQuota(quota);
  // A second server on the same port must fail, not share it (clients would see two maps).
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.SetMaxReceiveMessageSize(options.max_message_mb << 20);
  builder.RegisterService(server->service_.get());
  if (server->metrics_ != nullptr) {
    std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
    interceptors.push_back(server->metrics_->InterceptorFactory());
    builder.experimental().SetInterceptorCreators(std::move(interceptors));
  }
  server->server_ = builder.BuildAndStart();
  if (server->server_ == nullptr || server->port_ == 0) {
    return absl::UnavailableError(absl::StrCat("listen: cannot bind ", options.listen, " (in use by another process?)"));
  }
  server->server_->GetHealthCheckService()->SetServingStatus(true);
  if (options.start_worker) server->worker_->Start();
  spdlog::info("event=started version={} listen={} port={} db={} strategy={} workers={} max_queue={}",
               CROWDMAP_VERSION, options.listen, server->port_, options.db_path, UpdateStrategyName(context.update.strategy), options.worker.workers, options.max_queue);
  spdlog::info("event=security tls={} mtls={} auth={} identities={} reflection={} max_threads={} max_upload_streams={} "
               "max_upload_streams_per_identity={} max_watch_streams={} max_watch_streams_per_identity={} "
               "upload_idle_timeout_s={} max_inflight_mb={} vehicle_uploads_per_s={} vehicle_upload_mb_per_s={} "
               "max_covariance_reads={}",
               options.security.tls(), !options.security.tls_client_ca.empty(), auth_on,
               auth_on ? server->auth_->identities() : 0, reflection, options.limits.max_threads,
               options.limits.max_upload_streams, options.limits.max_upload_streams_per_identity,
               options.limits.max_watch_streams, options.limits.max_watch_streams_per_identity,
               options.limits.upload_idle_timeout_s, options.limits.max_inflight_mb,
               options.limits.vehicle_uploads_per_s, options.limits.vehicle_upload_mb_per_s,
               options.limits.max_covariance_reads);
  if (auth_on && !options.security.tls() && !IsLoopbackListen(options.listen)) {
    spdlog::warn("event=plaintext_tokens listen={} (bearer tokens cross the network in clear: give --tls-cert and --tls-key)",
                 options.listen);
  }
  return server;
}

absl::Status MapServer::ReloadAuth() {
  if (auth_ == nullptr) return absl::FailedPreconditionError("auth: off, nothing to reload");
  absl::Status s = auth_->Reload();
  if (s.ok()) {
    spdlog::info("event=auth_reloaded identities={}", auth_->identities());
  } else {
    spdlog::error("event=auth_reload_failed error=\"{}\" (the identities loaded before stay in force)", EscapeForLog(std::string(s.message())));
  }
  return s;
}

MapServer::DatabaseLock::~DatabaseLock() {
  if (fd >= 0) ::close(fd);
}

MapServer::~MapServer() { Shutdown(std::chrono::milliseconds(0)); }

std::string MapServer::address() const {
  const std::string& listen = options_.listen;
  const size_t colon = listen.rfind(':');
  std::string host = colon == std::string::npos ? listen : listen.substr(0, colon);
  if (host.empty() || host == "0.0.0.0" || host == "[::]") host = "127.0.0.1";
  return absl::StrCat(host, ":", port_);
}

void MapServer::Shutdown(std::chrono::milliseconds grace) {
  std::lock_guard<std::mutex> lock(shutdown_mu_);
  if (shut_down_) return;
  shut_down_ = true;
  spdlog::info("event=shutting_down");
  if (server_ != nullptr) server_->GetHealthCheckService()->SetServingStatus(false);
  http_.reset();
  context_.accepting_uploads = false;
  if (worker_ != nullptr) worker_->Stop();
  if (metrics_ != nullptr) metrics_->WatchWorker(nullptr);  // the worker is destroyed before the metrics
  notifier_.Close();
  if (server_ != nullptr) {
    server_->Shutdown(std::chrono::system_clock::now() + grace);
    server_->Wait();
  }
  spdlog::info("event=stopped");
}

}  // namespace crowdmap
