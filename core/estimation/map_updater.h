#ifndef CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_
#define CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_

#include <deque>
#include <functional>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/estimation/graph_builder.h"
#include "core/estimation/map_update_options.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"

namespace crowdmap {

// The sensors a passage's measurements come from, each tested on its own, in this order
// (PassageUpdateSummary::sensor_test_factors, MeasurementWeights::Sensor): odometry, GNSS, camera.
constexpr int kPassageSensors = 3;
// "odometry", "gnss", "camera".
const char* PassageSensorName(int sensor);

// What applying one passage did; Brief() is a key=value log line.
struct PassageUpdateSummary {
  int nodes = 0;
  int subgraphs = 0;
  int landmarks_updated = 0;      // already in the map and seen by the passage
  int landmarks_created = 0;      // new to the map
  int landmarks_conditioned = 0;  // outside the passage, moved through their correlation
  int landmarks_removed = 0;      // left without information (by an exclusion)
  int landmarks_held_back = 0;    // new, but not pinned down by the passage's rays: not created
  int landmarks_disagreeing = 0;  // map landmarks the passage would move beyond the map's uncertainty: not used
  int detections_used = 0;
  int detections_dropped = 0;     // e.g. behind the camera at the initial guess
  int detections_outliers = 0;    // residual beyond options.max_detection_residual_sigmas: not used
  int solver_iterations = 0;
  double final_cost = 0.0;
  double max_variance_factor = 1.0;  // largest inflation of a subgraph's measurements by their chi2 (1 = none)
  // The largest variance factor each sensor's own test applied over the subgraphs (odometry, GNSS,
  // camera; MapUpdateOptions::sensor_test_sigmas), beyond max_variance_factor's (1 = none).
  double sensor_test_factors[kPassageSensors] = {1.0, 1.0, 1.0};
  double solve_ms = 0.0;
  double covariance_ms = 0.0;
  double bias_correction_ms = 0.0;
  double max_bias_correction_m = 0.0;  // largest landmark shift by the bias correction
  double total_ms = 0.0;
  // With the camera yaw estimated (MapUpdateOptions::estimate_camera_yaw): the vehicle's estimate
  // after the passage, and its standard deviation.
  double camera_yaw_offset_rad = 0.0;
  double camera_yaw_sigma_rad = 0.0;
  // With the wheel-speed scale estimated (MapUpdateOptions::speed_scale_prior_sigma): the last
  // subgraph's estimate and its standard deviation.
  double speed_scale = 0.0;
  double speed_scale_sigma = 0.0;
  // A passage declaring white GNSS noise (MapUpdateOptions::correlated_gnss_min_lag1): the lag-1
  // correlation of its fixes' residuals, and the correlation time of the process it was estimated
  // with where they showed correlated errors (0: as declared).
  double gnss_residual_lag1 = 0.0;
  double gnss_correlation_time_s = 0.0;
  int64_t map_version = 0;  // version after the update
  int joint_passages = 0;       // passages solved jointly (warm-up or re-solve); 0 = sequential update
  bool joint_rejected = false;  // the joint solve was not usable, this is the sequential update

