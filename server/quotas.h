#ifndef CROWDMAP_SERVER_QUOTAS_H_
#define CROWDMAP_SERVER_QUOTAS_H_

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>

#include <grpcpp/server_context.h>

#include "absl/status/statusor.h"

namespace crowdmap {

// Limits that keep one client from taking the server: per-vehicle upload quotas, streams, bytes
// held by handlers, threads. 0 switches a limit off where said.
struct LimitOptions {
  double vehicle_uploads_per_s = 1.0;   // sustained passages per second per vehicle_id (0 = off)
  int vehicle_upload_burst = 30;        // passages a vehicle may upload at once (after being idle)
  double vehicle_upload_mb_per_s = 8;   // sustained MiB per second per vehicle_id (0 = off)
  int vehicle_upload_burst_mb = 128;    // MiB at once; at least max_passage_mb
  int max_upload_streams = 64;          // concurrent UploadPassageChunked calls (0 = off)
  int max_watch_streams = 128;          // concurrent WatchRegion calls (0 = off)
  // Concurrent reads with covariances (GetTile, QueryRegion with include_cross_covariance): each
  // holds its page's dense joint covariance and a factorisation of the map around it, up to a few
  // hundred MB for a page of 2,000 landmarks (0 = off).
  int max_covariance_reads = 4;
  // The same per authenticated identity (a token or certificate), so that one identity cannot
  // hold the server's streams (0 = off; callers are not told apart with authentication off).
  int max_upload_streams_per_identity = 4;
  int max_watch_streams_per_identity = 16;
  // A chunked upload with no chunk for this long is cancelled (0 = off). At least the time one
  // chunk takes on the slowest link: MapClient's 1 MiB takes 33 s at 256 kbit/s.
  int upload_idle_timeout_s = 60;
  int max_inflight_mb = 512;            // upload bytes held by handlers at once (0 = off)
  // gRPC's threads for the synchronous RPCs (grpc::ResourceQuota); beyond them a call gets
  // RESOURCE_EXHAUSTED. More than the two stream caps together, so streams cannot take them all.
  int max_threads = 512;

  absl::Status Validate(int max_passage_mb) const;
};

// A RESOURCE_EXHAUSTED status that carries when to retry (RetryAfter reads it back).
absl::Status ExhaustedRetryAfter(const std::string& message, std::chrono::milliseconds retry_after);
std::chrono::milliseconds RetryAfter(const absl::Status& status);  // 0 when the status has none
// Sets the trailing metadata "retry-after" (whole seconds, rounded up) and
// "grpc-retry-pushback-ms" (gRPC's retry policy honours it) when `status` carries a retry time.
void AddRetryTrailers(const absl::Status& status, grpc::ServerContextBase* ctx);

// A token bucket: `rate` per second up to `burst`; starts full.
class TokenBucket {
 public:
  TokenBucket(double rate_per_s, double burst, std::chrono::steady_clock::time_point now)
      : rate_(rate_per_s), burst_(burst), tokens_(burst), last_(now) {}
  // 0 when `n` are there, otherwise how long until they are.
  std::chrono::milliseconds WaitFor(double n, std::chrono::steady_clock::time_point now);
  void Take(double n) { tokens_ -= n; }  // after WaitFor returned 0
  bool Full(std::chrono::steady_clock::time_point now) const;

 private:
  void Refill(std::chrono::steady_clock::time_point now);
  double rate_, burst_, tokens_;
  std::chrono::steady_clock::time_point last_;
};

// Per-vehicle upload quotas (passages and bytes). Thread-safe.
class VehicleQuotas {
 public:
  explicit VehicleQuotas(const LimitOptions& options) : options_(options) {}
  // OK (and the quota taken), or RESOURCE_EXHAUSTED with the time until this upload would fit.
  absl::Status Admit(const std::string& vehicle_id, size_t bytes);

 private:
  struct Buckets {
    TokenBucket uploads;
    TokenBucket bytes;
  };
  const LimitOptions options_;
  std::mutex mu_;
  std::map<std::string, Buckets> vehicles_;
};

// Upload bytes held by handlers, under a cap. Thread-safe.
class InflightBytes {
 public:
  explicit InflightBytes(int64_t max_bytes) : max_bytes_(max_bytes) {}
  // Holds `bytes` until the returned lease is destroyed or grows it.
  class Lease {
   public:
    Lease(InflightBytes* owner) : owner_(owner) {}
    ~Lease();
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;
    // Holds `total` bytes in all, or RESOURCE_EXHAUSTED (the lease keeps what it held).
    absl::Status GrowTo(size_t total);

