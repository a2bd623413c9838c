#include "client/mapsim/reproduce.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <fstream>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/mapsim/experiment.h"
#include "core/map/sparse_threads.h"

namespace crowdmap {
namespace {

struct Job {
  std::string name;
  ExperimentOptions options;
  bool finished = false;
  absl::StatusOr<ExperimentResult> result = absl::UnknownError("not run");
};

// Thesis table 5.2 (white noise, 1000 passages): error (m) and time per passage (s).
struct ThesisRow {
  int landmarks;
  double cc, dc, cc_gsd, t_cc, t_dc, t_cc_gsd;
};
constexpr ThesisRow kThesisTable[] = {
    {4, 0.29, 0.31, 0.30, 4.90, 4.77, 4.31},   {25, 0.72, 1.10, 0.71, 5.44, 5.51, 4.78},
    {50, 0.51, 1.63, 0.51, 5.90, 5.92, 5.22},  {75, 0.41, 1.86, 0.41, 6.51, 6.63, 5.82},
    {100, 0.31, 2.13, 0.33, 7.02, 7.32, 5.87},
};
struct ThesisRobustness {
  const char* noise;
  double error;
};
constexpr ThesisRobustness kThesisRobustness[] = {
    {"white", 0.51}, {"yaw-bias", 0.67}, {"gnss-ar1", 0.69}, {"ar1+yaw", 0.80}};

// One cell of the grids: what its experiments share but the seed.
ExperimentOptions CellOptions(int landmarks, const std::string& strategy, NoiseConfig noise,
                              bool estimate_camera_yaw = false, int vehicles = 0) {
  ExperimentOptions cell;
  cell.scenario.landmarks = landmarks;
  cell.scenario.noise = noise;
  cell.strategy = strategy;
  cell.update.estimate_camera_yaw = estimate_camera_yaw;
  cell.scenario.vehicles = vehicles;
  // A fleet's vehicles each with their own camera yaw error, 0.5 degrees (1 sigma).
  cell.scenario.vehicle_yaw_bias_sigma_rad = vehicles > 0 ? 0.5 * M_PI / 180.0 : 0.0;
  return cell;
}

// The robustness grid again with the camera yaw estimated, and a fleet of 20 vehicles.
std::vector<ExperimentOptions> CameraYawCells() {
  std::vector<ExperimentOptions> cells;
  for (NoiseConfig noise :
       {NoiseConfig::kWhite, NoiseConfig::kYawBias, NoiseConfig::kGnssAr1, NoiseConfig::kGnssAr1YawBias}) {
    cells.push_back(CellOptions(50, "cc-gsd", noise, /*estimate_camera_yaw=*/true));
  }
  cells.push_back(CellOptions(50, "cc-gsd", NoiseConfig::kWhite, /*estimate_camera_yaw=*/true, /*vehicles=*/20));
  return cells;
}

Job MakeJob(const ReproduceOptions& o, const ExperimentOptions& cell, uint64_t seed) {
  Job job;
  job.options = cell;
  job.name = absl::StrCat("n", cell.scenario.landmarks, "_", cell.strategy, "_", NoiseConfigName(cell.scenario.noise),
                          cell.scenario.vehicles > 0 ? absl::StrCat("_v", cell.scenario.vehicles) : "",
                          cell.update.estimate_camera_yaw ? "_yaw" : "", "_s", seed);
  job.options.scenario.seed = seed;
  job.options.passages = o.passages;
  job.options.update.detections_per_landmark = o.detections_per_landmark;
  return job;
}

bool SameCell(const ExperimentOptions& a, const ExperimentOptions& b) {
  return a.scenario.landmarks == b.scenario.landmarks && a.strategy == b.strategy && a.scenario.noise == b.scenario.noise &&
         a.update.estimate_camera_yaw == b.update.estimate_camera_yaw && a.scenario.vehicles == b.scenario.vehicles;
}

// One cell of the report over the seeds: the results of every seed's experiment, or none if any
// of them failed.
std::vector<const ExperimentResult*> Results(const std::deque<Job>& jobs, const ExperimentOptions& cell) {
  std::vector<const ExperimentResult*> out;
  for (const Job& j : jobs) {
    if (!SameCell(j.options, cell)) continue;
    if (!j.result.ok()) return {};
    out.push_back(&*j.result);
  }
  return out;
}

double Mean(const std::vector<const ExperimentResult*>& rs, const std::function<double(const ExperimentResult&)>& f) {
  double sum = 0.0;
  for (const ExperimentResult* r : rs) sum += f(*r);
  return sum / rs.size();
}

// "mean" over the seeds, or "mean (min-max)" with `range` and more than one seed.
std::string Cell(const std::vector<const ExperimentResult*>& rs, double ExperimentResult::*field, const char* format,
                 bool range = false) {
  if (rs.empty()) return "failed";
  std::string cell = absl::StrFormat(format, Mean(rs, [&](const ExperimentResult& r) { return r.*field; }));
  if (!range || rs.size() < 2) return cell;
  double lo = rs[0]->*field, hi = lo;
  for (const ExperimentResult* r : rs) lo = std::min(lo, r->*field), hi = std::max(hi, r->*field);
  return absl::StrCat(cell, " (", absl::StrFormat(format, lo), "-", absl::StrFormat(format, hi), ")");
}

// The standard deviation the mean NEES over `rs` would have if the maps were consistent.
double NeesSdOfMean(const std::vector<const ExperimentResult*>& rs) {
  const double var = Mean(rs, [](const ExperimentResult& r) {
    return r.nees_per_dof_sd_if_consistent * r.nees_per_dof_sd_if_consistent;
  });
  return std::sqrt(var / rs.size());
}

// The mean NEES over the seeds, with the standard deviation that mean would have for consistent
// maps and the number of seeds: "1.02 ± 0.21 (5)".
std::string NeesCell(const std::vector<const ExperimentResult*>& rs) {
  if (rs.empty()) return "failed";
  const double nees = Mean(rs, [](const ExperimentResult& r) { return r.final_nees_per_dof; });
  const double sd = NeesSdOfMean(rs);
  if (!std::isfinite(sd)) return absl::StrFormat("%.2f (%d)", nees, rs.size());
  return absl::StrFormat("%.2f ± %.2f (%d)", nees, sd, rs.size());
}

// Whether consistency is judged on this cell: CC and CC+GSD with the noise the estimator models
// (white, coloured GNSS noise declared by the passages, and a camera yaw error where it is
// estimated).
bool IsConsistencyCell(const ExperimentOptions& e) {
  const bool modelled = e.scenario.noise == NoiseConfig::kWhite || e.scenario.noise == NoiseConfig::kGnssAr1 ||
                        e.update.estimate_camera_yaw;
  return modelled && (e.strategy == "cc" || e.strategy == "cc-gsd");
}

std::string Report(const ReproduceOptions& o, const std::deque<Job>& jobs, double wall_s) {
  const std::string seeds = o.seeds == 1 ? absl::StrCat("seed ", o.seed)
                                         : absl::StrCat("seeds ", o.seed, " to ", o.seed + o.seeds - 1);
  std::string md = absl::StrFormat(
      "# Reproduction of the thesis's simulation results\n\n"
      "%d passages per experiment, %s, %.0f s wall time on %d parallel jobs. Every figure is the mean over the "
      "seeds (with the range where shown). Errors are the mean landmark distance error after the last passage "
      "(m). NEES is per degree of freedom, averaged over the last 10%% of passages (1 = consistent); after the "
      "± is the standard deviation its mean over the seeds would have if the maps were consistent (errors "
      "common to many landmarks make one run's NEES a draw of few degrees of freedom), and in brackets the "
      "number of seeds: the CC and CC+GSD cells take further seeds until that standard deviation is at most "
      "%.2f (at most %d seeds), and their errors and times are means over the same seeds. Joint NEES uses the "
      "cross-covariances. Time is the median wall time to apply one passage. Thesis times are Python on a Xeon "
      "Silver 4114. Detections per landmark and passage: %s.\n\n",
      o.passages, seeds, wall_s, o.jobs, o.nees_sd_target, o.max_seeds,
      o.detections_per_landmark == 0 ? std::string("all") : absl::StrCat("the last ", o.detections_per_landmark));
  md += "## Table 5.2: white noise\n\n"
        "| N | CC (ours) | CC (thesis) | DC (ours) | DC (thesis) | CC+GSD (ours) | CC+GSD (thesis) | NEES CC | NEES DC "
        "| NEES CC+GSD | joint NEES CC / CC+GSD | ms CC | ms DC | ms CC+GSD | thesis s CC / DC / CC+GSD |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const ThesisRow& t : kThesisTable) {
    const auto cc = Results(jobs, CellOptions(t.landmarks, "cc", NoiseConfig::kWhite));
    const auto dc = Results(jobs, CellOptions(t.landmarks, "dc", NoiseConfig::kWhite));
    const auto gsd = Results(jobs, CellOptions(t.landmarks, "cc-gsd", NoiseConfig::kWhite));
    absl::StrAppendFormat(
        &md,
        "| %d | %s | %.2f | %s | %.2f | %s | %.2f | %s | %s | %s | %s / %s | %s | %s | %s | %.2f / %.2f / %.2f |\n",
        t.landmarks, Cell(cc, &ExperimentResult::final_mean_dist_err_m, "%.3f", true), t.cc,
        Cell(dc, &ExperimentResult::final_mean_dist_err_m, "%.3f"), t.dc,
        Cell(gsd, &ExperimentResult::final_mean_dist_err_m, "%.3f", true), t.cc_gsd, NeesCell(cc),
        Cell(dc, &ExperimentResult::final_nees_per_dof, "%.0f"), NeesCell(gsd),
        Cell(cc, &ExperimentResult::final_joint_nees_per_dof, "%.2f"),
        Cell(gsd, &ExperimentResult::final_joint_nees_per_dof, "%.2f"),
        Cell(cc, &ExperimentResult::median_passage_ms, "%.1f"), Cell(dc, &ExperimentResult::median_passage_ms, "%.1f"),
        Cell(gsd, &ExperimentResult::median_passage_ms, "%.1f"), t.t_cc, t.t_dc, t.t_cc_gsd);
  }
  md += "\n## Robustness: N = 50, CC+GSD; the estimator models the coloured GNSS process the passages declare, "
        "not the camera yaw bias\n\n"
        "CRLB: the Cramer-Rao bound on the mean error of the same passages with the simulated noise (the AR(1) "
        "process modelled exactly; a yaw bias is not noise and has no bound), mean over the seeds.\n\n"
        "| noise | error (ours) | error (thesis) | CRLB | error / CRLB | NEES (ours) | joint NEES | error after 40 "
        "passages (ours) |\n"
        "|---|---|---|---|---|---|---|---|\n";
  for (const ThesisRobustness& t : kThesisRobustness) {
    const auto rs = Results(jobs, CellOptions(50, "cc-gsd", *ParseNoiseConfig(t.noise)));
    std::string after40 = "n/a", ratio = "n/a";
    const auto has40 = [](const ExperimentResult* r) { return r->records.size() >= 40; };
    if (!rs.empty() && std::all_of(rs.begin(), rs.end(), has40)) {
      after40 = absl::StrFormat("%.3f", Mean(rs, [](const ExperimentResult& r) {
                                  return r.records[39].metrics.mean_dist_err_m;
                                }));
    }
    if (!rs.empty()) {
      ratio = absl::StrFormat("%.2f", Mean(rs, [](const ExperimentResult& r) {
                                return r.final_mean_dist_err_m / r.crlb_mean_dist_err_m;
                              }));
    }
    absl::StrAppendFormat(&md, "| %s | %s | %.2f | %s | %s | %s | %s | %s |\n", t.noise,
                          Cell(rs, &ExperimentResult::final_mean_dist_err_m, "%.3f", true), t.error,
                          Cell(rs, &ExperimentResult::crlb_mean_dist_err_m, "%.3f"), ratio, NeesCell(rs),
                          Cell(rs, &ExperimentResult::final_joint_nees_per_dof, "%.2f", true), after40);
  }
  md += "\nThesis: 1.99 m after 40 passages with ar1+yaw (field test: 1.90 m).\n";
  md += "\n## Robustness with each vehicle's camera yaw estimated (mapd's default): N = 50, CC+GSD\n\n"
        "Each passage's graph has a camera yaw offset state, its vehicle's record as prior (a simulated vehicle per "
        "passage, except the fleet row: 20 vehicles, each camera off by its own error, 0.5 degrees sigma). CRLB: the "
        "bound with each vehicle's yaw offset a state, and the estimator's prior on it. Vehicle yaw: the share of "
        "vehicles whose estimate is within 2 of its sigmas of the truth, the mean of (error / sigma)^2, and the "
        "error the vehicles' records share (the mean of their errors; rms over the seeds, mrad) beside their mean "
        "sigma.\n\n"
        "| noise | error (ours) | CRLB | error / CRLB | NEES (ours) | joint NEES | error after 40 passages | "
        "vehicle yaw within 2 sigma | vehicle yaw NEES | shared yaw error / record sigma (mrad) |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n";
  for (const ExperimentOptions& cell : CameraYawCells()) {
    const auto rs = Results(jobs, cell);
    const std::string name = cell.scenario.vehicles > 0
                                 ? absl::StrCat(NoiseConfigName(cell.scenario.noise), ", ", cell.scenario.vehicles,
                                                " vehicles with their own yaw")
                                 : NoiseConfigName(cell.scenario.noise);
    const auto mean = [&](const std::function<double(const ExperimentResult&)>& f, const char* format) {
      return rs.empty() ? std::string("failed") : absl::StrFormat(format, Mean(rs, f));
    };
    const auto has40 = [](const ExperimentResult* r) { return r->records.size() >= 40; };
    const std::string after40 =
        !rs.empty() && std::all_of(rs.begin(), rs.end(), has40)
            ? mean([](const ExperimentResult& r) { return r.records[39].metrics.mean_dist_err_m; }, "%.3f")
            : "n/a";
    std::string shared = "n/a";
    if (cell.scenario.vehicles > 0 && !rs.empty()) {
      const double rms = std::sqrt(Mean(rs, [](const ExperimentResult& r) {
        return r.vehicle_yaw.mean_error_rad * r.vehicle_yaw.mean_error_rad;
      }));
      const double sigma = Mean(rs, [](const ExperimentResult& r) { return r.vehicle_yaw.mean_sigma_rad; });
      shared = absl::StrFormat("%.2f / %.2f", 1e3 * rms, 1e3 * sigma);
    }
    absl::StrAppendFormat(
        &md, "| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s |\n", name,
        Cell(rs, &ExperimentResult::final_mean_dist_err_m, "%.3f", true),
        Cell(rs, &ExperimentResult::crlb_mean_dist_err_m, "%.3f"),
        mean([](const ExperimentResult& r) { return r.final_mean_dist_err_m / r.crlb_mean_dist_err_m; }, "%.2f"),
        NeesCell(rs), Cell(rs, &ExperimentResult::final_joint_nees_per_dof, "%.2f", true), after40,
        cell.scenario.vehicles > 0
            ? mean([](const ExperimentResult& r) { return r.vehicle_yaw.within_2sigma_fraction; }, "%.3f")
            : "n/a",
        cell.scenario.vehicles > 0 ? mean([](const ExperimentResult& r) { return r.vehicle_yaw.nees; }, "%.2f")
                                   : "n/a",
        shared);
  }
  return md;
}

// The further seeds `job`'s cell needs once all its runs so far are done: as many as bring the
// standard deviation of its mean NEES (if consistent) to the target, estimated from those runs.
std::vector<uint64_t> FurtherSeeds(const ReproduceOptions& o, const std::deque<Job>& jobs, const Job& job) {
  if (o.nees_sd_target <= 0.0 || !IsConsistencyCell(job.options)) return {};
  std::vector<const ExperimentResult*> done;
  for (const Job& j : jobs) {
    if (!SameCell(j.options, job.options)) continue;
    if (!j.finished) return {};      // the cell's other runs are not done yet
    if (!j.result.ok()) return {};  // a seed failed: the report shows it
    done.push_back(&*j.result);
  }
  const int runs = static_cast<int>(done.size());  // seeds o.seed .. o.seed + runs - 1
  const double sd = NeesSdOfMean(done);
  if (!std::isfinite(sd) || sd <= o.nees_sd_target) return {};
  const double needed = std::ceil(runs * (sd / o.nees_sd_target) * (sd / o.nees_sd_target));
  std::vector<uint64_t> seeds;
  for (int k = runs; k < std::min<double>(o.max_seeds, needed); ++k) seeds.push_back(o.seed + k);
  return seeds;
}

}  // namespace

