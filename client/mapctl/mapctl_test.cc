// mapctl against a real in-process mapd on an ephemeral port with a temporary database.
#include "client/mapctl/mapctl.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <fstream>
#include <thread>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_split.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "client/api/map_client.h"
#include "client/api/passage_files.h"
#include "client/mapsim/fleet.h"
#include "core/geo/tiles.h"
#include "server/testing/temp_dir.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

struct CliRun {
  int code = 0;
  std::string out, err;
};

CliRun Mapctl(std::vector<std::string> args, const std::string& server) {
  if (!server.empty()) {
    args.push_back("--server");
    args.push_back(server);
  }
  std::ostringstream out, err;
  CliRun r;
  r.code = RunMapctl(args, out, err);
  r.out = out.str();
  r.err = err.str();
  return r;
}

int Count(const std::string& text, const std::string& needle) {
  int n = 0;
  for (size_t p = text.find(needle); p != std::string::npos; p = text.find(needle, p + 1)) ++n;
  return n;
}

bool OneErrorLine(const CliRun& r) { return r.code != 0 && Count(r.err, "\n") == 1 && r.out.empty(); }

class MapctlTest : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = StartTestServer(TestServerOptions(dir_.File("map.db")));
    ASSERT_NE(server_, nullptr);
    address_ = server_->address();
    scenario_ = ShortScenario().options();
  }

  // Writes `passages` simulated passage files, uploads them with mapctl and waits until applied.
  void UploadAndApply(int passages) {
    ASSERT_TRUE(ExportPassages(scenario_, passages, /*binary=*/false, dir_.File("json")).ok());
    ASSERT_TRUE(ExportPassages(scenario_, passages, /*binary=*/true, dir_.File("pb")).ok());
    std::vector<std::string> args = {"upload", dir_.File("json/passage-00000.json")};
    for (int i = 1; i < passages; ++i) args.push_back(dir_.File(absl::StrFormat("pb/passage-%05d.pb", i)));
    CliRun r = Mapctl(args, address_);
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_EQ(Count(r.out, "queued"), passages) << r.out;
    MapClientOptions options;
    options.server = address_;
    auto client = MapClient::Create(options);
    ASSERT_TRUE(client.ok());
    auto info = (*client)->WaitUntilIdle(std::chrono::seconds(60));
    ASSERT_TRUE(info.ok()) << info.status();
    ASSERT_EQ(info->passages_applied(), passages);
  }

  std::string RouteBbox() const {
    return absl::StrFormat("%.6f,%.6f,%.6f,%.6f", scenario_.origin.lon_deg - 0.05, scenario_.origin.lat_deg - 0.05,
                           scenario_.origin.lon_deg + 0.05, scenario_.origin.lat_deg + 0.05);
  }

  TempDir dir_;
  std::unique_ptr<MapServer> server_;
  std::string address_;
  ScenarioOptions scenario_;
};

TEST_F(MapctlTest, InfoShowsTheEmptyMapAndItsStrategy) {
  CliRun r = Mapctl({"info"}, address_);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(absl::StrContains(r.out, "landmarks:         0")) << r.out;
  EXPECT_TRUE(absl::StrContains(r.out, "cc-gsd (warm-up 8 passages, re-solved at each doubling up to 128, subgraph dim 500")) << r.out;
  EXPECT_TRUE(absl::StrContains(r.out, "detections: the last 5)")) << r.out;
  EXPECT_TRUE(absl::StrContains(r.out, "re-linearisation:  off")) << r.out;  // the test server's setting
  CliRun j = Mapctl({"info", "--json"}, address_);
  ASSERT_EQ(j.code, 0) << j.err;
  EXPECT_TRUE(absl::StrContains(j.out, "\"strategy\": \"cc-gsd\"")) << j.out;
  EXPECT_TRUE(absl::StrContains(j.out, "\"warmup_passages\": 8")) << j.out;
  EXPECT_TRUE(absl::StrContains(j.out, "\"relinearize_until_passages\": 128")) << j.out;
  // Zero-valued fields are printed, not left out (int64 prints as a JSON string).
  EXPECT_TRUE(absl::StrContains(j.out, "\"landmark_count\": \"0\"")) << j.out;
  EXPECT_TRUE(absl::StrContains(j.out, "\"map_version\": \"0\"")) << j.out;
  EXPECT_TRUE(absl::StrContains(j.out, "\"passages_failed\": \"0\"")) << j.out;
}

