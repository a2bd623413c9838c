#ifndef CROWDMAP_CORE_ESTIMATION_MAP_UPDATE_OPTIONS_H_
#define CROWDMAP_CORE_ESTIMATION_MAP_UPDATE_OPTIONS_H_

// The settings of a map update (ComputePassageUpdate, ComputeBatchUpdate, MapUpdater), each with
// its meaning, unit and default. Measured effects are in the README.

#include <functional>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace crowdmap {

// How the current map enters a passage's graph (thesis section 4.4.3).
enum class UpdateStrategy {
  kCorrelated,            // "cc": one joint prior on the graph's map landmarks, whole passage at once
  kDecorrelated,          // "dc": one 2x2 prior per landmark; the map keeps no cross-covariances
  kCorrelatedSubdivided,  // "cc-gsd": cc on subgraphs of bounded state dimension (default)
};

absl::StatusOr<UpdateStrategy> ParseUpdateStrategy(std::string_view name);
const char* UpdateStrategyName(UpdateStrategy strategy);

// Passages that must have seen a landmark before MapUpdateOptions::max_update_shift_mahalanobis2
// bounds what one passage may do to it. A young landmark's covariance rests on a few passages and
// can be over-confident: on 60-passage city maps with 3 passages required, honest passages moved
// landmarks 3.0 to 3.7 of their sigmas and 5 of 1920 were refused.
constexpr int64_t kEstablishedLandmarkPassages = 10;

