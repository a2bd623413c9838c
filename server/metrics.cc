#include "server/metrics.h"

#include <chrono>
#include <exception>
#include <mutex>
#include <set>
#include <vector>

#include <google/protobuf/descriptor.h>
#include <prometheus/collectable.h>
#include <prometheus/counter.h>
#include <prometheus/exposer.h>
#include <prometheus/family.h>
#include <prometheus/histogram.h>
#include <prometheus/metric_family.h>
#include <prometheus/registry.h>
#include <spdlog/spdlog.h>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "server/http_thread_stacks.h"
#include "server/request_log.h"

namespace crowdmap {
namespace {

using prometheus::ClientMetric;
using prometheus::MetricFamily;

// RPCs: from a cached tile read (under a millisecond) to a chunked upload or a stream.
const prometheus::Histogram::BucketBoundaries& RpcBuckets() {
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30};
  return kBuckets;
}

// A passage's steps: a commit of a few milliseconds to a young map's joint re-solve (seconds).
const prometheus::Histogram::BucketBoundaries& WorkBuckets() {
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60};
  return kBuckets;
}

// "service/method" of every RPC mapd serves; anything else is counted as unknown.
const std::set<std::string, std::less<>>& ServedMethods() {
  static const std::set<std::string, std::less<>> kMethods = [] {
    std::set<std::string, std::less<>> methods = {"grpc.health.v1.Health/Check", "grpc.health.v1.Health/Watch",
                                                  "grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo"};
    const google::protobuf::ServiceDescriptor* service =
        google::protobuf::DescriptorPool::generated_pool()->FindServiceByName("mapservice.v1.MapService");
    for (int i = 0; service != nullptr && i < service->method_count(); ++i) {
      methods.insert(absl::StrCat(service->full_name(), "/", service->method(i)->name()));
    }
    return methods;
  }();
  return kMethods;
}

MetricFamily GaugeFamily(const std::string& name, const std::string& help) {
  MetricFamily family;
  family.name = name;
  family.help = help;
  family.type = prometheus::MetricType::Gauge;
  return family;
}

ClientMetric GaugeValue(double value, std::vector<ClientMetric::Label> labels = {}) {
  ClientMetric metric;
  metric.label = std::move(labels);
  metric.gauge.value = value;
  return metric;
}

// Times one call, from its creation to the status the server sends.
class RpcTimer : public grpc::experimental::Interceptor {
 public:
  RpcTimer(ServerMetrics* metrics, const char* method)
      : metrics_(metrics), method_(method == nullptr ? "" : method), start_(std::chrono::steady_clock::now()) {}

  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(grpc::experimental::InterceptionHookPoints::PRE_SEND_STATUS)) {
      const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
      metrics_->ObserveRpc(method_, methods->GetSendStatus().error_code(), seconds);
    }
    methods->Proceed();
  }

 private:
  ServerMetrics* const metrics_;
  const std::string method_;
  const std::chrono::steady_clock::time_point start_;
};

class RpcTimerFactory : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit RpcTimerFactory(ServerMetrics* metrics) : metrics_(metrics) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(grpc::experimental::ServerRpcInfo* info) override {
    return new RpcTimer(metrics_, info->method());
  }

 private:
  ServerMetrics* const metrics_;
};

}  // namespace

// The queue and the map, read from the store's row counts (GetMapInfo's source) at each scrape.
class StoreCollector : public prometheus::Collectable {
 public:
  explicit StoreCollector(MapStoreInterface* store) : store_(store) {}

  void WatchWorker(const MapWorker* worker) {
    std::lock_guard<std::mutex> lock(worker_mu_);
    worker_ = worker;
  }