// The same drive saved again under another passage id is refused; the files after it are still
// sent, and the exit code says that one was refused.
TEST_F(MapctlTest, AFileRefusedForItsContentDoesNotStopTheOthers) {
  ASSERT_TRUE(ExportPassages(scenario_, 2, /*binary=*/true, dir_.File("pb")).ok());
  absl::StatusOr<pb::Passage> copy = ReadPassageFile(dir_.File("pb/passage-00000.pb"));
  ASSERT_TRUE(copy.ok()) << copy.status();
  copy->set_passage_id("saved-again");
  {
    std::ofstream out(dir_.File("copy.pb"), std::ios::binary);
    out << copy->SerializeAsString();
  }
  CliRun r = Mapctl({"upload", dir_.File("pb/passage-00000.pb"), dir_.File("copy.pb"), dir_.File("pb/passage-00001.pb")},
                    address_);
  EXPECT_EQ(r.code, 1) << r.err;
  EXPECT_EQ(Count(r.out, "queued"), 2) << r.out;
  EXPECT_TRUE(absl::StrContains(r.err, "copy.pb")) << r.err;
  EXPECT_TRUE(absl::StrContains(r.err, "ALREADY_EXISTS")) << r.err;
  EXPECT_TRUE(absl::StrContains(r.err, "1 of 3 files refused")) << r.err;
}

TEST_F(MapctlTest, UploadedFilesAreAppliedAndListed) {
  UploadAndApply(3);
  CliRun again = Mapctl({"upload", dir_.File("json/passage-00000.json")}, address_);
  ASSERT_EQ(again.code, 0) << again.err;
  EXPECT_TRUE(absl::StrContains(again.out, "yes")) << again.out;  // duplicate

  CliRun applied = Mapctl({"passages", "--state", "applied"}, address_);
  ASSERT_EQ(applied.code, 0) << applied.err;
  EXPECT_TRUE(absl::StrContains(applied.out, "3 passages")) << applied.out;
  CliRun queued = Mapctl({"passages", "--state", "queued", "--json"}, address_);
  ASSERT_EQ(queued.code, 0) << queued.err;
  EXPECT_FALSE(absl::StrContains(queued.out, "passage_id")) << queued.out;

  CliRun by_id = Mapctl({"status", "1"}, address_);
  ASSERT_EQ(by_id.code, 0) << by_id.err;
  EXPECT_TRUE(absl::StrContains(by_id.out, "state:       applied")) << by_id.out;
  EXPECT_TRUE(absl::StrContains(by_id.out, "strategy=cc-gsd")) << by_id.out;
  const Passage third = Scenario::Create(scenario_)->MakePassage(2);
  CliRun by_key = Mapctl({"status", third.vehicle_id + "/" + third.passage_id, "--json"}, address_);
  ASSERT_EQ(by_key.code, 0) << by_key.err;
  EXPECT_TRUE(absl::StrContains(by_key.out, "\"PASSAGE_STATE_APPLIED\"")) << by_key.out;
}

TEST_F(MapctlTest, ExcludeTakesAnAppliedPassageOutOfTheMap) {
  UploadAndApply(3);
  const Passage second = Scenario::Create(scenario_)->MakePassage(1);
  CliRun r = Mapctl({"exclude", second.vehicle_id + "/" + second.passage_id}, address_);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(absl::StrContains(r.out, "passage 2 (" + second.vehicle_id + "/" + second.passage_id + ") excluded"))
      << r.out;
  CliRun status = Mapctl({"status", "2"}, address_);
  EXPECT_TRUE(absl::StrContains(status.out, "state:       excluded")) << status.out;
  CliRun listed = Mapctl({"passages", "--state", "excluded"}, address_);
  EXPECT_TRUE(absl::StrContains(listed.out, "1 passages")) << listed.out;
  CliRun again = Mapctl({"exclude", "2"}, address_);
  EXPECT_TRUE(OneErrorLine(again)) << again.err;
  EXPECT_TRUE(absl::StrContains(again.err, "only an applied passage can be excluded")) << again.err;
  CliRun landmark = Mapctl({"landmark", "1"}, address_);
  ASSERT_EQ(landmark.code, 0) << landmark.err;
  EXPECT_TRUE(absl::StrContains(landmark.out, "shaped by:   2 passages")) << landmark.out;
  EXPECT_FALSE(absl::StrContains(landmark.out, second.passage_id)) << landmark.out;
  CliRun usage = Mapctl({"exclude"}, address_);
  EXPECT_TRUE(OneErrorLine(usage)) << usage.err;
}

