#include "server/log_format.h"

#include <atomic>
#include <chrono>
#include <cstdint>
#include <ctime>
#include <random>

#include "absl/strings/str_format.h"

namespace crowdmap {
namespace {

class JsonLogFormatter : public spdlog::formatter {
 public:
  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    const auto since_epoch = msg.time.time_since_epoch();
    const std::time_t seconds = std::chrono::duration_cast<std::chrono::seconds>(since_epoch).count();
    const int millis = static_cast<int>(std::chrono::duration_cast<std::chrono::milliseconds>(since_epoch).count() % 1000);
    std::tm utc{};
    gmtime_r(&seconds, &utc);
    char time[32];
    std::strftime(time, sizeof(time), "%Y-%m-%dT%H:%M:%S", &utc);
    const spdlog::string_view_t level = spdlog::level::to_string_view(msg.level);
    const std::string line = JsonText({{"time", absl::StrFormat("%s.%03dZ", time, millis)},
                                       {"level", std::string_view(level.data(), level.size())},
                                       {"msg", std::string_view(msg.payload.data(), msg.payload.size())}}) +
                             "\n";
    dest.append(line.data(), line.data() + line.size());
  }

  std::unique_ptr<spdlog::formatter> clone() const override { return std::make_unique<JsonLogFormatter>(); }
};

}  // namespace

std::string JsonText(const nlohmann::ordered_json& value) {
  return value.dump(-1, ' ', /*ensure_ascii=*/true, nlohmann::ordered_json::error_handler_t::replace);
}

std::unique_ptr<spdlog::formatter> MakeJsonLogFormatter() { return std::make_unique<JsonLogFormatter>(); }

std::string NewRequestId() {
  static const uint64_t start = [] {
    std::random_device device;
    return (static_cast<uint64_t>(device()) << 32) ^ device();
  }();
  static std::atomic<uint64_t> counter{0};
  return absl::StrFormat("%016x", start + counter.fetch_add(1, std::memory_order_relaxed));
}

}  // namespace crowdmap
