#include "server/quotas.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

using Clock = std::chrono::steady_clock;
constexpr char kRetryPayload[] = "crowdmap/retry-after-ms";
constexpr size_t kMaxTrackedVehicles = 100000;  // idle (full) buckets are forgotten beyond this

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now().time_since_epoch()).count();
}

}  // namespace

absl::Status LimitOptions::Validate(int max_passage_mb) const {
  if (!(vehicle_uploads_per_s >= 0) || !(vehicle_upload_mb_per_s >= 0)) {
    return absl::InvalidArgumentError("--vehicle-upload-rate and --vehicle-upload-mb-per-s: must be >= 0 (0 = off)");
  }
  if (vehicle_uploads_per_s > 0 && vehicle_upload_burst < 1) {
    return absl::InvalidArgumentError(absl::StrCat("--vehicle-upload-burst: must be >= 1, got ", vehicle_upload_burst));
  }
  if (vehicle_upload_mb_per_s > 0 && vehicle_upload_burst_mb < max_passage_mb) {
    return absl::InvalidArgumentError(absl::StrCat("--vehicle-upload-burst-mb: must be at least --max-passage-mb (",
                                                   max_passage_mb, ") or no passage that large could pass, got ",
                                                   vehicle_upload_burst_mb));
  }
  if (max_upload_streams < 0 || max_watch_streams < 0 || upload_idle_timeout_s < 0 || max_inflight_mb < 0) {
    return absl::InvalidArgumentError(
        "--max-upload-streams, --max-watch-streams, --upload-idle-timeout-s, --max-inflight-mb: must be >= 0 (0 = off)");
  }
  if (max_covariance_reads < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("--max-covariance-reads: must be >= 0 (0 = off), got ", max_covariance_reads));
  }
  if (max_upload_streams_per_identity < 0) {
    return absl::InvalidArgumentError(absl::StrCat("--max-upload-streams-per-identity: must be >= 0 (0 = off), got ",
                                                   max_upload_streams_per_identity));
  }
  if (max_watch_streams_per_identity < 0) {
    return absl::InvalidArgumentError(absl::StrCat("--max-watch-streams-per-identity: must be >= 0 (0 = off), got ",
                                                   max_watch_streams_per_identity));
  }
  if (max_inflight_mb > 0 && max_inflight_mb < max_passage_mb) {
    return absl::InvalidArgumentError(absl::StrCat("--max-inflight-mb: must be 0 (off) or at least --max-passage-mb (",
                                                   max_passage_mb, "), got ", max_inflight_mb));
  }
  if (max_threads < 4) return absl::InvalidArgumentError(absl::StrCat("--max-threads: must be >= 4, got ", max_threads));
  if (max_upload_streams > 0 && max_watch_streams > 0 && max_threads < max_upload_streams + max_watch_streams + 16) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--max-threads: must exceed --max-upload-streams + --max-watch-streams by at least 16 (each open stream holds ",
        "a thread; unary calls need the rest), got ", max_threads, " < ", max_upload_streams, " + ", max_watch_streams,
        " + 16"));
  }
  return absl::OkStatus();
}

absl::Status ExhaustedRetryAfter(const std::string& message, std::chrono::milliseconds retry_after) {
  absl::Status status = absl::ResourceExhaustedError(
      absl::StrCat(message, "; retry after ", (retry_after.count() + 999) / 1000, " s"));
  status.SetPayload(kRetryPayload, absl::Cord(absl::StrCat(retry_after.count())));
  return status;
}

std::chrono::milliseconds RetryAfter(const absl::Status& status) {
  const auto payload = status.GetPayload(kRetryPayload);
  int64_t ms = 0;
  if (!payload.has_value() || !absl::SimpleAtoi(std::string(*payload), &ms)) return std::chrono::milliseconds(0);
  return std::chrono::milliseconds(ms);
}

void AddRetryTrailers(const absl::Status& status, grpc::ServerContextBase* ctx) {
  const std::chrono::milliseconds after = RetryAfter(status);
  if (after.count() <= 0) return;
  ctx->AddTrailingMetadata("retry-after", absl::StrCat((after.count() + 999) / 1000));
  ctx->AddTrailingMetadata("grpc-retry-pushback-ms", absl::StrCat(after.count()));
}

void TokenBucket::Refill(Clock::time_point now) {
  if (now > last_) {
    tokens_ = std::min(burst_, tokens_ + rate_ * std::chrono::duration<double>(now - last_).count());
    last_ = now;
  }
}