  std::string Brief() const;
  // " speed_scale=... speed_scale_sigma=..." when the scale was estimated, "" otherwise (a part of
  // Brief() that the service's applied-passage line carries too).
  std::string SpeedScaleBrief() const;
  // " gnss_residual_lag1=..." for a passage checked for correlated GNSS errors (gnss_correlation.h),
  // with " gnss_correlation_time_s=..." when it was estimated with the process they showed; ""
  // otherwise. In the applied-passage line too.
  std::string GnssBrief() const;
  // " odometry_factor=... gnss_factor=... camera_factor=..." (sensor_test_factors) when a sensor's
  // own test raised one, "" otherwise. In the applied-passage line too.
  std::string SensorBrief() const;
};

struct PassageUpdate {
  MapDelta delta;
  PassageUpdateSummary summary;
};

// The graph options of the map update's passages: which detections it uses.
GraphOptions UpdateGraphOptions(const MapUpdateOptions& options);

// Computes the map change one passage brings: builds its factor graph, subdivides it (cc-gsd),
// adds the map prior, solves with Ceres, recovers the landmark covariance and conditions the
// correlated landmarks outside the graph. `map` is only read; apply the returned delta to commit.
// The passage must have passed ValidatePassage. Errors: InvalidArgument for options or a passage
// that cannot be used (e.g. no landmark observable); Internal when the solver or the covariance
// fails (nothing is half-applied: the delta is returned only on success).
absl::StatusOr<PassageUpdate> ComputePassageUpdate(const Passage& passage, const MapUpdateOptions& options,
                                                   const MapReaderInterface& map);

// How free (metres, along its weakest direction) the map without a passage may leave a landmark
// while the passage is taken again (ComputePassageRelinearization). A young landmark the passage
// gave most of what the map knows of it is where re-linearising matters most, and the passage
// gives its information back in the same change; beyond this the window's covariance would not be
// numerically sound (a ray or two from other passages), and the passage stays as it is.
inline constexpr double kRelinearizationMaxLeftSigmaM = 1000.0;

// Takes the passage's contribution to `map` again at the map's current estimate: its factors are
// removed (as ComputePassageExclusion) and it is applied anew (ComputePassageUpdate) against the map
// without it, in one change. Every factor is a Gaussian taken at the estimate of its day; when the
// map has since moved by a sizeable part of its uncertainty (a young street), taking it again at
// today's removes what the old linearisation point left in the map. Where the map without the
// passage fixes a landmark less than an exclusion requires, the change is refused
// (FailedPrecondition) unless the passage taken again fixes it as required, and always when what
// is left is freer than kRelinearizationMaxLeftSigmaM. Other errors as for ComputePassageUpdate.
absl::StatusOr<PassageUpdate> ComputePassageRelinearization(const Passage& passage, const MapUpdateOptions& options,
                                                            const MapReaderInterface& map);

// Solves `passages` jointly, from no map: one factor graph of all their poses and the landmarks
// they saw (no subdivision, no map prior), with the same consistency test per passage, bias
// correction and covariance recovery as the sequential update. Meant for a map that holds only
// what the passages before the last produced: the solve starts from `map` with the last passage
// applied on its own (ComputePassageUpdate, whose errors it returns: a passage the estimator
// cannot use is refused the same way). The returned delta, computed against `map`, replaces the
// record of every landmark the passages saw (at one new version). Should the joint solve fail, or
// move a landmark out of the sequential update's confidence region (options.max_joint_mahalanobis2),
// the sequential update is returned instead, with summary.joint_rejected set.
absl::StatusOr<PassageUpdate> ComputeBatchUpdate(const std::vector<Passage>& passages, const MapUpdateOptions& options,
                                                 const MapReaderInterface& map);

// Takes the contributions of `passages`, all applied to `map` and retained there, again in one joint
// solve at the map's current estimate, with the rest of the map as its prior: the joint solve of
// ComputeBatchUpdate for one area of a grown map (a street mapped late gets what a young map's
// first streets get). Their factors are replaced by those of the joint solution, landmarks they
// alone informed included; the vehicles' records stay. An area's detections beyond
// options.max_detection_residual_sigmas are set aside, as the sequential update sets them aside.
// Refused (FailedPrecondition, nothing changed) when the rest of the map fixes one of their
// landmarks worse than a new landmark must be (options.max_new_landmark_ray_sigma_m), when a
// landmark only they inform is not pinned down by one passage's rays as a new one must be
// (WellDeterminedNewLandmark) or left fixed worse than that, when they cannot use their detections
// of a landmark they informed, or when the solution moves a landmark out of the map's confidence
// region (options.max_joint_mahalanobis2). Not with dc. Other errors as for ComputePassageUpdate.
absl::StatusOr<PassageUpdate> ComputeAreaRelinearization(const std::vector<Passage>& passages,
                                                         const MapUpdateOptions& options, const MapReaderInterface& map);

// The re-linearisation of a stale passage, `area`'s first, with the other passages of its area
// (MapUpdater::AreaOf): with options.relinearize_area_passages >= 1 their joint solve
// (ComputeAreaRelinearization), also of the passage alone; with 0, or when that is refused, the
// passage alone by its subgraphs (ComputePassageRelinearization, whose errors it returns).
absl::StatusOr<PassageUpdate> ComputeRelinearization(const std::vector<Passage>& area, const MapUpdateOptions& options,
                                                     const MapReaderInterface& map);

// Whether the map's `count`-th passage (1-based) is applied by the joint solve of all its passages:
// during the warm-up, and (except with dc) at each doubling of the count until
// options.relinearize_until_passages.
bool IsJointSolvePassage(int64_t count, const MapUpdateOptions& options);

// How many of a map's first passages a MapUpdater needs back (those of its last joint solve).
int JointSolvePassages(const MapUpdateOptions& options);

// Applies passages to one map in order, the way the service and the experiments do: while the
// map has taken fewer than options.warmup_passages passages, and then at each doubling of its
// passage count up to options.relinearize_until_passages, the update is the joint solve of all of
// them (ComputeBatchUpdate); otherwise one passage at a time (ComputePassageUpdate). Holds the
// passages a later joint solve needs; the map itself stays with the caller.
class MapUpdater {
 public:
  // `applied` are the passages the map has already taken, in order (enough of them to cover the
  // joint solves: the first JointSolvePassages(options), or all when fewer), `applied_count` how
  // many there are in all; `map`, when given, the map they made (whose retained passages are those
  // with factors, oldest first).
  explicit MapUpdater(const MapUpdateOptions& options, std::vector<Passage> applied = {}, int64_t applied_count = 0,
                      const MapState* map = nullptr);

