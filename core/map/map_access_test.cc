#include "core/map/map_access.h"

#include <gtest/gtest.h>

#include "core/map/map_testing.h"

namespace crowdmap {
namespace {

// Landmarks 1..6 at version 2; factors 1 = {1, 2} (passage a), 2 = {3, 4} (b), 3 = {5, 6} (c).
class MapAccessTest : public testing::Test {
 protected:
  MapAccessTest() {
    for (LandmarkId id = 1; id <= 6; ++id) map_.PutLandmark(MakeLandmark(id, 2));
    int64_t id = 0;
    for (const auto& [ids, passage] : std::vector<std::pair<std::vector<LandmarkId>, std::string>>{
             {{1, 2}, "a"}, {{3, 4}, "b"}, {{5, 6}, "c"}}) {
      MapFactor f = MakeFactor(++id, ids, passage);
      map_.PutFactor(f);
    }
    map_.set_last_factor_id(3);
    map_.set_version(2);
  }
  MapState map_;
};

TEST_F(MapAccessTest, TheRecorderRecordsEveryKindOfRead) {
  MapReadRecorder recorder(map_);
  recorder.FindLandmark(1);
  recorder.FindLandmark(99);  // a miss counts: a landmark created meanwhile changes the answer
  recorder.Information(2, 3);
  recorder.InformationVector(4);
  int links = 0;
  recorder.ForEachLink(5, [&](LandmarkId, const InformationBlock&) { ++links; });
  EXPECT_EQ(links, 1);
  std::vector<int64_t> ids;
  recorder.AppendFactorIds(6, &ids);
  recorder.FindFactor(1);
  recorder.AppendPassageFactorIds("v", "b", &ids);
  recorder.FindVehicle("car");
  EXPECT_EQ(recorder.version(), 2);
  EXPECT_EQ(recorder.last_factor_id(), 3);

  const MapReadSet read = recorder.TakeRead();
  EXPECT_EQ(read.landmarks, (std::unordered_set<LandmarkId>{1, 99, 2, 3, 4, 5}));
  EXPECT_EQ(read.factor_lists, (std::unordered_set<LandmarkId>{6}));
  EXPECT_EQ(read.factors, (std::unordered_set<int64_t>{3, 1})) << "6's list handed out factor 3";
  EXPECT_EQ(read.passage_factor_lists, (std::set<FactorSource>{{"v", "b"}}));
  EXPECT_EQ(read.vehicles, (std::set<std::string>{"car"}));
  EXPECT_FALSE(read.all_vehicles);
}

// Every reader gives the same row, whole (InformationRowOf) or link by link (ForEachLink and
// Information), through VisitRow: the map, an overlay (the base's row where its changes leave
// the landmark alone) and a recorder (which records the landmark as read).
TEST_F(MapAccessTest, ARowVisitedWholeIsTheRowReadLinkByLink) {
  MapOverlay overlay(map_);
  overlay.BumpVersion();
  overlay.AddFactor(MakeFactor(0, {2, 3}, "d"));
  MapReadRecorder recorder(map_);
  const auto by_links = [](const MapReaderInterface& map, LandmarkId id) {
    std::vector<std::pair<LandmarkId, Eigen::Matrix2d>> out;
    map.ForEachLink(id, [&](LandmarkId b, const InformationBlock& block) { out.emplace_back(b, block.value); });
    out.emplace_back(id, map.Information(id, id).value);
    return out;
  };
  const auto visited = [](const MapReaderInterface& map, LandmarkId id) {
    std::vector<std::pair<LandmarkId, Eigen::Matrix2d>> out;
    const InformationBlock diagonal =
        map.VisitRow(id, [&](LandmarkId b, const InformationBlock& block) { out.emplace_back(b, block.value); });
    out.emplace_back(id, diagonal.value);
    return out;
  };
  for (LandmarkId id = 1; id <= 7; ++id) {
    for (const MapReaderInterface* map : std::vector<const MapReaderInterface*>{&map_, &overlay, &recorder}) {
      EXPECT_EQ(visited(*map, id), by_links(*map, id)) << "landmark " << id;
    }
  }
  ASSERT_NE(map_.InformationRowOf(1), nullptr);
  EXPECT_EQ(map_.InformationRowOf(1)->size(), 2u) << "the diagonal and landmark 2";
  EXPECT_TRUE(map_.InformationRowOf(7)->empty()) << "no information";
  EXPECT_EQ(overlay.InformationRowOf(1), map_.InformationRowOf(1)) << "untouched: the base's";
  EXPECT_EQ(overlay.InformationRowOf(2), nullptr) << "changed by the added factor";
  EXPECT_EQ(recorder.read().landmarks.count(6), 1u);
}

// A factor's landmarks are read as the factor is (the same entries in the read set), through an
// overlay too, which shows the factors it adds and hides those it removes.
TEST_F(MapAccessTest, AFactorsLandmarksAreReadLikeTheFactor) {
  MapReadRecorder recorder(map_);
  std::vector<LandmarkId> landmarks;
  EXPECT_TRUE(recorder.AppendFactorLandmarks(2, &landmarks));
  EXPECT_EQ(landmarks, (std::vector<LandmarkId>{3, 4}));
  EXPECT_FALSE(recorder.AppendFactorLandmarks(99, &landmarks));
  EXPECT_EQ(landmarks.size(), 2u);
  EXPECT_EQ(recorder.read().factors, (std::unordered_set<int64_t>{2, 99})) << "a miss counts";
  EXPECT_TRUE(recorder.read().factor_lists.empty());

  MapOverlay overlay(recorder);
  overlay.RemoveFactor(1);
  const int64_t added = overlay.AddFactor(MakeFactor(0, {2, 5}, "d"));
  landmarks.clear();
  EXPECT_FALSE(overlay.AppendFactorLandmarks(1, &landmarks));
  EXPECT_TRUE(overlay.AppendFactorLandmarks(added, &landmarks));
  EXPECT_TRUE(overlay.AppendFactorLandmarks(3, &landmarks));
  EXPECT_EQ(landmarks, (std::vector<LandmarkId>{2, 5, 5, 6}));
}

// A row of links read twice is the first read, also when a commit changed it in between; the
// commit's write set overlaps the read, so the computation is discarded.
TEST_F(MapAccessTest, ARowReadTwiceIsReadOnce) {
  MapReadRecorder recorder([this](const std::function<void(const MapReaderInterface&)>& read) { read(map_); });
  const auto links_of_1 = [&] {
    std::vector<LandmarkId> linked;
    recorder.ForEachLink(1, [&](LandmarkId b, const InformationBlock&) { linked.push_back(b); });
    return linked;
  };
  EXPECT_EQ(links_of_1(), (std::vector<LandmarkId>{2}));
  MapDelta delta;
  delta.base_version = 2;
  delta.version = 3;
  MapFactor f = MakeFactor(4, {1, 3}, "d");
  delta.added_factors.emplace(4, f);
  const MapWriteSet written = WriteSetOf(delta, map_);
  map_.Apply(delta);
  EXPECT_EQ(links_of_1(), (std::vector<LandmarkId>{2}));
  EXPECT_TRUE(Overlaps(recorder.read(), written));
}

// A computation that read the whole fleet (a new vehicle's fleet prior) could have read
// differently after any vehicle's record changed.
TEST_F(MapAccessTest, ReadingEveryVehicleOverlapsAnyVehiclesChange) {
  VehicleCalibration car;
  car.vehicle_id = "car";
  map_.PutVehicle(car);
  MapReadRecorder recorder(map_);
  std::vector<std::string> listed;
  recorder.ForEachVehicle([&](const VehicleCalibration& v) { listed.push_back(v.vehicle_id); });
  EXPECT_EQ(listed, std::vector<std::string>{"car"});
  const MapReadSet read = recorder.TakeRead();
  EXPECT_TRUE(read.all_vehicles);
  MapWriteSet written;
  EXPECT_FALSE(Overlaps(read, written));
  written.vehicles.insert("bus");
  EXPECT_TRUE(Overlaps(read, written));
  MapReadSet one;
  one.vehicles.insert("car");
  EXPECT_FALSE(Overlaps(one, written));
}

TEST_F(MapAccessTest, WriteSetsSeparateInformationFromFactorLists) {
  MapOverlay overlay(map_);
  overlay.BumpVersion();
  overlay.PutLandmark(MakeLandmark(7, overlay.version()));
  overlay.AddFactor(MakeFactor(0, {6, 7}, "d"));
  overlay.RemoveFactor(2);
  overlay.FoldFactor(1);
  VehicleCalibration car;
  car.vehicle_id = "car";
  overlay.PutVehicle(car);
  const MapWriteSet written = WriteSetOf(overlay.delta(), map_);
  EXPECT_EQ(written.landmarks, (std::unordered_set<LandmarkId>{7, 6, 3, 4})) << "folding keeps the information";
  EXPECT_EQ(written.factor_lists, (std::unordered_set<LandmarkId>{6, 7, 3, 4}));
  EXPECT_EQ(written.factors, (std::unordered_set<int64_t>{4, 2, 1}));
  EXPECT_EQ(written.passages, (std::set<FactorSource>{{"v", "a"}, {"v", "b"}, {"v", "d"}}));
  EXPECT_EQ(written.vehicles, (std::set<std::string>{"car"}));

  // Each kind of read meets its kind of write, and only that.
  MapReadSet read;
  EXPECT_FALSE(Overlaps(read, written));
  read.landmarks = {1, 2, 5};
  EXPECT_FALSE(Overlaps(read, written)) << "1 and 2 were folded: their information is unchanged";
  read.factor_lists = {1};
  EXPECT_FALSE(Overlaps(read, written)) << "1's list lost factor 1, which the read would have seen";
  read.factors = {1};
  EXPECT_TRUE(Overlaps(read, written));
  read.factors = {3};
  EXPECT_FALSE(Overlaps(read, written));
  read.factor_lists = {6};
  EXPECT_TRUE(Overlaps(read, written)) << "6's list gained a factor";
  read.factor_lists.clear();
  read.factors.clear();
  read.landmarks.insert(3);
  EXPECT_TRUE(Overlaps(read, written));
  read.landmarks.clear();
  read.passage_factor_lists = {{"v", "c"}};
  EXPECT_FALSE(Overlaps(read, written));
  read.passage_factor_lists.insert({"v", "a"});
  EXPECT_TRUE(Overlaps(read, written));
  read.passage_factor_lists.clear();
  read.vehicles = {"car"};
  EXPECT_TRUE(Overlaps(read, written));
}

// Folding a factor (the oldest retained passage's, at a worker's commit) discards only the
// computations that saw it: one that read another factor of the same landmark stays valid, one
// that listed that landmark's factors (and so was handed the folded one) does not.
TEST_F(MapAccessTest, AFoldOverlapsOnlyTheReadsThatSawTheFolded) {
  map_.PutFactor(MakeFactor(4, {2, 5}, "d"));
  MapDelta fold;
  fold.base_version = 2;
  fold.version = 3;
  fold.folded_factors = {4};
  const MapWriteSet written = WriteSetOf(fold, map_);

  MapReadRecorder by_id(map_);
  ASSERT_NE(by_id.FindFactor(3), nullptr);  // {5, 6}: landmark 5 is the folded one's too
  std::vector<LandmarkId> landmarks;
  ASSERT_TRUE(by_id.AppendFactorLandmarks(1, &landmarks));  // {1, 2}: so is landmark 2
  EXPECT_FALSE(Overlaps(by_id.read(), written));

  MapReadRecorder listed(map_);
  std::vector<int64_t> ids;
  listed.AppendFactorIds(5, &ids);
  EXPECT_EQ(ids, (std::vector<int64_t>{3, 4}));
  EXPECT_TRUE(Overlaps(listed.read(), written));
  map_.Apply(fold);
  ids.clear();
  map_.AppendFactorIds(5, &ids);
  EXPECT_EQ(ids, (std::vector<int64_t>{3})) << "the list it read changed";
}

// A factor id looked up and not found is found once a commit adds it: the miss overlaps that
// addition.
TEST_F(MapAccessTest, AMissOverlapsTheAdditionOfThatFactor) {
  MapReadRecorder recorder(map_);  // counts as version 2, last factor id 3
  EXPECT_EQ(recorder.FindFactor(4), nullptr);
  MapDelta add;
  add.base_version = 2;
  add.version = 3;
  add.added_factors.emplace(4, MakeFactor(4, {5, 6}, "d"));
  EXPECT_TRUE(Overlaps(recorder.read(), WriteSetOf(add, map_)));
}

// A computation that removes a factor it added and looks its id up again reads, through its
// overlay, the factor another worker's commit added under that id meanwhile: the computation
// overlaps that commit.
TEST_F(MapAccessTest, AFactorReadThroughAnOwnRemovedIdOverlapsTheCommitThatAddedIt) {
  MapReadRecorder recorder(map_);  // counts as version 2, last factor id 3
  MapDelta other;                  // another worker's commit, from version 2: factor 4 on {5, 6}
  other.base_version = 2;
  other.version = 3;
  other.added_factors.emplace(4, MakeFactor(4, {5, 6}, "d"));
  const MapWriteSet written = WriteSetOf(other, map_);  // against the map before it, as the worker does
  map_.Apply(other);

  MapOverlay overlay(recorder);
  const int64_t own = overlay.AddFactor(MakeFactor(0, {1, 2}, "e"));
  ASSERT_EQ(own, 4) << "counted from the recorder's last factor id";
  overlay.RemoveFactor(own);
  const MapFactor* seen = overlay.FindFactor(own);
  ASSERT_NE(seen, nullptr);
  EXPECT_EQ(seen->passage_id, "d") << "the other commit's factor";
  EXPECT_TRUE(Overlaps(recorder.read(), written));
}

// A change computed against version 2, moved past another committed meanwhile, equals the same
// change computed against the map with the other one.
TEST_F(MapAccessTest, ARebasedDeltaEqualsTheDeltaComputedAfterTheOtherChange) {
  auto change = [](const MapReaderInterface& map) {
    MapOverlay overlay(map);
    overlay.BumpVersion();
    overlay.AddFactor(MakeFactor(0, {1, 2}, "e"));
    Landmark l = *map.FindLandmark(1);
    l.version = overlay.BumpVersion();
    overlay.PutLandmark(l);
    overlay.AddFactor(MakeFactor(0, {1, 8}, "e"));
    overlay.PutLandmark(MakeLandmark(8, overlay.version()));
    return overlay.TakeDelta();
  };
  MapOverlay other(map_);
  other.BumpVersion();
  other.AddFactor(MakeFactor(0, {5, 6}, "f"));
  other.AddFactor(MakeFactor(0, {6}, "f"));
  other.PutLandmark(MakeLandmark(6, other.version()));
  const MapDelta committed = other.TakeDelta();

  MapDelta rebased = change(map_);
  MapState after = map_;
  after.Apply(committed);
  RebaseDelta(map_.last_factor_id(), after.version(), after.last_factor_id(), &rebased);
  const MapDelta direct = change(after);

  EXPECT_EQ(rebased.base_version, 3);
  EXPECT_EQ(rebased.version, direct.version);
  EXPECT_EQ(rebased.version, 5);
  ASSERT_EQ(rebased.landmarks.size(), direct.landmarks.size());
  for (const auto& [id, l] : direct.landmarks) EXPECT_EQ(rebased.landmarks.at(id).version, l.version) << id;
  ASSERT_EQ(rebased.added_factors.size(), direct.added_factors.size());
  auto r = rebased.added_factors.begin();
  for (const auto& [id, f] : direct.added_factors) {
    EXPECT_EQ(r->first, id);
    EXPECT_EQ(r->second.id, id);
    EXPECT_EQ(r->second.landmarks, f.landmarks);
    ++r;
  }
  EXPECT_EQ(rebased.added_factors.begin()->first, 6) << "after the other change's factors 4 and 5";
  // Landmark records the delta copies unchanged keep their version.
  MapDelta old;
  old.base_version = 2;
  old.version = 3;
  old.landmarks[1] = MakeLandmark(1, 1);
  RebaseDelta(3, 4, 5, &old);
  EXPECT_EQ(old.landmarks[1].version, 1);
  EXPECT_EQ(old.version, 5);
}

}  // namespace
}  // namespace crowdmap
