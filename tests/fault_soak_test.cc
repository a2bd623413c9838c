// Faults over a whole run of the real mapd: SIGKILLs at random moments while several clients
// upload and the young map's joint solves run, and a full disk while uploads continue. Every
// acknowledged passage must end APPLIED exactly once (its state, the counts, and the map equal
// to an in-process replay of the same passages in the same order), and uploads on a full disk
// must be refused with a retryable code and a message.
//
// CI runs a short version; the full run (see README, "Faults and recovery"), one command:
//   CROWDMAP_SOAK_KILLS=24 CROWDMAP_SOAK_PASSAGES=130 CROWDMAP_SOAK_LANDMARKS=25 CROWDMAP_SOAK_PASSAGE_S=200
//   CROWDMAP_SOAK_FULL_DISK_S=60 CROWDMAP_SOAK_DISK_PASSAGES=60 ./build/tests/service_fault_soak_test
#include <sys/mount.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <thread>

#include "absl/strings/str_cat.h"
#include "core/estimation/map_updater.h"
#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "server/mapd_config.h"
#include "tests/support/map_compare.h"
#include "tests/support/mapd_process.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// The last lines of mapd's log, for a failure message.
std::string LogTail(const std::string& path, size_t bytes = 3000) {
  std::ifstream in(path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return text.size() > bytes ? text.substr(text.size() - bytes) : text;
}

int EnvInt(const char* name, int fallback) {
  const char* v = std::getenv(name);
  return v != nullptr && std::atoi(v) > 0 ? std::atoi(v) : fallback;
}

// The passage counts at which the default settings solve the map jointly: every passage of the
// warm-up (8), then the re-solves at each doubling up to 128.
bool IsJointSolve(int passage_number) {
  return passage_number <= 8 || passage_number == 16 || passage_number == 32 || passage_number == 64 ||
         passage_number == 128;
}

// What happened to one passage's upload.
struct UploadRecord {
  bool acknowledged = false;
  int64_t id = 0;
};

// Refused upload attempts, by phase.
struct Refusals {
  std::mutex mu;
  std::map<grpc::StatusCode, int> by_code;
  std::map<grpc::StatusCode, std::string> example;
  int empty_messages = 0;

  void Add(const absl::Status& s) {
    std::lock_guard<std::mutex> lock(mu);
    const auto code = static_cast<grpc::StatusCode>(s.code());
    ++by_code[code];
    if (example.count(code) == 0) example[code] = std::string(s.message());
    if (s.message().empty()) ++empty_messages;
  }
  std::string Brief() {
    std::lock_guard<std::mutex> lock(mu);
    std::string out;
    for (const auto& [code, n] : by_code) absl::StrAppend(&out, " code", static_cast<int>(code), "=", n, " (\"", example[code], "\")");
    return out.empty() ? " none" : out;
  }
};

// Clients uploading passages [first, last) of the scenario, `clients` threads, each passage
// retried (one attempt at a time, every refusal recorded) until acknowledged, with a random pause
// of mean `pace_ms` before each. The server may be down for a while: they keep trying.
class Fleet {
 public:
  Fleet(const Scenario& scenario, const std::string& address, int first, int last, int clients, int pace_ms,
        Refusals* refusals, std::vector<UploadRecord>* records)
      : refusals_(refusals), records_(records) {
    for (int c = 0; c < clients; ++c) {
      threads_.emplace_back([=, &scenario] {
        std::mt19937 rng(1000 + c);
        std::uniform_int_distribution<int> pause(0, 2 * pace_ms);
        MockVehicle vehicle(address);
        for (int i = first + c; i < last; i += clients) {
          std::this_thread::sleep_for(std::chrono::milliseconds(pause(rng)));
          pb::Passage wire;
          PassageToProto(scenario.MakePassage(i), &wire);
          const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(5);
          std::chrono::milliseconds backoff(20);
          while (std::chrono::steady_clock::now() < give_up) {
            absl::StatusOr<pb::UploadPassageResponse> response = vehicle.UploadOnce(wire);
            if (response.ok()) {
              (*records_)[i] = {true, response->status().id()};
              break;
            }
            refusals_->Add(response.status());
            std::this_thread::sleep_for(backoff);
            backoff = std::min(backoff * 2, std::chrono::milliseconds(500));
          }
        }
      });
    }
  }
  void Join() {
    for (std::thread& t : threads_) t.join();
    threads_.clear();
  }
  ~Fleet() { Join(); }

 private:
  Refusals* refusals_;
  std::vector<UploadRecord>* records_;
  std::vector<std::thread> threads_;
};

// Every acknowledged passage is APPLIED, nothing failed, was refused or quarantined, and the map
// equals the same passages applied in-process in the server's order, each as the server took it
// (a joint solve, or a sequential update where its joint solve kept being interrupted: its
// result's strategy says which): a passage applied twice, or one lost, changes both the map and
// its version.
void ExpectEveryAcknowledgedPassageAppliedOnce(MockVehicle* client, const Scenario& scenario,
                                               const std::vector<UploadRecord>& records) {
  auto info = client->WaitUntilIdle(std::chrono::minutes(10));
  ASSERT_TRUE(info.ok()) << info.status();
  struct Applied {
    int64_t id;   // the server's
    int index;    // the scenario's
    bool joint;   // the server took it by a joint solve
    bool operator<(const Applied& o) const { return id < o.id; }
  };
  std::vector<Applied> order;
  int acknowledged = 0, applied = 0;
  for (size_t i = 0; i < records.size(); ++i) {
    EXPECT_TRUE(records[i].acknowledged) << "passage " << i << " was never acknowledged";
    if (!records[i].acknowledged) continue;
    ++acknowledged;
    const Passage p = scenario.MakePassage(static_cast<int>(i));
    auto status = client->GetPassage(p.vehicle_id, p.passage_id);
    ASSERT_TRUE(status.ok()) << status.status();
    EXPECT_EQ(status->id(), records[i].id);
    EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED) << p.passage_id << " error=" << status->error();
    applied += status->state() == pb::PASSAGE_STATE_APPLIED;
    const std::string& strategy = status->result().strategy();
    order.push_back({status->id(), static_cast<int>(i), strategy.size() > 6 && strategy.substr(strategy.size() - 6) == "+joint"});
  }
  EXPECT_EQ(info->passages_applied(), acknowledged);
  EXPECT_EQ(info->passages_failed(), 0);
  EXPECT_EQ(info->passages_rejected(), 0);
  EXPECT_EQ(info->passages_quarantined(), 0);
  EXPECT_EQ(info->queue_depth(), 0);
  std::sort(order.begin(), order.end());
  MapState expected;
  MapUpdater updater{ReplayableMapdUpdateOptions()};  // mapd's
  int sequential_instead = 0;
  for (const Applied& a : order) {
    const Passage passage = scenario.MakePassage(a.index);
    MapUpdater::Mode mode;
    mode.sequential = updater.joint_next() && !a.joint;
    sequential_instead += mode.sequential;
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, expected, mode);
    ASSERT_TRUE(update.ok()) << update.status();
    expected.Apply(update->delta);
    updater.Applied(passage, update->delta);
  }
  auto map = client->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(map.ok()) << map.status();
  EXPECT_TRUE(MapsMatch(expected, *map, 1e-6, 1e-9));
  EXPECT_EQ(map->version(), expected.version());
  std::printf("soak: acknowledged=%d applied=%d (%d by a sequential update instead of an interrupted joint solve) "
              "failed=%ld quarantined=%ld map_version=%ld landmarks=%ld\n",
              acknowledged, applied, sequential_instead, static_cast<long>(info->passages_failed()),
              static_cast<long>(info->passages_quarantined()), static_cast<long>(map->version()),
              static_cast<long>(info->landmark_count()));
}