  const MapUpdateOptions& options() const { return options_; }
  bool warming_up() const { return applied_count_ < options_.warmup_passages; }
  // Whether the next passage will be applied by a joint solve (never without all the map's
  // passages: a joint solve replaces what the passages it lacks brought). Never again once the map
  // has taken more passages than its joint solves need, exclusions included: by then the oldest
  // may be folded into its base, which a joint solve would count twice.
  bool joint_next() const {
    return IsJointSolvePassage(applied_count_ + 1, options_) && static_cast<int64_t>(kept_.size()) == applied_count_ &&
           taken_count_ <= JointSolvePassages(options_);
  }

  // The map change `passage` brings to `map` (see ComputePassageUpdate for the errors), with the
  // folding of the passages that leave the retention (MapUpdateOptions::retain_passages).
  // How one passage is to be taken, beyond the options.
  struct Mode {
    // An operator released the passage from quarantine: taken with the map's consistency checks
    // off (options.max_chi2_per_dof and max_landmark_shift_mahalanobis2; the invariants still
    // hold), e.g. for a landmark that really moved.
    bool vouched = false;
    // A sequential update even where a joint solve is due (as when a joint solve is not usable):
    // the service takes a passage this way once its joint solves were interrupted again and again.
    bool sequential = false;
  };
  absl::StatusOr<PassageUpdate> Compute(const Passage& passage, const MapReaderInterface& map, Mode mode) const;
  absl::StatusOr<PassageUpdate> Compute(const Passage& passage, const MapReaderInterface& map) const {
    return Compute(passage, map, Mode());
  }

  // Compute in three steps, for a caller that reads and changes the updater under a lock but
  // computes outside it (the service's parallel workers): Plan reads the updater, ComputePlanned
  // only the map, and AddFolding, called when the change is committed, the updater as it is then.
  struct Plan {
    MapUpdateOptions options;     // with the Mode applied
    bool joint = false;           // a joint solve of `kept` and the new passage; otherwise sequential
    std::vector<Passage> kept;    // the map's passages before the new one, for the joint solve
    int64_t applied_count = 0;    // passages the map had taken when planned
  };
  Plan PlanFor(Mode mode) const;
  static absl::StatusOr<PassageUpdate> ComputePlanned(const Plan& plan, const Passage& passage,
                                                      const MapReaderInterface& map);
  // Appends to delta->folded_factors the factors of the passages that one more passage pushes out of
  // the retention (MapUpdateOptions::retain_passages), as `map` holds them.
  void AddFolding(const MapReaderInterface& map, MapDelta* delta) const;
  int64_t applied_count() const { return applied_count_; }