  std::vector<MetricFamily> Collect() const override {
    absl::StatusOr<MapStats> stats = store_->GetStats();
    MetricFamily up = GaugeFamily("mapd_store_up", "1 when the store answered this scrape, else 0");
    up.metric.push_back(GaugeValue(stats.ok() ? 1 : 0));
    if (!stats.ok()) return {up};
    MetricFamily queue = GaugeFamily("mapd_queue_depth", "passages queued or processing");
    queue.metric.push_back(GaugeValue(static_cast<double>(stats->queue_depth())));
    MetricFamily passages = GaugeFamily("mapd_passages", "passages by state");
    for (int state = 1; state < kPassageStateCount; ++state) {
      passages.metric.push_back(GaugeValue(static_cast<double>(stats->passages_by_state[state]),
                                           {{"state", PassageStateName(static_cast<PassageState>(state))}}));
    }
    MetricFamily landmarks = GaugeFamily("mapd_map_landmarks", "landmarks in the map");
    landmarks.metric.push_back(GaugeValue(static_cast<double>(stats->landmark_count)));
    MetricFamily factors = GaugeFamily("mapd_map_factors", "information factors kept in the map");
    factors.metric.push_back(GaugeValue(static_cast<double>(stats->factor_count)));
    MetricFamily version = GaugeFamily("mapd_map_version", "the map's version (one more per committed change)");
    version.metric.push_back(GaugeValue(static_cast<double>(stats->map_version)));
    std::vector<MetricFamily> out = {up, queue, passages, landmarks, factors, version};
    std::lock_guard<std::mutex> lock(worker_mu_);
    if (worker_ != nullptr) {
      MetricFamily due = GaugeFamily("mapd_relinearizations_due",
                                     "re-linearisations the worker owes, done while the queue is empty (--relinearize-sigmas)");
      due.metric.push_back(GaugeValue(static_cast<double>(worker_->relinearizations_due())));
      out.push_back(std::move(due));
    }
    return out;
  }

 private:
  MapStoreInterface* const store_;
  mutable std::mutex worker_mu_;
  const MapWorker* worker_ = nullptr;
};

absl::StatusOr<std::unique_ptr<ServerMetrics>> ServerMetrics::Start(const std::string& listen,
                                                                    MapStoreInterface* store) {
  if (listen.empty() || listen.find(':') == std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat("metrics-listen: expected host:port, got '", listen, "'"));
  }
  std::unique_ptr<ServerMetrics> m(new ServerMetrics());
  m->registry_ = std::make_shared<prometheus::Registry>();
  prometheus::Registry& r = *m->registry_;
  m->rpc_duration_ = &prometheus::BuildHistogram()
                          .Name("mapd_rpc_duration_seconds")
                          .Help("RPC latency, from the call's start to its status, by method and status code")
                          .Register(r);
  auto work = [&r](const std::string& name, const std::string& help) {
    return &prometheus::BuildHistogram().Name(name).Help(help).Register(r).Add({}, WorkBuckets());
  };
  m->apply_ = work("mapd_passage_apply_seconds", "time to apply one passage: update, durable commit, mirror");
  m->solve_ = work("mapd_passage_solve_seconds", "the estimator's solves for one applied passage");
  m->covariance_ = work("mapd_passage_covariance_seconds", "the estimator's covariance recovery for one applied passage");
  m->commit_ = work("mapd_passage_commit_seconds", "the durable commit of one applied passage");
  m->recomputed_ = &prometheus::BuildCounter()
                         .Name("mapd_passage_recomputed_total")
                         .Help("updates computed again because another worker's commit changed what they read (--workers)")
                         .Register(r)
                         .Add({});
  auto& inflations = prometheus::BuildCounter()
                         .Name("mapd_passage_inflations_total")
                         .Help("applied passages whose noise a consistency test found larger than declared, by test: "
                               "the whole subgraph's chi-square, or one sensor's own (odometry, gnss, camera)")
                         .Register(r);
  m->inflated_[0] = &inflations.Add({{"test", "whole"}});
  for (int s = 0; s < kPassageSensors; ++s) m->inflated_[1 + s] = &inflations.Add({{"test", PassageSensorName(s)}});
  auto& relinearizations = prometheus::BuildCounter()
                               .Name("mapd_relinearizations_total")
                               .Help("retained passages taken again at the map's current estimate "
                                     "(--relinearize-sigmas), by outcome")
                               .Register(r);
  m->relinearized_ = &relinearizations.Add({{"outcome", "committed"}});
  m->relinearizations_refused_ = &relinearizations.Add({{"outcome", "refused"}});
  m->upload_bytes_ = &prometheus::BuildCounter()
                          .Name("mapd_upload_bytes_total")
                          .Help("serialized passage bytes of acknowledged uploads, duplicates included")
                          .Register(r)
                          .Add({});
  auto& uploads = prometheus::BuildCounter().Name("mapd_uploads_total").Help("acknowledged uploads").Register(r);
  m->uploads_new_ = &uploads.Add({{"outcome", "queued"}});
  m->uploads_duplicate_ = &uploads.Add({{"outcome", "duplicate"}});
  auto& covariance_reads =
      prometheus::BuildCounter()
          .Name("mapd_covariance_reads_total")
          .Help("reads with covariances (GetTile, QueryRegion) by how their covariance relates to the exact one")
          .Register(r);
  for (CovarianceBound bound :
       {CovarianceBound::kExact, CovarianceBound::kConservative, CovarianceBound::kMayBeNarrower}) {
    m->covariance_reads_[static_cast<int>(bound)] = &covariance_reads.Add({{"bound", CovarianceBoundName(bound)}});
  }
  prometheus::BuildGauge()
      .Name("mapd_build_info")
      .Help("1, labelled with the build's version")
      .Register(r)
      .Add({{"version", CROWDMAP_VERSION}})
      .Set(1);
  m->store_collector_ = std::make_shared<StoreCollector>(store);
  try {
    m->exposer_ = std::make_unique<prometheus::Exposer>(listen, 2);
  } catch (const std::exception& e) {
    return absl::UnavailableError(
        absl::StrCat("metrics-listen: cannot serve metrics on ", listen, " (in use by another process?): ", e.what()));
  }
  m->exposer_->RegisterCollectable(m->registry_);
  m->exposer_->RegisterCollectable(m->store_collector_);
  const std::vector<int> ports = m->exposer_->GetListeningPorts();
  m->port_ = ports.empty() ? 0 : ports.front();
  spdlog::info("event=metrics listen={} port={} thread_stack_bytes={}", EscapeForLog(listen), m->port_,
               HttpThreadStackBytes());
  return m;
}