   private:
    InflightBytes* owner_;
    int64_t held_ = 0;
  };
  int64_t held() const { return held_.load(); }

 private:
  const int64_t max_bytes_;
  std::atomic<int64_t> held_{0};
};

// At most `max` calls of one kind at once (0 = no limit); the next one gets RESOURCE_EXHAUSTED
// naming the setting, with a retry time. Thread-safe.
class ConcurrentCalls {
 public:
  ConcurrentCalls(int max, std::string what, std::string flag);
  ConcurrentCalls(const ConcurrentCalls&) = delete;
  ConcurrentCalls& operator=(const ConcurrentCalls&) = delete;

  class Lease {
   public:
    ~Lease();
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;

   private:
    friend class ConcurrentCalls;
    explicit Lease(ConcurrentCalls* owner) : owner_(owner) {}
    ConcurrentCalls* owner_;
  };
  absl::StatusOr<std::unique_ptr<Lease>> Enter();
  int running() const;

 private:
  const int max_;
  const std::string what_, flag_;
  mutable std::mutex mu_;
  int running_ = 0;
};

// Counts the streaming calls, in all and per identity, and cancels chunked uploads that stall. A
// watchdog thread checks the open uploads every quarter of the idle timeout (at most every second).
class StreamLimiter {
 public:
  // Reads the stream caps and the idle timeout of `limits`.
  explicit StreamLimiter(const LimitOptions& limits);
  ~StreamLimiter();
  StreamLimiter(const StreamLimiter&) = delete;
  StreamLimiter& operator=(const StreamLimiter&) = delete;

  class Lease {
   public:
    ~Lease();
    // A chunk of `bytes` arrived. An empty one is no progress: it keeps no stream open.
    void Touch(size_t bytes);
    bool timed_out() const { return timed_out_.load(); }

   private:
    friend class StreamLimiter;
    Lease(StreamLimiter* owner, grpc::ServerContext* ctx, bool upload, std::string identity);
    StreamLimiter* owner_;
    grpc::ServerContext* ctx_;
    bool upload_;
    const std::string identity_;  // counted per identity when not empty
    const int64_t start_ms_;
    std::atomic<int64_t> last_ms_;
    std::atomic<int64_t> bytes_{0};
    std::atomic<bool> timed_out_{false};
  };
  // Once a chunked upload has been open longer than the idle timeout, it must have averaged this
  // much: bytes dribbled in just inside the idle timeout would otherwise hold a stream for days.
  static constexpr int64_t kMinUploadBytesPerS = 1024;
  // A lease for one chunked upload (watched for idleness and a trickle), or RESOURCE_EXHAUSTED.
  // `identity` is the authenticated caller's name, counted against the per-identity caps; empty
  // when authentication is off.
  absl::StatusOr<std::unique_ptr<Lease>> OpenUpload(grpc::ServerContext* ctx, const std::string& identity);
  absl::StatusOr<std::unique_ptr<Lease>> OpenWatch(grpc::ServerContext* ctx, const std::string& identity);
  int open_uploads() const;

 private:
  // Streams of one kind: open in all, and per identity.
  struct Counts {
    const int max, max_per_identity;
    const char* what;  // for the refusal
    const char* flag;
    int open = 0;
    std::map<std::string, int> per_identity;
  };
  // Counts a new stream in `counts`, or RESOURCE_EXHAUSTED naming the cap it would break. Under mu_.
  static absl::Status Admit(Counts* counts, const std::string& identity, std::chrono::milliseconds retry_after);
  static void Release(Counts* counts, const std::string& identity);  // under mu_
  void Watchdog();

  const std::chrono::milliseconds idle_timeout_;
  mutable std::mutex mu_;
  std::condition_variable stop_cv_;
  bool stop_ = false;
  Counts upload_counts_, watch_counts_;
  std::set<Lease*> uploads_;  // for the watchdog
  std::thread watchdog_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_QUOTAS_H_
