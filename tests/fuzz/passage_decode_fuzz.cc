// Fuzz target: an uploaded passage's bytes through decoding, conversion and validation, as the
// upload RPCs take them. Whatever the bytes: no crash, and a passage that is accepted converts back
// and forth to the same accepted passage.
#include <cstdlib>
#include <string>
#include <vector>

#include <google/protobuf/stubs/logging.h>

#include "core/model/passage.h"
#include "core/sim/scenario.h"
#include "server/wire_convert.h"
#include "tests/fuzz/fuzz_seeds.h"

namespace crowdmap {

std::vector<std::string> FuzzSeeds() {
  ScenarioOptions options;
  options.landmarks = 8;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  if (!scenario.ok()) std::abort();
  std::vector<std::string> seeds;
  for (int i = 0; i < 2; ++i) {
    pb::Passage wire;
    PassageToProto(scenario->MakePassage(i), &wire);
    seeds.push_back(wire.SerializeAsString());
  }
  return seeds;
}

}  // namespace crowdmap

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace crowdmap;
  static const bool kQuiet = [] {  // invalid UTF-8 is an expected refusal, not worth a log line each
    google::protobuf::SetLogHandler(nullptr);
    return true;
  }();
  (void)kQuiet;
  pb::Passage wire;
  if (!wire.ParseFromArray(data, static_cast<int>(size))) return 0;
  absl::StatusOr<Passage> passage = PassageFromProto(wire);
  if (!passage.ok()) {
    if (passage.status().code() != absl::StatusCode::kInvalidArgument || passage.status().message().empty()) {
      std::abort();  // a refusal is InvalidArgument and says why
    }
    return 0;
  }
  if (!ValidatePassage(*passage).ok()) std::abort();
  pb::Passage again;
  PassageToProto(*passage, &again);
  absl::StatusOr<Passage> round_trip = PassageFromProto(again);
  if (!round_trip.ok() || round_trip->odometry.size() != passage->odometry.size() ||
      round_trip->detections.size() != passage->detections.size() || round_trip->gnss.size() != passage->gnss.size()) {
    std::abort();
  }
  return 0;
}