TEST_F(MapctlTest, MapReadsShowEveryLandmark) {
  UploadAndApply(2);
  const int landmarks = scenario_.landmarks;
  CliRun region = Mapctl({"region", "--bbox", RouteBbox()}, address_);
  ASSERT_EQ(region.code, 0) << region.err;
  EXPECT_TRUE(absl::StrContains(region.out, absl::StrCat(landmarks, " landmarks"))) << region.out;

  CliRun json = Mapctl({"region", "--bbox", RouteBbox(), "--json"}, address_);
  ASSERT_EQ(json.code, 0) << json.err;
  EXPECT_EQ(Count(json.out, "\"cov_en_m2\""), landmarks);

  CliRun geo = Mapctl({"export", "--bbox", RouteBbox(), "--format", "geojson", "--ellipses"}, address_);
  ASSERT_EQ(geo.code, 0) << geo.err;
  EXPECT_TRUE(absl::StartsWith(geo.out, "{\"type\":\"FeatureCollection\"")) << geo.out.substr(0, 80);
  EXPECT_EQ(Count(geo.out, "\"Point\""), landmarks);
  EXPECT_EQ(Count(geo.out, "\"Polygon\""), landmarks);
  CliRun to_file = Mapctl({"export", "--bbox", RouteBbox(), "--out", dir_.File("map.geojson")}, address_);
  ASSERT_EQ(to_file.code, 0) << to_file.err;
  std::ifstream file(dir_.File("map.geojson"));
  std::stringstream written;
  written << file.rdbuf();
  EXPECT_EQ(Count(written.str(), "\"Point\""), landmarks);
  EXPECT_EQ(Count(written.str(), "\"Polygon\""), 0);

  auto scenario = Scenario::Create(scenario_);
  ASSERT_TRUE(scenario.ok());
  const TileId tile = TileContaining(scenario->landmarks()[0].position);
  CliRun t = Mapctl({"tile", std::to_string(tile.z), std::to_string(tile.x), std::to_string(tile.y)}, address_);
  ASSERT_EQ(t.code, 0) << t.err;
  EXPECT_TRUE(absl::StrContains(t.out, absl::StrFormat("tile %d/%d/%d", tile.z, tile.x, tile.y))) << t.out;
  EXPECT_FALSE(absl::StrContains(t.out, " 0 landmarks")) << t.out;
}

TEST_F(MapctlTest, WatchPrintsChangesSinceAVersion) {
  UploadAndApply(1);
  CliRun w = Mapctl({"watch", "--bbox", RouteBbox(), "--since", "0", "--updates", "1", "--seconds", "20"}, address_);
  ASSERT_EQ(w.code, 0) << w.err;
  EXPECT_TRUE(absl::StrContains(w.out, "\n  landmark ")) << w.out;
  CliRun info = Mapctl({"info", "--json"}, address_);
  ASSERT_TRUE(absl::StrContains(info.out, "\"map_version\": \"1\"")) << info.out;  // the one passage
  CliRun quiet = Mapctl({"watch", "--bbox", RouteBbox(), "--since", "1", "--seconds", "0.3"}, address_);
  ASSERT_EQ(quiet.code, 0) << quiet.err;
  EXPECT_FALSE(absl::StrContains(quiet.out, "\n  landmark ")) << quiet.out;
  // A version the map has not reached: refused once the server has waited for it (2 s).
  CliRun ahead = Mapctl({"watch", "--bbox", RouteBbox(), "--since", "1000000", "--seconds", "10"}, address_);
  EXPECT_EQ(ahead.code, 1);
  EXPECT_TRUE(absl::StrContains(ahead.err, "FAILED_PRECONDITION")) << ahead.err;
  // The only passage excluded: its landmarks are removed, and a watch says so.
  ASSERT_EQ(Mapctl({"exclude", "1"}, address_).code, 0);
  CliRun removed = Mapctl({"watch", "--bbox", RouteBbox(), "--since", "1", "--updates", "1", "--seconds", "20"},
                          address_);
  ASSERT_EQ(removed.code, 0) << removed.err;
  EXPECT_TRUE(absl::StrContains(removed.out, absl::StrCat("0 landmarks changed, ", scenario_.landmarks, " removed")))
      << removed.out;
  EXPECT_EQ(Count(removed.out, " removed\n"), scenario_.landmarks + 1) << removed.out;
}