  using PassageKey = std::pair<std::string, std::string>;  // vehicle_id, passage_id

  // Records that the delta Compute returned for `passage` was applied to the map.
  void Applied(const Passage& passage, const MapDelta& delta);
  // The retained passage whose factors were taken furthest from the map's current estimate: the
  // largest move of one of its landmarks since, in that landmark's current standard deviations
  // (Mahalanobis distance). None when no passage's move exceeds options.relinearize_sigmas (or it
  // is 0). Passages applied before this updater was made count as taken at the estimate it found.
  // Passages in `skip` are passed over (a service's re-linearisations under way).
  std::optional<PassageKey> StalestPassage(const MapReaderInterface& map, const std::set<PassageKey>& skip = {}) const;
  // The passages to take again with `stalest` in one joint solve (options.relinearize_area_passages):
  // `stalest` first, then the other retained passages on one of its landmarks whose own landmarks
  // moved by more than one sigma since their factors were taken, stalest first, up to
  // options.relinearize_area_passages in all. Just `stalest` when that option is below 2.
  std::vector<PassageKey> AreaOf(const PassageKey& stalest, const MapReaderInterface& map) const;
  // Records that a re-linearisation (ComputePassageRelinearization, or ComputeAreaRelinearization
  // for an area), `delta`, was applied: its passages' factors were taken where the delta puts their
  // landmarks.
  void Relinearized(const MapDelta& delta) { RecordLinearization(delta); }
  // A passage whose re-linearisation failed is not proposed again until it is applied anew.
  void RelinearizationFailed(const PassageKey& key) { linearized_at_.erase(key); }
  // Re-linearises up to options.relinearizations_per_passage of the stalest passages, one at a
  // time, each with its area (AreaOf; ComputeRelinearization says how it is solved): `passage_of`
  // returns a retained passage's data, `apply` commits a change to the map the updater reads (and
  // fails if it could not). Returns how many were applied; a passage whose
  // re-linearisation fails is skipped (reported through `on_error`), never retried in a loop.
  int RelinearizeStale(const MapReaderInterface& map,
                       const std::function<absl::StatusOr<Passage>(const PassageKey&)>& passage_of,
                       const std::function<absl::Status(const PassageKey&, const PassageUpdate&)>& apply,
                       const std::function<void(const PassageKey&, const absl::Status&)>& on_error);
  // Records that an applied passage was taken out of the map (ComputePassageExclusion): later
  // joint solves leave it out.
  void Excluded(const std::string& vehicle_id, const std::string& passage_id);

 private:
  // Records where the factors of each passage in `delta` were taken: its landmarks' positions.
  void RecordLinearization(const MapDelta& delta);
  // The largest move of a landmark of `landmarks` since they were recorded, squared, in the
  // landmark's current standard deviations.
  static double Staleness(const std::vector<std::pair<LandmarkId, LatLon>>& landmarks, const MapReaderInterface& map);
  // How many of the oldest retained passages one more passage pushes out of the retention.
  size_t Leaving() const;

  MapUpdateOptions options_;
  std::vector<Passage> kept_;  // the map's first passages, as many as its joint solves need
  int64_t applied_count_ = 0;
  int64_t taken_count_ = 0;  // passages ever applied: applied_count_ and those excluded since
  std::deque<PassageKey> retained_;  // passages whose factors are kept, oldest first
  // For retained passages: their landmarks and where they were when the factors were taken.
  std::map<PassageKey, std::vector<std::pair<LandmarkId, LatLon>>> linearized_at_;
};

// MapUpdater::RelinearizeStale for a map held in memory (experiments and tests): changes are
// applied to `map` directly; failures are logged.
int RelinearizeStaleInMemory(const std::function<absl::StatusOr<Passage>(const MapUpdater::PassageKey&)>& passage_of,
                             MapUpdater* updater, MapState* map);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_MAP_UPDATER_H_