ServerMetrics::~ServerMetrics() = default;

void ServerMetrics::ObserveRpc(std::string_view full_method, grpc::StatusCode code, double seconds) {
  std::string_view name = full_method;
  if (!name.empty() && name.front() == '/') name.remove_prefix(1);
  std::string service = "unknown", method = "unknown";
  if (ServedMethods().count(name) > 0) {
    const size_t slash = name.find('/');
    service = std::string(name.substr(0, slash));
    method = std::string(name.substr(slash + 1));
  }
  rpc_duration_
      ->Add({{"service", service}, {"method", method},
             {"code", absl::StatusCodeToString(static_cast<absl::StatusCode>(code))}},
            RpcBuckets())
      .Observe(seconds);
}

void ServerMetrics::ObserveCovarianceRead(CovarianceBound bound) {
  covariance_reads_[static_cast<int>(bound)]->Increment();
}

void ServerMetrics::ObserveUpload(size_t bytes, bool duplicate) {
  upload_bytes_->Increment(static_cast<double>(bytes));
  (duplicate ? uploads_duplicate_ : uploads_new_)->Increment();
}

void ServerMetrics::ObserveApplied(const AppliedPassageTimings& t) {
  apply_->Observe(t.apply_ms / 1000.0);
  solve_->Observe(t.solve_ms / 1000.0);
  covariance_->Observe(t.covariance_ms / 1000.0);
  commit_->Observe(t.commit_ms / 1000.0);
  recomputed_->Increment(t.recomputed);
  if (t.inflated) inflated_[0]->Increment();
  for (int s = 0; s < kPassageSensors; ++s) {
    if (t.sensor_inflated[s]) inflated_[1 + s]->Increment();
  }
}

void ServerMetrics::WatchWorker(const MapWorker* worker) { store_collector_->WatchWorker(worker); }

void ServerMetrics::ObserveRelinearized(bool committed) {
  (committed ? relinearized_ : relinearizations_refused_)->Increment();
}

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> ServerMetrics::InterceptorFactory() {
  return std::make_unique<RpcTimerFactory>(this);
}

}  // namespace crowdmap