TEST_F(MapctlTest, BadInputGivesOneLineAndNonZeroExit) {
  CliRun unknown_id = Mapctl({"status", "4242"}, address_);
  EXPECT_TRUE(OneErrorLine(unknown_id)) << unknown_id.err;
  EXPECT_TRUE(absl::StrContains(unknown_id.err, "NOT_FOUND")) << unknown_id.err;

  {
    std::ofstream bad(dir_.File("bad.json"));
    bad << "{\"vehicle_id\": \"v\", \"odometry\": [ {\"t_s\": \"oops\"} ]";
  }
  CliRun malformed = Mapctl({"upload", dir_.File("bad.json")}, address_);
  EXPECT_TRUE(OneErrorLine(malformed)) << malformed.err;
  EXPECT_TRUE(absl::StrContains(malformed.err, "bad.json")) << malformed.err;
  {
    std::ofstream junk(dir_.File("junk.pb"), std::ios::binary);
    junk << "\xff\xff\xff\xff not a passage";
  }
  CliRun binary = Mapctl({"upload", dir_.File("junk.pb")}, address_);
  EXPECT_TRUE(OneErrorLine(binary)) << binary.err;
  CliRun missing = Mapctl({"upload", dir_.File("nowhere.json")}, address_);
  EXPECT_TRUE(OneErrorLine(missing)) << missing.err;

  for (const CliRun& failed : {unknown_id, malformed, binary, missing}) EXPECT_EQ(failed.code, 1) << failed.err;

  CliRun bbox = Mapctl({"region", "--bbox", "1,2,3"}, address_);
  EXPECT_TRUE(OneErrorLine(bbox)) << bbox.err;
  EXPECT_EQ(bbox.code, 2);
  CliRun state = Mapctl({"passages", "--state", "sleeping"}, address_);
  EXPECT_TRUE(OneErrorLine(state)) << state.err;
  EXPECT_EQ(state.code, 2);
  // The server refuses the zoom: a failed call, not a usage error.
  CliRun tile = Mapctl({"tile", "3", "1", "1"}, address_);
  EXPECT_TRUE(OneErrorLine(tile)) << tile.err;
  EXPECT_TRUE(absl::StrContains(tile.err, "INVALID_ARGUMENT")) << tile.err;
  EXPECT_EQ(tile.code, 1);

  CliRun command = Mapctl({"frobnicate"}, address_);
  EXPECT_EQ(command.code, 2);
  CliRun flag = Mapctl({"info", "--colour"}, address_);
  EXPECT_EQ(flag.code, 2);
}

TEST(Mapctl, UnreachableServerGivesOneLineAndNonZeroExit) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  const std::string address = server->address();
  server->Shutdown();
  server.reset();
  for (const std::vector<std::string>& args :
       {std::vector<std::string>{"info"}, {"passages"}, {"status", "1"}, {"tile", "16", "1", "1"},
        {"region", "--bbox", "0,0,1,1"}, {"export", "--bbox", "0,0,1,1"}, {"watch", "--bbox", "0,0,1,1", "--seconds", "1"}}) {
    CliRun r = Mapctl(args, address);
    EXPECT_TRUE(OneErrorLine(r)) << args[0] << ": " << r.err;
    EXPECT_EQ(r.code, 1) << args[0] << ": " << r.err;
    EXPECT_TRUE(absl::StrContains(r.err, "UNAVAILABLE")) << args[0] << ": " << r.err;
  }
}