TEST(FaultSoak, SigkillsDuringUploadsAndJointSolvesLoseNothingAndApplyNothingTwice) {
  const int passages = EnvInt("CROWDMAP_SOAK_PASSAGES", 20);
  const int kills = EnvInt("CROWDMAP_SOAK_KILLS", 4);
  const int clients = EnvInt("CROWDMAP_SOAK_CLIENTS", 4);
  // Longer passages with more landmarks keep the worker busy (and the joint solves long).
  const Scenario scenario =
      ShortScenario(EnvInt("CROWDMAP_SOAK_LANDMARKS", 10), EnvInt("CROWDMAP_SOAK_PASSAGE_S", 60));
  TempDir dir;
  const std::string db = dir.File("map.db"), log = dir.File("mapd.log");
  auto mapd = std::make_unique<MapdProcess>(db, log, /*port=*/0, ReplayableMapdFlags());
  const int port = mapd->port();
  ASSERT_TRUE(mapd->WaitReady());
  MockVehicle observer(mapd->address());

  std::vector<UploadRecord> records(passages);
  Refusals refusals;
  const auto start = std::chrono::steady_clock::now();
  // Uploads spread over the kills (about 1.1 s apart with the restart).
  Fleet fleet(scenario, mapd->address(), 0, passages, clients, std::max(10, 1100 * kills * clients / passages / 2),
              &refusals, &records);
  std::mt19937 rng(17);
  std::uniform_int_distribution<int> delay_ms(20, 1500);
  int while_processing = 0, during_joint_solve = 0;
  for (int k = 0; k < kills; ++k) {
    bool processing = false, joint = false;
    if (k % 3 != 2) {
      // Aim at a joint solve (every third kill) or at any passage being applied: wait (a while)
      // until one is under way, then a little longer.
      for (int poll = 0; poll < 600; ++poll) {
        auto info = observer.GetMapInfo();
        if (info.ok() && info->passages_processing() > 0 &&
            (k % 3 == 1 || IsJointSolve(info->passages_applied() + 1))) {
          processing = true;
          joint = IsJointSolve(info->passages_applied() + 1);
          std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms(rng) / 10));
          break;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
    }
    if (!joint) {
      std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms(rng)));
      auto info = observer.GetMapInfo();
      processing = info.ok() && info->passages_processing() > 0;
      joint = processing && IsJointSolve(info->passages_applied() + 1);
    }
    while_processing += processing;
    during_joint_solve += joint;
    const int status = mapd->Kill(SIGKILL);
    ASSERT_TRUE(WIFSIGNALED(status));
    mapd = std::make_unique<MapdProcess>(db, log, port, ReplayableMapdFlags());
    ASSERT_TRUE(mapd->WaitReady()) << "restart " << k + 1 << ": " << mapd->last_error() << "; mapd's log ends:\n" << LogTail(log);
  }
  fleet.Join();
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("soak: kills=%d while_processing=%d during_joint_solve=%d passages=%d clients=%d seconds=%.1f "
              "refused_attempts:%s\n",
              kills, while_processing, during_joint_solve, passages, clients, seconds, refusals.Brief().c_str());
  EXPECT_GT(while_processing, 0) << "no kill hit a passage being applied: the test proved little";
  ExpectEveryAcknowledgedPassageAppliedOnce(&observer, scenario, records);
  const int status = mapd->Kill(SIGTERM);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
}