std::chrono::milliseconds TokenBucket::WaitFor(double n, Clock::time_point now) {
  Refill(now);
  if (tokens_ >= n) return std::chrono::milliseconds(0);
  const double wait_s = (n - tokens_) / rate_;
  return std::chrono::milliseconds(std::max<int64_t>(1, static_cast<int64_t>(std::ceil(wait_s * 1000.0))));
}

bool TokenBucket::Full(Clock::time_point now) const {
  return tokens_ + rate_ * std::chrono::duration<double>(now - last_).count() >= burst_;
}

absl::Status VehicleQuotas::Admit(const std::string& vehicle_id, size_t bytes) {
  const bool count_on = options_.vehicle_uploads_per_s > 0, bytes_on = options_.vehicle_upload_mb_per_s > 0;
  if (!count_on && !bytes_on) return absl::OkStatus();
  const Clock::time_point now = Clock::now();
  const double mib = static_cast<double>(bytes) / (1 << 20);
  std::lock_guard<std::mutex> lock(mu_);
  if (vehicles_.size() >= kMaxTrackedVehicles) {
    for (auto it = vehicles_.begin(); it != vehicles_.end();) {
      it = it->second.uploads.Full(now) && it->second.bytes.Full(now) ? vehicles_.erase(it) : std::next(it);
    }
  }
  auto it = vehicles_.try_emplace(
      vehicle_id, Buckets{TokenBucket(options_.vehicle_uploads_per_s, options_.vehicle_upload_burst, now),
                          TokenBucket(options_.vehicle_upload_mb_per_s, options_.vehicle_upload_burst_mb, now)}).first;
  Buckets& b = it->second;
  // Take both or neither.
  if (count_on) {
    if (auto wait = b.uploads.WaitFor(1.0, now); wait.count() > 0) {
      return ExhaustedRetryAfter(absl::StrCat("vehicle_id: over its upload quota (", options_.vehicle_uploads_per_s,
                                              " passages/s, burst ", options_.vehicle_upload_burst, ")"),
                                 wait);
    }
  }
  if (bytes_on) {
    if (auto wait = b.bytes.WaitFor(mib, now); wait.count() > 0) {
      return ExhaustedRetryAfter(absl::StrCat("vehicle_id: over its byte quota (", options_.vehicle_upload_mb_per_s,
                                              " MiB/s, burst ", options_.vehicle_upload_burst_mb, " MiB)"),
                                 wait);
    }
  }
  if (count_on) b.uploads.Take(1.0);
  if (bytes_on) b.bytes.Take(mib);
  return absl::OkStatus();
}

InflightBytes::Lease::~Lease() {
  if (held_ > 0) owner_->held_.fetch_sub(held_);
}

absl::Status InflightBytes::Lease::GrowTo(size_t total) {
  const int64_t more = static_cast<int64_t>(total) - held_;
  if (more <= 0) return absl::OkStatus();
  const int64_t now = owner_->held_.fetch_add(more) + more;
  if (owner_->max_bytes_ > 0 && now > owner_->max_bytes_) {
    owner_->held_.fetch_sub(more);
    return ExhaustedRetryAfter(absl::StrCat("server: ", owner_->max_bytes_ >> 20,
                                            " MiB of uploads in flight (--max-inflight-mb)"),
                               std::chrono::seconds(1));
  }
  held_ += more;
  return absl::OkStatus();
}

ConcurrentCalls::ConcurrentCalls(int max, std::string what, std::string flag)
    : max_(max), what_(std::move(what)), flag_(std::move(flag)) {}

ConcurrentCalls::Lease::~Lease() {
  std::lock_guard<std::mutex> lock(owner_->mu_);
  --owner_->running_;
}

absl::StatusOr<std::unique_ptr<ConcurrentCalls::Lease>> ConcurrentCalls::Enter() {
  std::lock_guard<std::mutex> lock(mu_);
  if (max_ > 0 && running_ >= max_) {
    return ExhaustedRetryAfter(absl::StrCat(what_, ": ", running_, " running, the most at once (", flag_,
                                            "); retry shortly"),
                               std::chrono::seconds(1));
  }
  ++running_;
  return std::unique_ptr<Lease>(new Lease(this));
}

int ConcurrentCalls::running() const {
  std::lock_guard<std::mutex> lock(mu_);
  return running_;
}

StreamLimiter::StreamLimiter(const LimitOptions& limits)
    : idle_timeout_(std::chrono::seconds(limits.upload_idle_timeout_s)),
      upload_counts_{limits.max_upload_streams, limits.max_upload_streams_per_identity, "chunked uploads",
                     "--max-upload-streams", 0, {}},
      watch_counts_{limits.max_watch_streams, limits.max_watch_streams_per_identity, "WatchRegion streams",
                    "--max-watch-streams", 0, {}} {
  if (idle_timeout_.count() > 0) watchdog_ = std::thread([this] { Watchdog(); });
}