// Every usage error exits with 2 and one line naming the problem, before any call: the server
// here is unreachable, so a call would exit with 1.
TEST(Mapctl, UsageErrorsExitWithTwoBeforeAnyCall) {
  const std::string nowhere = "127.0.0.1:1";
  const std::vector<std::pair<std::vector<std::string>, std::string>> cases = {
      {{"frobnicate"}, "unknown command"},
      {{"info", "--colour"}, "not expected: --colour"},
      {{"info", "extra"}, "not expected: extra"},
      {{"region", "--bbox"}, "--bbox: needs a value"},  // the next argument is --server
      {{"region"}, "--bbox is required"},
      {{"region", "--bbox", "0,0,x,1"}, "'x' is not a number"},
      {{"region", "--bbox", "0,0,200,100"}, "--bbox: '0,0,200,100' cannot be a box"},
      {{"region", "--bbox", "2,0,1,1"}, "--bbox: need MINLON <= MAXLON"},
      {{"watch", "--bbox", "0,0,1,1", "--seconds", "soon"}, "--seconds: expected a number"},
      {{"watch", "--bbox", "0,0,1,1", "--since", "1.5"}, "Could not convert: --since = 1.5"},
      {{"watch", "--bbox", "0,0,1,1", "--since", "-1"}, "--since: must be >= 0"},
      {{"info", "--deadline-s", "-1"}, "--deadline-s"},
      {{"status"}, "give one ID"},
      {{"status", "abc"}, "neither a number nor VEHICLE/PASSAGE_ID"},
      {{"landmark", "x"}, "give one landmark id"},
      {{"upload"}, "give at least one passage file"},
      {{"passages", "--state", "sleeping"}, "--state: 'sleeping'"},
      {{"tile", "16", "1"}, "give Z X Y or --at LAT,LON"},
      {{"tile", "--at", "48.1"}, "--at: '48.1' is not LAT,LON"},
      {{"tile", "--at", "89,11"}, "--at: need |LAT| <= 85.0511"},
      {{"export", "--bbox", "0,0,1,1", "--format", "kml"}, "--format: kml not in {geojson}"},
      {{"localize", "x.json", "--format", "kml"}, "--format: kml not in {csv,geojson}"},
  };
  for (const auto& [args, message] : cases) {
    CliRun r = Mapctl(args, nowhere);
    EXPECT_EQ(r.code, 2) << args[0] << ": " << r.err;
    EXPECT_TRUE(OneErrorLine(r)) << args[0] << ": " << r.err;
    EXPECT_TRUE(absl::StrContains(r.err, message)) << r.err;
    EXPECT_FALSE(absl::StrContains(r.err, "UNAVAILABLE")) << r.err;
  }
  CliRun none = Mapctl({}, "");
  EXPECT_EQ(none.code, 2);
  EXPECT_TRUE(absl::StrContains(none.err, "Usage:")) << none.err;
  CliRun help = Mapctl({"region", "--help"}, "");
  EXPECT_EQ(help.code, 0);
  EXPECT_TRUE(absl::StrContains(help.out, "Exit codes: 0 success, 1 failure")) << help.out;
}

TEST(Mapctl, TileAtPrintsTheStorageTileOfAPoint) {
  const LatLon munich{48.137154, 11.576124};
  const TileId expected = TileContaining(munich, kStorageZoom);
  CliRun r = Mapctl({"tile", "--at", "48.137154,11.576124"}, "127.0.0.1:1");  // no call is made
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out, absl::StrFormat("16 %d %d\n", expected.x, expected.y));
  EXPECT_EQ(expected.x, 34875);  // OpenStreetMap's z16 tile of Munich's Marienplatz
  EXPECT_EQ(expected.y, 22743);
  CliRun json = Mapctl({"tile", "--at=48.137154,11.576124", "--json"}, "127.0.0.1:1");
  ASSERT_EQ(json.code, 0) << json.err;
  EXPECT_EQ(json.out, absl::StrFormat("{\n  \"z\": 16,\n  \"x\": %d,\n  \"y\": %d\n}\n", expected.x, expected.y));
  CliRun south_west = Mapctl({"tile", "--at", "-33.8568,151.2153"}, "127.0.0.1:1");
  ASSERT_EQ(south_west.code, 0) << south_west.err;
  EXPECT_EQ(south_west.out, "16 60295 39325\n");
}

TEST_F(MapctlTest, TileAtNamesTheTileThatHoldsALandmark) {
  UploadAndApply(1);
  auto scenario = Scenario::Create(scenario_);
  ASSERT_TRUE(scenario.ok());
  const LatLon p = scenario->landmarks()[0].position;
  CliRun at = Mapctl({"tile", "--at", absl::StrFormat("%.9f,%.9f", p.lat_deg, p.lon_deg)}, address_);
  ASSERT_EQ(at.code, 0) << at.err;
  std::vector<std::string> zxy = absl::StrSplit(absl::StripAsciiWhitespace(at.out), ' ');
  ASSERT_EQ(zxy.size(), 3u) << at.out;
  CliRun tile = Mapctl({"tile", zxy[0], zxy[1], zxy[2], "--json"}, address_);
  ASSERT_EQ(tile.code, 0) << tile.err;
  EXPECT_TRUE(absl::StrContains(tile.out, absl::StrCat("\"id\": \"", scenario->landmarks()[0].id, "\""))) << tile.out;
}

