// Fuzz target: one hostile or broken passage against an established map (40 passages), through
// validation and the whole map update with the service's default settings. The input is an edit
// script over a valid passage (shifted or scattered GNSS, over-confident sigmas, mislabelled or
// invented landmarks, garbage calibration, odd speeds and steering, cut drives, shifted times).
// Whatever it does, an update that is accepted must keep the map's invariants (finite estimates,
// positive semi-definite factors, positive-definite marginals) and must not move any established
// landmark of the map further than the whole-update gate allows (MapUpdateOptions::
// max_update_shift_mahalanobis2, in the landmark's standard deviations: 3 by default).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Cholesky>

#include "core/estimation/map_updater.h"
#include "core/model/passage.h"
#include "core/sim/scenario.h"
#include "tests/fuzz/fuzz_input.h"
#include "tests/fuzz/fuzz_seeds.h"

namespace crowdmap {
namespace {

constexpr int kLandmarks = 10;
constexpr int kMapPassages = 40;

struct EstablishedMap {
  std::unique_ptr<Scenario> scenario;
  MapUpdateOptions options;
  std::unique_ptr<MapUpdater> updater;
  MapState map;
};

[[noreturn]] void Fail(const std::string& what) {
  std::fprintf(stderr, "fuzz: %s\n", what.c_str());
  std::abort();
}

const EstablishedMap& Map() {
  static const EstablishedMap* kMap = [] {
    auto m = new EstablishedMap;
    ScenarioOptions options;
    options.landmarks = kLandmarks;
    absl::StatusOr<Scenario> scenario = Scenario::Create(options);
    if (!scenario.ok()) Fail(std::string(scenario.status().message()));
    m->scenario = std::make_unique<Scenario>(*std::move(scenario));
    m->updater = std::make_unique<MapUpdater>(m->options);
    for (int i = 0; i < kMapPassages; ++i) {
      const Passage passage = m->scenario->MakePassage(i);
      absl::StatusOr<PassageUpdate> update = m->updater->Compute(passage, m->map);
      if (!update.ok()) Fail("building the map: " + std::string(update.status().message()));
      m->map.Apply(update->delta);
      m->updater->Applied(passage, update->delta);
    }
    return m;
  }();
  return *kMap;
}

template <typename T, typename Pred>
void EraseIf(std::vector<T>& v, Pred pred) {
  v.erase(std::remove_if(v.begin(), v.end(), pred), v.end());
}

void Edit(FuzzInput& in, Passage& p) {
  const int edits = 1 + in.Byte() % 4;
  for (int e = 0; e < edits && !in.empty(); ++e) {
    switch (in.Byte() % 12) {
      case 0: {  // every fix shifted (degrees of about 1e-5 per metre)
        const double de = in.Double(1e4) * 1e-5, dn = in.Double(1e4) * 1e-5;
        for (GnssFix& f : p.gnss) f.lat_deg += dn, f.lon_deg += de;
        break;
      }
      case 1: {  // one fix anywhere
        if (p.gnss.empty()) break;
        GnssFix& f = p.gnss[in.Index(p.gnss.size())];
        f.lat_deg += in.Double(1e-2);
        f.lon_deg += in.Double(1e-2);
        break;
      }
      case 2: {  // declared sigmas scaled (over- or under-confident)
        const double scale = std::pow(10.0, in.Double(4.0));
        for (GnssFix& f : p.gnss) f.cov_en_m2 *= scale;
        break;
      }
      case 3: {  // detections of one landmark reported under another's id (mislabelled)
        const LandmarkId from = 1 + static_cast<LandmarkId>(in.Index(kLandmarks));
        const LandmarkId to = 1 + static_cast<LandmarkId>(in.Index(kLandmarks));
        for (Detection& d : p.detections) {
          if (d.landmark_id == from) d.landmark_id = to;
        }
        break;
      }
      case 4: {  // a calibration field
        const double v = in.Double(20.0);
        switch (in.Byte() % 6) {
          case 0: p.calibration.wheelbase_m = v; break;
          case 1: p.calibration.gnss_lever_arm_m.x() = v; break;
          case 2: p.calibration.camera_position_m.y() = v; break;
          case 3: p.calibration.camera_yaw_rad = v / 20.0; break;
          case 4: p.calibration.fx_px = std::abs(v) * 100.0; break;
          default: p.calibration.cx_px = v * 100.0; break;
        }
        break;
      }
      case 5: case 6: {  // speed or steering over a stretch
        if (p.odometry.empty()) break;
        const size_t a = in.Index(p.odometry.size()), n = in.Index(p.odometry.size() - a + 1);
        const bool speed = in.Byte() & 1;
        const double v = in.Double(speed ? 40.0 : 1.0);
        for (size_t i = a; i < a + n && i < p.odometry.size(); ++i) {
          (speed ? p.odometry[i].speed_mps : p.odometry[i].steering_rad) = v;
        }
        break;
      }
      case 7: {  // a piece of the drive (partial passage)
        if (p.odometry.size() < 2) break;
        const double t0 = p.odometry.front().t_s, t1 = p.odometry.back().t_s;
        const double from = t0 + (t1 - t0) * (in.Byte() / 255.0);
        const double to = from + (t1 - from) * (in.Byte() / 255.0);
        auto outside = [&](double t) { return t < from || t > to; };
        EraseIf(p.odometry, [&](const OdometrySample& s) { return outside(s.t_s); });
        EraseIf(p.gnss, [&](const GnssFix& f) { return outside(f.t_s); });
        EraseIf(p.detections, [&](const Detection& d) { return outside(d.t_s); });
        break;
      }
      case 8: {  // detection times shifted
        const double dt = in.Double(5.0);
        for (Detection& d : p.detections) d.t_s += dt;
        break;
      }
      case 9: {  // one detection's pixel anywhere
        if (p.detections.empty()) break;
        p.detections[in.Index(p.detections.size())].u_px = in.Double(5000.0);
        break;
      }
      case 10: {  // every pixel offset (a camera yaw the vehicle does not declare)
        const double du = in.Double(200.0);
        for (Detection& d : p.detections) d.u_px += du;
        break;
      }
      default: {  // one landmark's detections under a new id
        const LandmarkId from = 1 + static_cast<LandmarkId>(in.Index(kLandmarks));
        for (Detection& d : p.detections) {
          if (d.landmark_id == from) d.landmark_id = 1000 + from;
        }
        break;
      }
    }
  }
}

}  // namespace

std::vector<std::string> FuzzSeeds() {
  std::vector<std::string> seeds;
  for (int op = 0; op < 12; ++op) {
    std::string s = {'\1', static_cast<char>(op)};
    for (int i = 0; i < 24; ++i) s.push_back(static_cast<char>(37 * (op + 1) * (i + 3)));
    seeds.push_back(s);
  }
  return seeds;
}

}  // namespace crowdmap

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace crowdmap;
  const EstablishedMap& m = Map();
  FuzzInput in(data, size);
  Passage passage = m.scenario->MakePassage(kMapPassages + in.Byte() % 64);
  Edit(in, passage);
  if (!ValidatePassage(passage).ok()) return 0;
  absl::StatusOr<PassageUpdate> update = m.updater->Compute(passage, m.map);
  if (!update.ok()) return 0;  // refused: the map is unchanged
  if (absl::Status s = CheckDeltaInvariants(update->delta); !s.ok()) Fail(std::string(s.message()));
  MapState after = m.map;
  after.Apply(update->delta);
  if (absl::Status s = CheckStoredMap(after); !s.ok()) Fail(std::string(s.message()));
  for (const auto& [id, changed] : update->delta.landmarks) {
    const Landmark* before = m.map.FindLandmark(id);
    if (before == nullptr) continue;  // created by this passage
    if (before->passages_seen < kEstablishedLandmarkPassages) continue;
    const Eigen::Vector2d shift = changed.Offset() - before->Offset();
    const double sigmas = std::sqrt(shift.dot(before->cov_en_m2.llt().solve(shift)));
    if (!(sigmas * sigmas <= m.options.max_update_shift_mahalanobis2)) {
      Fail("landmark " + std::to_string(id) + " moved " + std::to_string(shift.norm()) + " m, " +
           std::to_string(sigmas) + " of its sigmas");
    }
  }
  return 0;
}