// A tmpfs of a fixed size mounted on a fresh directory, unmounted on destruction.
class SmallFilesystem {
 public:
  explicit SmallFilesystem(int size_mb) {
    const std::string options = absl::StrCat("size=", size_mb, "m");
    mounted_ = mount("tmpfs", dir_.path().c_str(), "tmpfs", 0, options.c_str()) == 0;
    if (!mounted_) error_ = std::strerror(errno);
  }
  ~SmallFilesystem() {
    if (mounted_) umount2(dir_.path().c_str(), MNT_DETACH);
  }
  bool mounted() const { return mounted_; }
  const std::string& error() const { return error_; }
  std::string File(const std::string& name) const { return dir_.File(name); }

  // Writes `path` until the filesystem is full; the bytes written.
  static int64_t Fill(const std::string& path) {
    FILE* f = std::fopen(path.c_str(), "wb");
    if (f == nullptr) return 0;
    std::setvbuf(f, nullptr, _IONBF, 0);
    const std::string block(64 << 10, 'x');
    int64_t written = 0;
    while (true) {
      const size_t n = std::fwrite(block.data(), 1, block.size(), f);
      written += static_cast<int64_t>(n);
      if (n < block.size()) break;
    }
    std::fclose(f);
    return written;
  }

 private:
  TempDir dir_;
  bool mounted_ = false;
  std::string error_;
};