TEST_F(MapctlTest, SwappedBboxIsReadSwappedWithAWarning) {
  // West of -90 degrees a box written MINLAT,MINLON,MAXLAT,MAXLON has "latitudes" beyond -90.
  scenario_.origin = LatLon{37.7749, -122.4194};
  UploadAndApply(1);
  const double lat = scenario_.origin.lat_deg, lon = scenario_.origin.lon_deg;
  CliRun right = Mapctl({"region", "--bbox", RouteBbox()}, address_);
  ASSERT_EQ(right.code, 0) << right.err;
  EXPECT_TRUE(right.err.empty()) << right.err;
  EXPECT_TRUE(absl::StrContains(right.out, absl::StrCat(scenario_.landmarks, " landmarks"))) << right.out;

  const std::string swapped =
      absl::StrFormat("%.6f,%.6f,%.6f,%.6f", lat - 0.05, lon - 0.05, lat + 0.05, lon + 0.05);
  CliRun r = Mapctl({"region", "--bbox", swapped}, address_);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(Count(r.err, "\n"), 1) << r.err;
  EXPECT_TRUE(absl::StrContains(r.err, "mapctl region: warning: --bbox")) << r.err;
  EXPECT_TRUE(absl::StrContains(r.err, "swapped")) << r.err;
  EXPECT_EQ(r.out, right.out);

  // Swapped or not, latitudes beyond 90 cannot make a box.
  CliRun neither = Mapctl({"region", "--bbox", "-122.5,95,-122.3,97"}, address_);
  EXPECT_EQ(neither.code, 2);
  EXPECT_TRUE(OneErrorLine(neither)) << neither.err;
  EXPECT_TRUE(absl::StrContains(neither.err, "--bbox")) << neither.err;
}

// Every row of the table has its columns where the header has them, whatever the ids' length.
TEST_F(MapctlTest, TablesKeepTheirColumnsWithLongIds) {
  ASSERT_TRUE(ExportPassages(scenario_, 2, /*binary=*/false, dir_.File("json")).ok());
  const std::string long_vehicle(100, 'v');
  const std::string long_passage = "passage-" + std::string(110, 'p');
  std::vector<std::string> files;
  for (int i = 0; i < 2; ++i) {
    std::ifstream in(dir_.File(absl::StrFormat("json/passage-%05d.json", i)));
    std::stringstream text;
    text << in.rdbuf();
    std::string json = text.str();
    const Passage original = Scenario::Create(scenario_)->MakePassage(i);
    json = absl::StrReplaceAll(json, {{"\"" + original.vehicle_id + "\"", "\"" + long_vehicle + "\""}});
    if (i == 1) json = absl::StrReplaceAll(json, {{"\"" + original.passage_id + "\"", "\"" + long_passage + "\""}});
    files.push_back(dir_.File(absl::StrFormat("long-%d-%s.json", i, std::string(40, 'f'))));
    std::ofstream(files.back()) << json;
  }
  CliRun upload = Mapctl({"upload", files[0], files[1]}, address_);
  ASSERT_EQ(upload.code, 0) << upload.err;
  CliRun list = Mapctl({"passages"}, address_);
  ASSERT_EQ(list.code, 0) << list.err;
  for (const CliRun* table : {&upload, &list}) {
    std::vector<std::string> lines = absl::StrSplit(table->out, '\n', absl::SkipEmpty());
    ASSERT_GE(lines.size(), 3u) << table->out;
    // The column after PASSAGE starts at the same character in the header and both rows.
    const size_t state_column = lines[0].find("STATE");
    ASSERT_NE(state_column, std::string::npos) << lines[0];
    for (size_t k = 1; k < 3; ++k) {
      EXPECT_NE(lines[k].find("\u2026"), std::string::npos) << lines[k];
      EXPECT_FALSE(absl::StrContains(lines[k], long_vehicle)) << lines[k];
      // Count characters (code points), not bytes: the ellipsis is 3 bytes.
      size_t chars = 0, byte = 0;
      for (; byte < lines[k].size() && chars < state_column; ++byte) {
        if ((static_cast<unsigned char>(lines[k][byte]) & 0xc0) != 0x80) ++chars;
      }
      while (byte < lines[k].size() && (static_cast<unsigned char>(lines[k][byte]) & 0xc0) == 0x80) ++byte;
      EXPECT_TRUE(absl::StartsWith(lines[k].substr(byte), "queued") ||
                  absl::StartsWith(lines[k].substr(byte), "processing") ||
                  absl::StartsWith(lines[k].substr(byte), "applied"))
          << "\n" << lines[0] << "\n" << lines[k];
    }
  }
  // The detail view shows the whole id.
  CliRun status = Mapctl({"status", "2"}, address_);
  ASSERT_EQ(status.code, 0) << status.err;
  EXPECT_TRUE(absl::StrContains(status.out, long_passage)) << status.out;
}