absl::Status ReproduceOptions::Validate() const {
  if (passages < 1) return absl::InvalidArgumentError(absl::StrCat("passages: must be >= 1, got ", passages));
  if (jobs < 1) return absl::InvalidArgumentError(absl::StrCat("jobs: must be >= 1, got ", jobs));
  if (seeds < 1) return absl::InvalidArgumentError(absl::StrCat("seeds: must be >= 1, got ", seeds));
  if (max_seeds < seeds) {
    return absl::InvalidArgumentError(absl::StrCat("max_seeds: must be >= seeds (", seeds, "), got ", max_seeds));
  }
  if (!(nees_sd_target >= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat("nees_sd_target: must be >= 0, got ", nees_sd_target));
  }
  MapUpdateOptions update;
  update.detections_per_landmark = detections_per_landmark;
  return update.Validate();
}

absl::Status RunReproduction(const ReproduceOptions& o) {
  if (absl::Status s = o.Validate(); !s.ok()) return s;
  if (o.jobs > 1) {  // the experiments' threads call the BLAS at once
    if (absl::Status s = CheckBlasIsSafeForConcurrentCalls(); !s.ok()) return s;
  }
  std::vector<Job> initial;
  for (uint64_t seed = o.seed; seed < o.seed + o.seeds; ++seed) {
    for (int n : {4, 25, 50, 75, 100}) {
      for (const char* strategy : {"cc", "dc", "cc-gsd"}) {
        initial.push_back(MakeJob(o, CellOptions(n, strategy, NoiseConfig::kWhite), seed));
      }
    }
    for (NoiseConfig noise : {NoiseConfig::kGnssAr1, NoiseConfig::kYawBias, NoiseConfig::kGnssAr1YawBias}) {
      initial.push_back(MakeJob(o, CellOptions(50, "cc-gsd", noise), seed));
    }
    for (const ExperimentOptions& cell : CameraYawCells()) initial.push_back(MakeJob(o, cell, seed));
  }
  // Longest first, so that the two workers finish together.
  std::stable_sort(initial.begin(), initial.end(), [](const Job& a, const Job& b) {
    return a.options.scenario.landmarks > b.options.scenario.landmarks;
  });
  // A deque: jobs added while others run keep every reference valid.
  std::deque<Job> jobs(initial.begin(), initial.end());

  const auto start = std::chrono::steady_clock::now();
  std::mutex mu;  // guards jobs (the list and the results), next, running and the log
  std::condition_variable changed;
  size_t next = 0;
  int running = 0;
  int done = 0;
  auto worker = [&] {
    std::unique_lock<std::mutex> lock(mu);
    while (true) {
      // A running job may still add seeds: wait for it before leaving.
      changed.wait(lock, [&] { return next < jobs.size() || running == 0; });
      if (next == jobs.size()) return;
      Job& job = jobs[next++];
      ++running;
      lock.unlock();
      absl::StatusOr<ExperimentResult> result = RunExperiment(job.options);
      const std::string dir = (std::filesystem::path(o.out_dir) / job.name).string();
      absl::Status written = result.ok() ? WriteExperimentOutputs(job.options, *result, dir) : result.status();
      lock.lock();
      job.result = std::move(result);
      job.finished = true;
      --running;
      ++done;
      if (!written.ok()) {
        spdlog::error("[{}/{}] {}: {}", done, jobs.size(), job.name, written.ToString());
      } else {
        spdlog::info("[{}/{}] {}: error={:.3f} m nees={:.2f} median_ms={:.1f}", done, jobs.size(), job.name,
                     job.result->final_mean_dist_err_m, job.result->final_nees_per_dof, job.result->median_passage_ms);
      }
      const std::vector<uint64_t> further = FurtherSeeds(o, jobs, job);
      if (!further.empty()) {
        spdlog::info("{} N={}: {} further seeds for the NEES", job.options.strategy, job.options.scenario.landmarks,
                     further.size());
      }
      for (uint64_t seed : further) {
        jobs.push_back(MakeJob(o, job.options, seed));
      }
      changed.notify_all();
    }
  };
  std::vector<std::thread> threads;
  for (int t = 0; t < o.jobs; ++t) threads.emplace_back(worker);
  for (std::thread& t : threads) t.join();
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  const std::string md = Report(o, jobs, wall_s);
  const std::filesystem::path path = std::filesystem::path(o.out_dir) / "reproduction.md";
  std::ofstream out(path);
  out << md;
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path.string()));
  spdlog::info("wrote {} ({:.0f} s)", path.string(), wall_s);
  for (const Job& j : jobs) {
    if (!j.result.ok()) return absl::InternalError(absl::StrCat(j.name, ": ", j.result.status().ToString()));
  }
  return absl::OkStatus();
}

}  // namespace crowdmap