struct MapUpdateOptions {
  UpdateStrategy strategy = UpdateStrategy::kCorrelatedSubdivided;
  // Largest state dimension (3 per pose + 2 per landmark) of one subgraph with cc-gsd.
  int max_subgraph_dim = 500;
  // Detections used per landmark and passage: the last K (0 = all), of the first camera frame in
  // each interval of `detection_spacing_s`. The thesis's K = 5 are the last 2 s of a landmark's
  // track at its camera's 2 frames per second; from a 25 or 50 Hz camera the last 5 frames are a
  // tenth of a second apart: the same view five times, near the image border where the landmark
  // leaves it, and the map was 1.6 to 2.1 times its bound with up to a third of the passages
  // failing the consistency test (loop N = 25, 100 passages). On this grid of frames every
  // camera gives the 2 Hz camera's geometry and pose nodes (docs/results.md, "Camera frame
  // rates"); at 2 Hz or slower every frame is on it.
  int detections_per_landmark = 5;
  // The K detections spread evenly over each landmark's track in the passage (its first and last
  // grid frames among them) instead of the last K. A narrow lens loses a landmark far down the
  // street, where its last frames see it with little parallax: on the simulator's city, 60
  // passages of 1 km, 10 seeds, 17% less error with lenses of 50-110 degrees (outliers 38 -> 7)
  // and 13% less with the thesis camera, but +3% +- 5% for a varied fleet with AR(1) GNSS; on the
  // thesis loop (N = 50, 1000 passages, 3 seeds) 6-15% less, but one seed's joint NEES/dof 1.16 ->
  // 1.44, and 25% more with a camera yaw error left unestimated (the far views count more). Off by
  // default: the thesis's figures are the last K's (docs/results.md, "Detections spread over the
  // track").
  bool spread_detections = false;
  double detection_spacing_s = 0.5;
  // ...and of those only frames taken once the vehicle is this far (m) along its path from the grid
  // frame before (its speeds integrated with their signs, so that zero-mean noise read while the
  // wheels stand still is no travel): a vehicle standing still (parked, at a red light) adds no
  // detections. A camera that does not move sees the same view, whose detector error is the same
  // from frame to frame; taken as independent, twenty minutes parked in front of a sign would be
  // 2,400 measurements of one bearing. 0 = by time alone.
  double detection_spacing_m = 1.0;
  // Detections of map landmarks predicted less than this many pixel sigmas from the image border
  // are not used: the detector reports only what falls inside the image, which biases those
  // inwards (see InitializeLandmarks). Sequential updates only (not the warm-up's joint solve).
  // 0 uses them all.
  double edge_margin_sigmas = 3.0;
  // A landmark new to the map is created only when the passage's rays to it span at least this
  // angle (rad): with less its distance along the rays is undetermined (a landmark approached
  // head-on at the end of a street), and a solve places it hundreds of metres off with a
  // covariance that does not show it. 0 = any two rays that intersect.
  double min_new_landmark_parallax_rad = 0.05;
  // ...and only from at least this many usable detections: two rays always intersect, so nothing
  // in a passage checks a landmark it saw twice.
  int min_new_landmark_detections = 3;
  // After the solve, a new landmark enters the map only if it lies within this distance (m) of
  // every camera that detected it (a detector of poles and signs sees a few tens of metres; a
  // landmark placed further is one the rays do not pin down)...
  double max_new_landmark_range_m = 150.0;
  // ...and if its own rays, with the passage's poses held, fix its position to this standard
  // deviation (m) in every direction. Otherwise its detections are set aside for the passage and
  // the subgraph is solved again without them; a later passage with better geometry creates it.
  double max_new_landmark_ray_sigma_m = 3.0;
  // ...and if the solution's second-order bias correction (bias_correction) moves it by at most
  // this many of its sigmas: a larger correction shows a landmark the update's Gaussian does not
  // describe (a city passage's new landmark 12.8 m off with a 22.8 m sigma, corrected by 28.5 m,
  // then held 43 m off with a 2.4 m sigma; docs/results.md, "A fleet of several car models").
  // 0 = no such test.
  double max_new_landmark_bias_sigmas = 1.0;
  // MapUpdater keeps the factors of the map's last this-many passages apart (they can be
  // excluded: ComputePassageExclusion) and folds those of older passages into the map's base with
  // the next update (MapDelta::folded_factors), so that the map's size grows with the road, not
  // with its history. At least the passages the young map's joint solves take again
  // (JointSolvePassages + 1); 0 = keep every factor.
  int retain_passages = 256;
  // The map's covariance is recovered for the prior, and the map re-estimated after the passage,
  // over the landmarks within this many links (shared factors) of the passage's landmarks (one
  // window per passage with CC, PassagePrior; per graph with DC); the rest of the map is held at
  // its estimate, and the covariance is conservative (never smaller than the exact one). 0 = the
  // whole connected part of the map: exact, with a cost that grows with it.
  int window_hops = 0;
  int max_solver_iterations = 100;
  // Per-vehicle camera yaw calibration (docs/estimation.md, "Per-vehicle camera calibration"):
  // every sequential update estimates the passage's camera yaw offset from its declared
  // calibration, one state shared by all its camera residuals, with the vehicle's stored estimate
  // (VehicleCalibration) as its prior, and stores the solve's posterior as the vehicle's new
  // estimate. The state is eliminated with the poses, so the map's factor holds its uncertainty.
  // false: the declared calibration is taken as exact (no state, no vehicle records).
  bool estimate_camera_yaw = false;
  // Prior standard deviation (rad) of the camera yaw offset of a vehicle without an estimate yet
  // (mean 0), and of every passage in the joint solves (warm-up, re-solves). Default 1 degree.
  double camera_yaw_prior_sigma_rad = 0.017453292519943295;
  // With at least this many vehicles' records in the map, a new vehicle's camera yaw prior is the
  // fleet's (FleetCameraYawPrior: the records' precision-weighted mean, with their spread as its
  // variance but never narrower than camera_yaw_prior_sigma_rad) instead of mean 0. 0 = off (mapd
  // uses 10). The joint solves keep the fixed prior.
  int fleet_camera_yaw_prior_vehicles = 0;
  // Wheel-speed scale (docs/estimation.md, "Wheel-speed scale"): with a positive value, every
  // subgraph's solve, and each passage of a joint solve, estimates one scale s of the encoders'
  // speeds (ScaledOdometryFactor) with prior mean 1 and this standard deviation; the state is
  // eliminated with the poses, so the map's factor holds its uncertainty. Tyre radius, pressure and
  // wear put a vehicle's encoders 1-3% off; taken as exact, a fleet with 2% errors (one per
  // vehicle) mapped the city with 2.3 m mean error and NEES/dof 26 instead of 0.36 m and 0.7.
  // With AR(1) GNSS the state hurt (mean error 0.91 -> 3.65 m, NEES/dof 0.32 -> 4.0 on a clean
  // fleet), so it stays off by default, in mapd too. 0 = off: the speeds are taken as unbiased.
  double speed_scale_prior_sigma = 0.0;
  // A passage that declares white GNSS noise whose fixes' residuals against its own odometry +
  // GNSS trajectory have a lag-1 correlation above this is estimated with a Gauss-Markov process
  // instead (gnss_correlation.h): the correlation time the residuals' fix-to-fix differences give,
  // the covariance scaled up to the residuals' where they are larger than declared.
  // Errors correlated over minutes, declared white, otherwise place the passage's landmarks metres
  // off with centimetre covariances. 0 = off.
  double correlated_gnss_min_lag1 = 0.5;
  // A map landmark that a subgraph's solve moves further than this from its map estimate (squared
  // Mahalanobis distance in the map's marginal covariance; an honest update moves it by much less,
  // since its move has covariance prior - posterior) is one the passage and the map disagree
  // about: its detections are set aside and the subgraph solved again without them. 0 = off.
  double max_landmark_shift_mahalanobis2 = 25.0;
  // The whole sequential update of one passage is refused (FailedPrecondition: the passage is
  // quarantined, the map unchanged) when it moves a landmark the map has from at least
  // kEstablishedLandmarkPassages passages further than this from its map estimate (squared
  // Mahalanobis distance in its map marginal covariance). The bound on what one passage can do to
  // an established map, whatever it contains: the gate above sets aside the detections of a
  // landmark in disagreement, but a passage can still move landmarks through the others it sees
  // and their correlations. Honest moves have covariance prior - posterior, a small fraction of
  // the prior once a landmark has been seen a few times. 0 = off.
  double max_update_shift_mahalanobis2 = 9.0;
  // A detection whose residual at a subgraph's solution exceeds this many pixel sigmas is an
  // outlier (a neighbouring landmark reported under this one's id, a false detection): it is set
  // aside and the subgraph solved again without it, before the consistency test. 0 = off.
  double max_detection_residual_sigmas = 5.0;
  // A passage more than this fraction of whose detections the test above sets aside
  // (kMinUnfitDetections of them at least) is refused whole (FailedPrecondition, "detections do
  // not fit"): its camera reports landmarks under wrong ids, or detections of nothing, and what
  // the test would leave of it is no more to be trusted. 70 to 93% of the detections of a passage
  // with random landmark ids lie beyond the test; through a young map's joint solve such a passage
  // moved landmarks by 2 to 3 of their sigmas. Honest fleets set aside none of 116,000
  // detections, or a few with the camera twice as noisy as declared. A quarter, counting the
  // detections of landmarks set aside as disagreeing with the map too, refused 46 of 60 passages
  // of a fleet whose detector gives 10% of its detections a neighbour's id, and 2 of 60 with GNSS
  // multipath bursts (docs/results.md, "Passages whose detections do not fit"). Sequential updates
  // only: a joint solve first makes the arriving passage's sequential update, which refuses it.
  // 0 = off.
  double max_unfit_detection_fraction = 0.5;
  static constexpr int kMinUnfitDetections = 10;
  // Adaptive covariance inflation: when a (sub)graph solve's chi-square (2 x final cost) exceeds
  // its degrees of freedom by more than this many standard deviations (sqrt(2 dof)), the data
  // contradict the noise model (e.g. coloured GNSS errors); the passage's measurement covariances
  // are then scaled by the variance factor chi2/dof and the solve is repeated, so the passage
  // enters the map with an honest weight. 0 disables it.
  double inflation_test_sigmas = 4.0;
  // The same test per sensor (odometry, GNSS, camera): the chi-square of one sensor's residuals
  // against their redundancy (their count less their share of the parameters), after the whole
  // graph's test. A sensor more than this many standard deviations noisier than declared has its
  // covariances scaled by the ratio and the graph is solved again (at most twice). It finds what the
  // whole graph's test cannot when the other sensors hold most of the degrees of freedom: a camera
  // with twice its declared pixel noise left the thesis loop's map with a joint NEES/dof of 1.9
  // (1.0 with this test; docs/results.md, "One sensor noisier than declared"). 0 disables it.
  double sensor_test_sigmas = 4.0;
  // A subgraph whose solve leaves a chi2 per degree of freedom above this (before any inflation)
  // refuses the whole passage (FailedPrecondition, "inconsistent: ..."): its measurements
  // contradict their declared noise or the map (a GNSS multipath burst, sigmas declared five
  // times too small, a wrong calibration). Off by default: honest white-noise passages stay near 1
  // (at most 1.28 over 90 city subgraphs) and faulty ones reach 10 to 60, but honest passages
  // with coloured GNSS noise they do not declare reach 29 (5 of 400 loop subgraphs above 10); with
  // it declared and modelled, solves in a wrong minimum reached 10 to 15 until the initial guess
  // was aligned to the map (AlignToMap). On a faulty city fleet 5 quarantines 14 of 60 faulty
  // passages (mean error 1.46 -> 0.92 m); its false refusals on clean fleets: docs/results.md.
  // 0 = never.
  double max_chi2_per_dof = 0.0;
  // Remove the second-order bias of each (sub)graph's MAP solution before it is committed (see
  // CorrectSecondOrderBias): the MAP poses of one passage are decimetres off on average, the same
  // way on every passage of a road, which would otherwise accumulate in the map.
  bool bias_correction = true;
  // Warm-up: the map's first this-many passages are solved jointly (re-solved from no map with
  // each new one) instead of one at a time. A passage applied to a map still metres off enters it
  // as a Gaussian taken at that poor estimate, so with sequential updates alone the order of a
  // young map's first passages stays in the map (about 1-2 cm at 200 passages); the joint solve
  // removes it. 0 disables it.
  int warmup_passages = 8;
  // Re-linearisation of a young map: after the warm-up, each time the map's passage count reaches
  // twice the last joint solve's (16, 32, 64, ... with the default warm-up), the passage is applied
  // by re-solving all the map's passages jointly, as long as the count is at most this. Every
  // passage applied one at a time stays in the map as a Gaussian taken at the estimate of its day;
  // the joint solve takes them all again at today's, so that what the first hundred or so
  // passages left in the map no longer depends on their order or on which of them came first
  // (without it, on 200 passages, up to 1 cm of mean error). The cost is one joint solve at each
  // doubling, about 0.05 s per passage re-solved at 100 landmarks. 0 = off. Not with dc: its
  // covariances ignore the correlations, so its map is too confident to take a re-solve (the
  // guard below would refuse every one).
  int relinearize_until_passages = 128;
  // Guard of the warm-up: a joint solution that does not fit its passages (the consistency test
  // inflated a passage's variance) and puts any landmark further than this (squared Mahalanobis
  // distance) from the sequential update's estimate is not used; the sequential update is. With
  // white noise the two differ by a squared distance below 5 (4.2 at most in the measured runs); a
  // joint solve caught in a wrong minimum by far more. A joint solution that fits every passage is
  // used whatever it moves (joint_solve.cc, FitsEveryPassage). Under coloured GNSS noise the
  // passages do not declare they often differ by more, and the sequential update is used; with it
  // declared, 10 of the 96 joint solves of 8 x 100 loop passages (N = 50) were still refused.
  double max_joint_mahalanobis2 = 36.0;
  // Local re-linearisation (MapUpdater::RelinearizeStale): after each passage, the retained
  // passage whose landmarks have moved furthest since its factors were taken, measured in their
  // current standard deviations, is taken again at today's estimate (ComputePassageRelinearization)
  // when that move exceeds this many sigmas; up to relinearizations_per_passage of them. Unlike the
  // warm-up and re-solves, which count the whole map's passages, this follows each street: one
  // mapped for the first time on day 300 gets the same treatment as the first. 0 = off.
  double relinearize_sigmas = 0.0;
  int relinearizations_per_passage = 1;
  // With N >= 1, the stalest passage is taken again together with up to N - 1 other stale retained
  // passages on its landmarks, in one joint solve against the rest of the map
  // (MapUpdater::AreaOf, ComputeAreaRelinearization): the area's own young-map joint solve; with 1
  // the passage alone, solved whole. 0: the passage's subgraphs applied anew
  // (ComputePassageRelinearization). Not in mapd: with areas of 4 a district mapped late had 5%
  // more error over five seeds than with one passage at a time (docs/results.md, "The per-area
  // joint solve").
  int relinearize_area_passages = 0;
  // Called between the steps of an update (after every solver iteration and every stage of a
  // subgraph's update: at most a few milliseconds apart, mostly well under one), on the thread
  // computing it. A service gives its request threads the CPU there (see server/map_worker.cc).
  // Empty: not called.
  std::function<void()> yield_point;

  absl::Status Validate() const;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_MAP_UPDATE_OPTIONS_H_
