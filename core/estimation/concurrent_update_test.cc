// Passage updates computed concurrently against one map version (core/map/map_access.h): what one
// read is recorded, and when another change committed meanwhile touched none of it, the update
// moved onto the new map is the one computed against it.
#include <optional>

#include <gtest/gtest.h>

#include "core/estimation/map_updater.h"
#include "core/map/map_access.h"
#include "core/sim/city_scenario.h"

namespace crowdmap {
namespace {

struct Recorded {
  PassageUpdate update;
  MapReadSet read;
};

Recorded ComputeRecorded(const Passage& passage, const MapUpdateOptions& options, MapReadRecorder recorder) {
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(passage, options, recorder);
  EXPECT_TRUE(update.ok()) << update.status();
  return {update.ok() ? *std::move(update) : PassageUpdate(), recorder.TakeRead()};
}

Recorded ComputeRecorded(const Passage& passage, const MapUpdateOptions& options, const MapState& map) {
  return ComputeRecorded(passage, options, MapReadRecorder(map));
}

void ExpectSameDelta(const MapDelta& a, const MapDelta& b) {
  EXPECT_EQ(a.base_version, b.base_version);
  EXPECT_EQ(a.version, b.version);
  ASSERT_EQ(a.landmarks.size(), b.landmarks.size());
  for (const auto& [id, l] : b.landmarks) {
    ASSERT_EQ(a.landmarks.count(id), 1u) << id;
    const Landmark& r = a.landmarks.at(id);
    EXPECT_EQ(r.position.lat_deg, l.position.lat_deg) << id;
    EXPECT_EQ(r.position.lon_deg, l.position.lon_deg) << id;
    EXPECT_EQ(r.cov_en_m2, l.cov_en_m2) << id;
    EXPECT_EQ(r.version, l.version) << id;
    EXPECT_EQ(r.passages_seen, l.passages_seen) << id;
  }
  ASSERT_EQ(a.added_factors.size(), b.added_factors.size());
  for (const auto& [id, f] : b.added_factors) {
    ASSERT_EQ(a.added_factors.count(id), 1u) << id;
    const MapFactor& r = a.added_factors.at(id);
    EXPECT_EQ(r.id, f.id);
    EXPECT_EQ(r.landmarks, f.landmarks) << id;
    EXPECT_EQ(r.information, f.information) << id;
    EXPECT_EQ(r.information_vector, f.information_vector) << id;
  }
  EXPECT_EQ(a.removed_factors, b.removed_factors);
  EXPECT_EQ(a.removed_landmarks, b.removed_landmarks);
}

// A 10 x 10 block city after 30 short passages (window of two links, as the service runs it at
// city scale), and passage 30's update computed against it.
struct CityMapAndAChange {
  MapUpdateOptions options;
  std::optional<CityScenario> scenario;
  MapState map;
  Recorded first;
  MapWriteSet written;  // by the first update
  MapState after;       // the map with it
};

void MakeCityMapAndAChange(CityMapAndAChange* out) {
  CityScenarioOptions city;
  city.blocks_x = 10;
  city.blocks_y = 10;
  city.route_length_m = 500.0;
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  out->scenario.emplace(*std::move(scenario));
  out->options.warmup_passages = 0;
  out->options.relinearize_until_passages = 0;
  out->options.window_hops = 2;
  for (int i = 0; i < 30; ++i) {
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(out->scenario->MakePassage(i), out->options, out->map);
    ASSERT_TRUE(update.ok()) << i << ": " << update.status();
    out->map.Apply(update->delta);
  }
  out->first = ComputeRecorded(out->scenario->MakePassage(30), out->options, out->map);
  out->written = WriteSetOf(out->first.update.delta, out->map);
  out->after = out->map;
  out->after.Apply(out->first.update.delta);
}

// Passage 30 is applied; of the next ones, computed against the map without it, those
// that read nothing it changed are moved onto the map with it and must equal, exactly, the update
// computed against that map. Those that did read something are told apart; a passage always
// overlaps itself.
TEST(ConcurrentUpdates, AnUpdateThatReadNothingTheOtherChangedIsTheSameAfterIt) {
  CityMapAndAChange c;
  MakeCityMapAndAChange(&c);
  if (HasFatalFailure()) return;
  const MapUpdateOptions& options = c.options;
  const MapState& map = c.map;
  const MapState& after = c.after;
  const MapWriteSet& written = c.written;
  EXPECT_TRUE(Overlaps(c.first.read, written)) << "a passage reads what it changes";

  int disjoint = 0;
  int overlapping = 0;
  for (int j = 31; j < 45 && (disjoint < 2 || overlapping < 1); ++j) {
    const Passage passage = c.scenario->MakePassage(j);
    Recorded second = ComputeRecorded(passage, options, map);
    if (Overlaps(second.read, written)) {
      ++overlapping;
      continue;
    }
    ++disjoint;
    RebaseDelta(map.last_factor_id(), after.version(), after.last_factor_id(), &second.update.delta);
    absl::StatusOr<PassageUpdate> direct = ComputePassageUpdate(passage, options, after);
    ASSERT_TRUE(direct.ok()) << direct.status();
    SCOPED_TRACE(j);
    ExpectSameDelta(second.update.delta, direct->delta);
  }
  EXPECT_GE(disjoint, 2);
  EXPECT_GE(overlapping, 1);
}

// A computation begun while another change's commit was under way (the map worker's other workers
// compute while one worker's durable transaction runs): it counts as made against the map before
// that change (MapReadRecorder's version and last factor id given) but reads the map with it. Those
// that read nothing the change wrote are the update computed against the map with it, exactly,
// once moved onto it; the change's own passage, computed so again, is told apart.
TEST(ConcurrentUpdates, AnUpdateBegunDuringACommitIsCheckedAgainstIt) {
  CityMapAndAChange c;
  MakeCityMapAndAChange(&c);
  if (HasFatalFailure()) return;
  const auto reading_after = [&c] {
    return MapReadRecorder([&c](const std::function<void(const MapReaderInterface&)>& read) { read(c.after); },
                           c.map.version(), c.map.last_factor_id());
  };
  const Recorded again = ComputeRecorded(c.scenario->MakePassage(30), c.options, reading_after());
  EXPECT_TRUE(Overlaps(again.read, c.written));
  EXPECT_EQ(again.update.delta.base_version, c.map.version());

  int disjoint = 0;
  int overlapping = 0;
  for (int j = 31; j < 45 && (disjoint < 2 || overlapping < 1); ++j) {
    const Passage passage = c.scenario->MakePassage(j);
    Recorded second = ComputeRecorded(passage, c.options, reading_after());
    if (Overlaps(second.read, c.written)) {
      ++overlapping;
      continue;
    }
    ++disjoint;
    EXPECT_EQ(second.update.delta.base_version, c.map.version());
    RebaseDelta(c.map.last_factor_id(), c.after.version(), c.after.last_factor_id(), &second.update.delta);
    absl::StatusOr<PassageUpdate> direct = ComputePassageUpdate(passage, c.options, c.after);
    ASSERT_TRUE(direct.ok()) << direct.status();
    SCOPED_TRACE(j);
    ExpectSameDelta(second.update.delta, direct->delta);
  }
  EXPECT_GE(disjoint, 2);
  EXPECT_GE(overlapping, 1);
}

}  // namespace
}  // namespace crowdmap