TEST_F(MapctlTest, WatchReconnectsFromItsLastVersionWhenTheServerRestarts) {
  UploadAndApply(1);
  MapClientOptions client_options;
  client_options.server = address_;
  auto client = MapClient::Create(client_options);
  ASSERT_TRUE(client.ok());
  const int64_t first_version = (*client)->GetMapInfo()->map_version();
  ASSERT_GT(first_version, 0);

  // The watch runs a fixed time: whether it reconnects before or after the next upload lands, it
  // must print the first passage's changes once and the next passage's changes once.
  CliRun w;
  std::thread watch([&] {
    w = Mapctl({"watch", "--bbox", RouteBbox(), "--since", "0", "--seconds", "6", "--deadline-s", "20"}, address_);
  });
  // Give the watch its first answer before the restart, so that it has a version to resume from.
  std::this_thread::sleep_for(std::chrono::milliseconds(1000));
  server_->Shutdown();
  server_.reset();
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  MapServerOptions again = TestServerOptions(dir_.File("map.db"));
  again.listen = address_;
  server_ = StartTestServer(again);
  ASSERT_NE(server_, nullptr);
  // The second passage of the scenario, uploaded to the restarted server.
  ASSERT_TRUE(ExportPassages(scenario_, 2, /*binary=*/false, dir_.File("more")).ok());
  CliRun upload = Mapctl({"upload", dir_.File("more/passage-00001.json")}, address_);
  ASSERT_EQ(upload.code, 0) << upload.err;
  watch.join();

  ASSERT_EQ(w.code, 0) << w.err;
  // One line per lost connection, each resuming from the version it had: usually one (UNAVAILABLE),
  // more when a reconnection reached the old server while it was still shutting down (UNAVAILABLE
  // again, or its stream CANCELLED by the shutdown).
  EXPECT_GE(Count(w.err, "\n"), 1) << w.err;
  for (absl::string_view line : absl::StrSplit(w.err, '\n', absl::SkipEmpty())) {
    EXPECT_TRUE(absl::StartsWith(line, "mapctl watch: connection lost (")) << line;
    EXPECT_TRUE(absl::EndsWith(line, absl::StrCat("reconnecting from map version ", first_version))) << line;
  }
  std::vector<std::string> with_changes;
  for (absl::string_view line : absl::StrSplit(w.out, '\n')) {
    if (absl::StartsWith(line, "map version ") && !absl::StrContains(line, ": 0 landmarks")) {
      with_changes.emplace_back(line);
    }
  }
  ASSERT_EQ(with_changes.size(), 2u) << w.out;
  EXPECT_TRUE(absl::StartsWith(with_changes[0], absl::StrCat("map version ", first_version, ": "))) << w.out;
  EXPECT_TRUE(absl::StartsWith(with_changes[1], absl::StrCat("map version ", first_version + 1, ": "))) << w.out;
}

// A server that accepts the connection but never answers: the watch gives up after --deadline-s.
TEST(Mapctl, WatchHonoursTheDeadlineForItsFirstAnswer) {
  const int listener = socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(listener, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(bind(listener, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)), 0);
  ASSERT_EQ(listen(listener, 4), 0);
  socklen_t len = sizeof(addr);
  ASSERT_EQ(getsockname(listener, reinterpret_cast<sockaddr*>(&addr), &len), 0);
  const std::string address = absl::StrCat("127.0.0.1:", ntohs(addr.sin_port));
  const auto start = std::chrono::steady_clock::now();
  CliRun r = Mapctl({"watch", "--bbox", "0,0,1,1", "--deadline-s", "0.5"}, address);
  const double elapsed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  close(listener);
  EXPECT_EQ(r.code, 1) << r.err;
  EXPECT_TRUE(OneErrorLine(r)) << r.err;
  EXPECT_TRUE(absl::StrContains(r.err, "DEADLINE_EXCEEDED")) << r.err;
  EXPECT_GE(elapsed_s, 0.4);
  EXPECT_LT(elapsed_s, 5.0);
}

