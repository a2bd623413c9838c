#include "server/map_server.h"

#include <fcntl.h>
#include <malloc.h>
#include <sys/file.h>
#include <unistd.h>

#include <filesystem>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpc/impl/codegen/grpc_types.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "server/storage/cached_map_store.h"

namespace crowdmap {

absl::Status MapServerOptions::Validate() const {
  if (listen.empty()) return absl::InvalidArgumentError("listen: must not be empty");
  if (db_path.empty()) return absl::InvalidArgumentError("db: must not be empty");
  if (!metrics_listen.empty() && metrics_listen.rfind(':') == std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat("metrics-listen: expected host:port, got '", metrics_listen, "'"));
  }
  if (max_queue < 0) return absl::InvalidArgumentError(absl::StrCat("max_queue: must be >= 0, got ", max_queue));
  if (max_message_mb < 1 || max_message_mb > 2047) {
    return absl::InvalidArgumentError(absl::StrCat("max_message_mb: must lie in [1, 2047], got ", max_message_mb));
  }
  if (max_passage_mb < 1 || max_passage_mb > 2047) {
    return absl::InvalidArgumentError(absl::StrCat("max_passage_mb: must lie in [1, 2047], got ", max_passage_mb));
  }
  return worker.Validate();
}

namespace {

// The writer's yields come about every 0.1 ms of a commit (some 65 cross-covariance rows; a
// passage's commit at 100 landmarks writes 4950 of them in about 8 ms).
constexpr int kWriteYieldVmSteps = 4000;

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
  std::unique_ptr<MapServer> server(new MapServer());
  server->options_ = options;

  if (absl::Status s = CheckDatabasePath(options.db_path, options.create_db); !s.ok()) return s;
  absl::StatusOr<int> lock = LockDatabase(options.db_path);
  if (!lock.ok()) return lock.status();
  server->lock_.fd = *lock;
  SqliteMapStoreOptions store_options;
  if (options.worker.yield) store_options.write_yield_vm_steps = kWriteYieldVmSteps;
  store_options.covariance_window_hops = options.worker.update.window_hops;
  auto sqlite = CreateSqliteMapStore(options.db_path, store_options);
  if (!sqlite.ok()) return sqlite.status();
  // Map reads are served from memory; SQLite stays the source of truth.
  auto store = CachedMapStore::Create(std::move(*sqlite), options.worker.update.window_hops);
  if (!store.ok()) return store.status();
  server->store_ = std::move(*store);
  MapWorkerOptions worker_options = options.worker;
  if (!options.metrics_listen.empty()) {
    auto metrics = ServerMetrics::Start(options.metrics_listen, server->store_.get());
    if (!metrics.ok()) return metrics.status();
    server->metrics_ = std::move(*metrics);
    worker_options.on_applied = [m = server->metrics_.get()](const AppliedPassageTimings& t) { m->ObserveApplied(t); };
  }
  server->committer_ = std::make_unique<UploadCommitter>(server->store_.get(), options.max_queue);
  auto worker = MapWorker::Create(server->store_.get(), worker_options, &server->notifier_);
  if (!worker.ok()) return worker.status();
  server->worker_ = std::move(*worker);

  MapServiceContext& context = server->context_;
  context.store = server->store_.get();
  context.committer = server->committer_.get();
  context.worker = server->worker_.get();
  context.notifier = &server->notifier_;
  context.metrics = server->metrics_.get();
  context.limits.max_passage_bytes = static_cast<size_t>(options.max_passage_mb) << 20;
  context.update = options.worker.update;
  server->service_ = std::make_unique<MapService>(&context);

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(options.listen, grpc::InsecureServerCredentials(), &server->port_);
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
  return server;
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
  context_.accepting_uploads = false;
  if (worker_ != nullptr) worker_->Stop();
  notifier_.Close();
  if (server_ != nullptr) {
    server_->Shutdown(std::chrono::system_clock::now() + grace);
    server_->Wait();
  }
  spdlog::info("event=stopped");
}

}  // namespace crowdmap
