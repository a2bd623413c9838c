// The installed binaries mapctl and mapsim, run as an operator runs them: exit codes (0 success,
// 1 failure, 2 usage error) and $MAPCTL_SERVER.
#include <sys/wait.h>

#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "client/api/map_client.h"
#include "server/testing/temp_dir.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

struct BinaryRun {
  int code = -1;
  std::string out, err;
};

std::string Quoted(const std::string& arg) {
  std::string q = "'";
  for (char c : arg) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

std::string ReadFile(const std::string& path) {
  std::ifstream file(path);
  std::stringstream text;
  text << file.rdbuf();
  return text.str();
}

// Runs `binary args` through the shell with `env` (NAME=value) prepended, MAPCTL_SERVER unset
// unless `env` sets it.
BinaryRun RunBinary(const std::string& binary, const std::vector<std::string>& args, const std::string& env = "") {
  static int runs = 0;
  TempDir dir;
  const std::string out = dir.File(absl::StrCat("out", runs)), err = dir.File(absl::StrCat("err", runs++));
  std::string command = absl::StrCat("env -u MAPCTL_SERVER ", env, " ", Quoted(binary));
  for (const std::string& a : args) absl::StrAppend(&command, " ", Quoted(a));
  absl::StrAppend(&command, " >", Quoted(out), " 2>", Quoted(err));
  const int status = std::system(command.c_str());
  BinaryRun r;
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.out = ReadFile(out);
  r.err = ReadFile(err);
  return r;
}

int Lines(const std::string& text) {
  int n = 0;
  for (char c : text) n += c == '\n';
  return n;
}

TEST(MapsimExitCodes, UsageErrorsExitWithTwoAndOneLine) {
  const std::vector<std::pair<std::vector<std::string>, std::string>> cases = {
      {{"frobnicate"}, "unknown command 'frobnicate'"},
      {{"experiment", "--colour"}, "not expected: --colour"},
      {{"experiment", "extra"}, "not expected: extra"},
      {{"experiment", "--passages"}, "--passages: 1 required"},
      {{"experiment", "--passages", "--quiet"}, "--passages: needs a value"},
      {{"experiment", "--passages", "x"}, "Could not convert: --passages = x"},
      {{"experiment", "--passages", "0"}, "passages: must be >= 1"},
      {{"experiment", "--noise", "pink"}, "unknown 'pink'"},
      {{"experiment", "--strategy", "foo"}, "unknown 'foo'"},
      {{"experiment", "--gnss-noise-scale", "0"}, "gnss-noise-scale: must be > 0"},
      {{"experiment", "--relinearize-until-passages", "64", "--retain-passages", "32"}, "retain_passages: must be 0"},
      {{"city", "--strategy", "foo"}, "unknown 'foo'"},
      {{"city", "--mislabel-rate", "2"}, "mislabel"},
      {{"crlb", "--passages", "0"}, "passages: must be >= 1"},
      {{"pose-bias", "--passages", "-1"}, "passages: must be >= 2"},
      {{"passage-consistency", "--strategy", "dc"}, "strategy: dc"},
      {{"passage-consistency", "--noise", "pink"}, "unknown 'pink'"},
      {{"localize", "--landmarks", "a,b"}, "Could not convert: --landmarks = a,b"},
      {{"reproduce", "--jobs", "two"}, "Could not convert: --jobs = two"},
      {{"reproduce", "--seeds", "0"}, "seeds: must be >= 1"},
      {{"reproduce", "--detections-per-landmark", "2"}, "detections_per_landmark: must be 0 (all) or >= 3"},
      {{"fleet", "--vehicles", "0"}, "vehicles: must be >= 1"},
      {{"fleet", "--route-m", "900"}, "--route-m requires --city"},
      {{"fleet", "--tls-cert", "c.pem"}, "--tls-cert"},
      {{"export-passages", "--format", "xml"}, "--format: xml not in {json,binary}"},
      {{"bench", "--clients", "0"}, "clients >= 1"},
  };
  for (const auto& [args, message] : cases) {
    BinaryRun r = RunBinary(MAPSIM_PATH, args);
    EXPECT_EQ(r.code, 2) << args[0] << " " << args.size() << ": " << r.err;
    EXPECT_EQ(Lines(r.err), 1) << r.err;
    EXPECT_TRUE(absl::StrContains(r.err, message)) << "want '" << message << "' in: " << r.err;
    EXPECT_TRUE(absl::StrContains(r.err, "(see mapsim --help)")) << r.err;
    EXPECT_TRUE(r.out.empty()) << r.out;
  }
  BinaryRun none = RunBinary(MAPSIM_PATH, {});
  EXPECT_EQ(none.code, 2);
  EXPECT_TRUE(none.out.empty());
  EXPECT_TRUE(absl::StrContains(none.err, "Usage:")) << none.err;
  BinaryRun help = RunBinary(MAPSIM_PATH, {"experiment", "--help"});
  EXPECT_EQ(help.code, 0);
  EXPECT_TRUE(absl::StrContains(help.out, "Exit codes: 0 success, 1 failure")) << help.out;
}

TEST(MapsimExitCodes, FailureExitsWithOneAndSuccessWithZero) {
  TempDir dir;
  BinaryRun ok = RunBinary(MAPSIM_PATH, {"export-passages", "--passages", "1", "--landmarks", "6", "--out", dir.File("p")});
  EXPECT_EQ(ok.code, 0) << ok.err;
  EXPECT_TRUE(std::ifstream(dir.File("p/passage-00000.json")).good());
  BinaryRun failed =
      RunBinary(MAPSIM_PATH, {"export-passages", "--passages", "1", "--out", dir.File("p/passage-00000.json/sub")});
  EXPECT_EQ(failed.code, 1) << failed.err;
  EXPECT_EQ(Lines(failed.err), 1) << failed.err;
  BinaryRun unreachable = RunBinary(MAPSIM_PATH, {"fleet", "--server", "127.0.0.1:1", "--passages", "1", "--quiet"});
  EXPECT_EQ(unreachable.code, 1) << unreachable.err;
}

TEST(MapctlExitCodes, TheBinaryExitsWithTheDocumentedCodes) {
  EXPECT_EQ(RunBinary(MAPCTL_PATH, {"frobnicate"}).code, 2);
  EXPECT_EQ(RunBinary(MAPCTL_PATH, {"region", "--bbox", "0,0,1"}).code, 2);
  EXPECT_EQ(RunBinary(MAPCTL_PATH, {"info", "--server", "127.0.0.1:1"}).code, 1);
  BinaryRun tile = RunBinary(MAPCTL_PATH, {"tile", "--at", "0.5,0.5"});
  EXPECT_EQ(tile.code, 0) << tile.err;
  EXPECT_EQ(tile.out, "16 32859 32676\n");
}

TEST(MapctlServer, ReadsMapctlServerAndTheFlagWins) {
  BinaryRun env = RunBinary(MAPCTL_PATH, {"info"}, "MAPCTL_SERVER=127.0.0.1:1");
  EXPECT_EQ(env.code, 1);
  EXPECT_TRUE(absl::StrContains(env.err, "127.0.0.1:1")) << env.err;
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  BinaryRun r = RunBinary(MAPCTL_PATH, {"info", "--json"}, "MAPCTL_SERVER=" + server->address());
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(absl::StrContains(r.out, "\"landmark_count\": \"0\"")) << r.out;
  BinaryRun flagged = RunBinary(MAPCTL_PATH, {"info", "--server", server->address()}, "MAPCTL_SERVER=127.0.0.1:1");
  EXPECT_EQ(flagged.code, 0) << flagged.err;
  // The token file named by the environment is read like --token-file's.
  BinaryRun token = RunBinary(MAPCTL_PATH, {"info", "--server", server->address()},
                              "CROWDMAP_TOKEN_FILE=" + dir.File("no-such-token"));
  EXPECT_EQ(token.code, 2) << token.err;
  EXPECT_TRUE(absl::StrContains(token.err, "--token-file: cannot read")) << token.err;
}

TEST(MapsimServer, FleetReadsMapctlServerLikeMapctl) {
  BinaryRun env = RunBinary(MAPSIM_PATH, {"fleet", "--passages", "1", "--quiet"}, "MAPCTL_SERVER=127.0.0.1:1");
  EXPECT_EQ(env.code, 1);
  EXPECT_TRUE(absl::StrContains(env.err, "127.0.0.1:1")) << env.err;
  BinaryRun bench = RunBinary(MAPSIM_PATH, {"bench", "--passages", "1", "--clients", "1"}, "MAPCTL_SERVER=127.0.0.1:1");
  EXPECT_EQ(bench.code, 1);
  EXPECT_TRUE(absl::StrContains(bench.err, "127.0.0.1:1")) << bench.err;

  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  const std::vector<std::string> fleet = {"fleet",  "--passages", "2",          "--vehicles", "1",
                                          "--landmarks", "6", "--no-replay", "--quiet", "--out", dir.File("fleet")};
  BinaryRun r = RunBinary(MAPSIM_PATH, fleet, "MAPCTL_SERVER=" + server->address());
  ASSERT_EQ(r.code, 0) << r.err;
  // --server wins over the environment.
  std::vector<std::string> flagged = fleet;
  flagged.insert(flagged.end(), {"--server", server->address()});
  BinaryRun f = RunBinary(MAPSIM_PATH, flagged, "MAPCTL_SERVER=127.0.0.1:1");
  ASSERT_EQ(f.code, 0) << f.err;
  MapClientOptions options;
  options.server = server->address();
  auto client = MapClient::Create(options);
  ASSERT_TRUE(client.ok());
  auto info = (*client)->GetMapInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), 2);  // the second run's passages are duplicates of the first's
}

}  // namespace
}  // namespace crowdmap