StreamLimiter::~StreamLimiter() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  stop_cv_.notify_all();
  if (watchdog_.joinable()) watchdog_.join();
}

StreamLimiter::Lease::Lease(StreamLimiter* owner, grpc::ServerContext* ctx, bool upload, std::string identity)
    : owner_(owner), ctx_(ctx), upload_(upload), identity_(std::move(identity)), start_ms_(NowMs()),
      last_ms_(start_ms_) {}

StreamLimiter::Lease::~Lease() {
  std::lock_guard<std::mutex> lock(owner_->mu_);
  if (upload_) {
    owner_->uploads_.erase(this);
    Release(&owner_->upload_counts_, identity_);
  } else {
    Release(&owner_->watch_counts_, identity_);
  }
}

void StreamLimiter::Lease::Touch(size_t bytes) {
  if (bytes == 0) return;
  bytes_.fetch_add(static_cast<int64_t>(bytes), std::memory_order_relaxed);
  last_ms_.store(NowMs(), std::memory_order_relaxed);
}

absl::Status StreamLimiter::Admit(Counts* counts, const std::string& identity, std::chrono::milliseconds retry_after) {
  if (counts->max > 0 && counts->open >= counts->max) {
    return ExhaustedRetryAfter(absl::StrCat("server: ", counts->max, " ", counts->what, " open (", counts->flag, ")"),
                               retry_after);
  }
  if (!identity.empty() && counts->max_per_identity > 0) {
    auto it = counts->per_identity.find(identity);
    if (it != counts->per_identity.end() && it->second >= counts->max_per_identity) {
      return ExhaustedRetryAfter(absl::StrCat("'", identity, "' has ", counts->max_per_identity, " ", counts->what,
                                              " open (", counts->flag, "-per-identity)"),
                                 retry_after);
    }
  }
  ++counts->open;
  if (!identity.empty()) ++counts->per_identity[identity];
  return absl::OkStatus();
}

void StreamLimiter::Release(Counts* counts, const std::string& identity) {
  --counts->open;
  if (identity.empty()) return;
  auto it = counts->per_identity.find(identity);
  if (it != counts->per_identity.end() && --it->second <= 0) counts->per_identity.erase(it);
}

absl::StatusOr<std::unique_ptr<StreamLimiter::Lease>> StreamLimiter::OpenUpload(grpc::ServerContext* ctx,
                                                                                const std::string& identity) {
  std::lock_guard<std::mutex> lock(mu_);
  if (absl::Status s = Admit(&upload_counts_, identity, std::chrono::seconds(1)); !s.ok()) return s;
  std::unique_ptr<Lease> lease(new Lease(this, ctx, /*upload=*/true, identity));
  uploads_.insert(lease.get());
  return lease;
}

absl::StatusOr<std::unique_ptr<StreamLimiter::Lease>> StreamLimiter::OpenWatch(grpc::ServerContext* ctx,
                                                                               const std::string& identity) {
  std::lock_guard<std::mutex> lock(mu_);
  if (absl::Status s = Admit(&watch_counts_, identity, std::chrono::seconds(5)); !s.ok()) return s;
  return std::unique_ptr<Lease>(new Lease(this, ctx, /*upload=*/false, identity));
}

int StreamLimiter::open_uploads() const {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(uploads_.size());
}

void StreamLimiter::Watchdog() {
  const auto period = std::min<std::chrono::milliseconds>(std::chrono::seconds(1), idle_timeout_ / 4);
  std::unique_lock<std::mutex> lock(mu_);
  while (!stop_cv_.wait_for(lock, std::max(period, std::chrono::milliseconds(10)), [this] { return stop_; })) {
    const int64_t now = NowMs();
    for (Lease* lease : uploads_) {
      const int64_t open_ms = now - lease->start_ms_;
      const bool idle = now - lease->last_ms_.load(std::memory_order_relaxed) > idle_timeout_.count();
      const bool trickle = open_ms > idle_timeout_.count() &&
                           lease->bytes_.load(std::memory_order_relaxed) * 1000 < kMinUploadBytesPerS * open_ms;
      if (!lease->timed_out_ && (idle || trickle)) {
        lease->timed_out_ = true;
        lease->ctx_->TryCancel();  // its Read() returns false; the lease is released under mu_
      }
    }
  }
}

}  // namespace crowdmap