TEST_F(MapctlTest, LocalizeWritesCsvAndGeoJson) {
  UploadAndApply(3);
  const std::string file = dir_.File("json/passage-00001.json");
  CliRun csv = Mapctl({"localize", file}, address_);
  ASSERT_EQ(csv.code, 0) << csv.err;
  EXPECT_TRUE(absl::StartsWith(csv.out, "t_s,lat_deg,lon_deg,heading_rad,cov_ee,")) << csv.out.substr(0, 80);
  EXPECT_GT(Count(csv.out, "\n"), 40);
  CliRun geo = Mapctl({"localize", file, "--format", "geojson", "--out", dir_.File("track.geojson")}, address_);
  ASSERT_EQ(geo.code, 0) << geo.err;
  EXPECT_TRUE(absl::StrContains(geo.out, "landmarks used")) << geo.out;
  std::ifstream written(dir_.File("track.geojson"));
  std::stringstream text;
  text << written.rdbuf();
  EXPECT_EQ(Count(text.str(), "\"LineString\""), 1);
  EXPECT_GT(Count(text.str(), "\"Point\""), 40);
  CliRun bad = Mapctl({"localize", file, "--format", "kml"}, address_);
  EXPECT_NE(bad.code, 0);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

TEST(Mapctl, VehiclesPrintsEachVehiclesEstimatedCameraYaw) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.worker.update.estimate_camera_yaw = true;
  std::unique_ptr<MapServer> server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  ScenarioOptions scenario = ShortScenario().options();
  scenario.vehicles = 2;
  ASSERT_TRUE(ExportPassages(scenario, 3, /*binary=*/true, dir.File("pb")).ok());
  CliRun upload = Mapctl({"upload", dir.File("pb/passage-00000.pb"), dir.File("pb/passage-00001.pb"),
                          dir.File("pb/passage-00002.pb")},
                         server->address());
  ASSERT_EQ(upload.code, 0) << upload.err;
  MapClientOptions client_options;
  client_options.server = server->address();
  auto client = MapClient::Create(client_options);
  ASSERT_TRUE(client.ok());
  ASSERT_TRUE((*client)->WaitUntilIdle(std::chrono::seconds(60)).ok());

  CliRun all = Mapctl({"vehicles"}, server->address());
  ASSERT_EQ(all.code, 0) << all.err;
  EXPECT_TRUE(absl::StrContains(all.out, "2 vehicles")) << all.out;
  EXPECT_TRUE(absl::StrContains(all.out, "sim-v0: camera yaw ")) << all.out;
  EXPECT_TRUE(absl::StrContains(all.out, "° after 2 passages")) << all.out;
  EXPECT_TRUE(absl::StrContains(all.out, "sim-v1: camera yaw ")) << all.out;
  EXPECT_TRUE(absl::StrContains(all.out, "° after 1 passage\n")) << all.out;
  CliRun one = Mapctl({"vehicles", "sim-v1"}, server->address());
  ASSERT_EQ(one.code, 0) << one.err;
  EXPECT_TRUE(absl::StartsWith(one.out, "sim-v1: camera yaw ")) << one.out;
  EXPECT_TRUE(absl::StrContains(one.out, " ± ")) << one.out;
  CliRun json = Mapctl({"vehicles", "sim-v0", "--json"}, server->address());
  ASSERT_EQ(json.code, 0) << json.err;
  EXPECT_TRUE(absl::StrContains(json.out, "\"camera_yaw_sigma_rad\"")) << json.out;
  EXPECT_TRUE(absl::StrContains(json.out, "\"passages\": \"2\"")) << json.out;
  CliRun unknown = Mapctl({"vehicles", "sim-v9"}, server->address());
  EXPECT_EQ(unknown.code, 1);
  EXPECT_TRUE(OneErrorLine(unknown)) << unknown.err;
  EXPECT_TRUE(absl::StrContains(unknown.err, "NOT_FOUND")) << unknown.err;
  CliRun usage = Mapctl({"vehicles", "a", "b"}, server->address());
  EXPECT_EQ(usage.code, 2) << usage.err;
}

TEST(Mapctl, VersionPrintsTheProjectVersion) {
  std::ostringstream out, err;
  EXPECT_EQ(RunMapctl({"--version"}, out, err), 0);
  EXPECT_EQ(out.str(), std::string("mapctl (crowdmap) ") + CROWDMAP_VERSION + "\n");
}

}  // namespace
}  // namespace crowdmap