TEST(FaultSoak, AFullDiskRefusesUploadsRetryablyAndLosesNothing) {
  SmallFilesystem disk(64);
  if (!disk.mounted()) {
    GTEST_SKIP() << "cannot mount a size-limited tmpfs here (" << disk.error()
                 << "; needs root or CAP_SYS_ADMIN): the full-disk test did not run";
  }
  const int before = EnvInt("CROWDMAP_SOAK_DISK_PASSAGES_BEFORE", 6);
  const int during = EnvInt("CROWDMAP_SOAK_DISK_PASSAGES", 12);
  const int full_s = EnvInt("CROWDMAP_SOAK_FULL_DISK_S", 3);
  const int clients = EnvInt("CROWDMAP_SOAK_CLIENTS", 4);
  const Scenario scenario = ShortScenario(10, 60.0);
  TempDir logs;
  const std::string db = disk.File("map.db"), filler = disk.File("filler");
  MapdProcess mapd(db, logs.File("mapd.log"), /*port=*/0, ReplayableMapdFlags());
  ASSERT_TRUE(mapd.WaitReady());
  MockVehicle observer(mapd.address());
  std::vector<UploadRecord> records(before + during);
  Refusals before_refusals, refusals;
  Fleet(scenario, mapd.address(), 0, before, clients, 10, &before_refusals, &records).Join();
  ASSERT_TRUE(observer.WaitUntilIdle().ok());

  const int64_t filled = SmallFilesystem::Fill(filler);
  const auto full_since = std::chrono::steady_clock::now();
  // Uploads arrive while the disk is full: spread over the full period.
  Fleet fleet(scenario, mapd.address(), before, before + during, clients, 1000 * full_s * clients / during / 2,
              &refusals, &records);
  std::this_thread::sleep_for(std::chrono::seconds(full_s));
  auto info_full = observer.GetMapInfo();
  std::remove(filler.c_str());
  const double full_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - full_since).count();
  fleet.Join();
  std::printf("soak: disk full for %.1f s (filler %.1f MiB), uploads during it: %d, refused attempts:%s\n",
              full_seconds, filled / 1048576.0, during, refusals.Brief().c_str());
  {
    std::lock_guard<std::mutex> lock(refusals.mu);
    EXPECT_GT(refusals.by_code[grpc::StatusCode::RESOURCE_EXHAUSTED] + refusals.by_code[grpc::StatusCode::UNAVAILABLE],
              0)
        << "no upload was refused: the disk was not full";
    for (const auto& [code, n] : refusals.by_code) {
      EXPECT_TRUE(code == grpc::StatusCode::RESOURCE_EXHAUSTED || code == grpc::StatusCode::UNAVAILABLE)
          << n << " uploads got code " << code << ": " << refusals.example[code];
    }
    EXPECT_EQ(refusals.empty_messages, 0);
  }
  ASSERT_TRUE(info_full.ok());
  EXPECT_EQ(info_full->passages_failed(), 0);
  ExpectEveryAcknowledgedPassageAppliedOnce(&observer, scenario, records);
  const int status = mapd.Kill(SIGTERM);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
}

}  // namespace
}  // namespace crowdmap
