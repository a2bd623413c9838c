#ifndef CROWDMAP_TESTS_SUPPORT_MAPD_PROCESS_H_
#define CROWDMAP_TESTS_SUPPORT_MAPD_PROCESS_H_

// The real mapd binary as a child process, for tests that kill and restart it.

#include <arpa/inet.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "server/mapd_config.h"
#include "tests/support/mock_vehicle.h"

namespace crowdmap {

inline int FreeLoopbackPort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr));
  socklen_t len = sizeof(addr);
  getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
  close(fd);
  return ntohs(addr.sin_port);
}

// mapd's flags for a test that replays its passages in process in their commit order: mapd takes
// stale passages again while its queue is empty (--relinearize-sigmas), at moments a replay cannot
// know, so that is off (ServiceRelinearization in parallel_workers_test.cc tests it).
inline std::vector<std::string> ReplayableMapdFlags() { return {"--relinearize-sigmas", "0"}; }
// The in-process options of mapd's defaults with ReplayableMapdFlags().
inline MapUpdateOptions ReplayableMapdUpdateOptions() {
  MapUpdateOptions options = MapdDefaultUpdateOptions();
  options.relinearize_sigmas = 0.0;
  return options;
}

// A mapd child process serving `db` on a loopback port (a free one, or `port`), its stderr
// appended to `log_path`, with `extra_args` after the defaults.
class MapdProcess {
 public:
  MapdProcess(const std::string& db, const std::string& log_path, int port = 0,
              const std::vector<std::string>& extra_args = {})
      : port_(port > 0 ? port : FreeLoopbackPort()) {
    const std::string listen = "127.0.0.1:" + std::to_string(port_);
    std::vector<std::string> args = {MAPD_PATH, "--listen", listen, "--db", db, "--create", "--log-level", "info"};
    args.insert(args.end(), extra_args.begin(), extra_args.end());
    pid_ = fork();
    if (pid_ == 0) {
      freopen(log_path.c_str(), "a", stderr);
      std::vector<char*> argv;
      for (std::string& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(MAPD_PATH, argv.data());
      _exit(127);
    }
  }
  ~MapdProcess() {
    if (pid_ > 0) Kill(SIGKILL);
  }
  MapdProcess(const MapdProcess&) = delete;
  MapdProcess& operator=(const MapdProcess&) = delete;

  int port() const { return port_; }
  // Why WaitReady last failed.
  const std::string& last_error() const { return last_error_; }
  std::string address() const { return "127.0.0.1:" + std::to_string(port_); }

  // Waits until the port accepts connections (a client dialing earlier would sit in gRPC's
  // reconnect backoff), then until the server answers (about 10 s at most).
  bool WaitReady() {
    for (int i = 0; i < 1000; ++i) {
      const int fd = socket(AF_INET, SOCK_STREAM, 0);
      sockaddr_in addr{};
      addr.sin_family = AF_INET;
      addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      addr.sin_port = htons(port_);
      const bool up = connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0;
      close(fd);
      if (up) {
        absl::StatusOr<pb::MapInfo> info = MockVehicle(address()).GetMapInfo();
        if (info.ok()) return true;
        last_error_ = info.status().ToString();
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return false;
  }

  // Sends `signal` and returns the wait status.
  int Kill(int signal) {
    kill(pid_, signal);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
    return status;
  }

 private:
  int port_;
  pid_t pid_ = -1;
  std::string last_error_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_SUPPORT_MAPD_PROCESS_H_
