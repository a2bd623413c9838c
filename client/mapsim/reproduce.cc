#include "client/mapsim/reproduce.h"

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/mapsim/experiment.h"

namespace crowdmap {
namespace {

struct Job {
  std::string name;
  ExperimentOptions options;
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

Job MakeJob(const ReproduceOptions& o, int landmarks, const std::string& strategy, NoiseConfig noise) {
  Job job;
  job.name = absl::StrCat("n", landmarks, "_", strategy, "_", NoiseConfigName(noise));
  job.options.scenario.landmarks = landmarks;
  job.options.scenario.noise = noise;
  job.options.scenario.seed = o.seed;
  job.options.passages = o.passages;
  job.options.strategy = strategy;
  return job;
}

const ExperimentResult* Find(const std::vector<Job>& jobs, const std::string& name) {
  for (const Job& j : jobs) {
    if (j.name == name && j.result.ok()) return &*j.result;
  }
  return nullptr;
}

std::string Cell(const ExperimentResult* r, double ExperimentResult::*field, const char* format) {
  return r ? absl::StrFormat(format, r->*field) : std::string("failed");
}

std::string Report(const ReproduceOptions& o, const std::vector<Job>& jobs, double wall_s) {
  std::string md = absl::StrFormat(
      "# Reproduction of the thesis's simulation results\n\n"
      "%d passages per experiment, seed %d, %.0f s wall time on %d parallel jobs. Errors are the mean landmark "
      "distance error after the last passage (m); NEES is per degree of freedom, averaged over the last 10%% of "
      "passages (1 = consistent); time is the median wall time to apply one passage. Thesis times are Python "
      "on a Xeon Silver 4114.\n\n",
      o.passages, o.seed, wall_s, o.jobs);
  md += "## Table 5.2: white noise\n\n"
        "| N | CC (ours) | CC (thesis) | DC (ours) | DC (thesis) | CC+GSD (ours) | CC+GSD (thesis) | NEES CC | NEES DC "
        "| NEES CC+GSD | ms CC | ms DC | ms CC+GSD | thesis s CC / DC / CC+GSD |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const ThesisRow& t : kThesisTable) {
    const ExperimentResult* cc = Find(jobs, absl::StrCat("n", t.landmarks, "_cc_white"));
    const ExperimentResult* dc = Find(jobs, absl::StrCat("n", t.landmarks, "_dc_white"));
    const ExperimentResult* gsd = Find(jobs, absl::StrCat("n", t.landmarks, "_cc-gsd_white"));
    absl::StrAppendFormat(&md, "| %d | %s | %.2f | %s | %.2f | %s | %.2f | %s | %s | %s | %s | %s | %s | %.2f / %.2f / %.2f |\n",
                          t.landmarks, Cell(cc, &ExperimentResult::final_mean_dist_err_m, "%.3f"), t.cc,
                          Cell(dc, &ExperimentResult::final_mean_dist_err_m, "%.3f"), t.dc,
                          Cell(gsd, &ExperimentResult::final_mean_dist_err_m, "%.3f"), t.cc_gsd,
                          Cell(cc, &ExperimentResult::final_nees_per_dof, "%.2f"),
                          Cell(dc, &ExperimentResult::final_nees_per_dof, "%.2f"),
                          Cell(gsd, &ExperimentResult::final_nees_per_dof, "%.2f"),
                          Cell(cc, &ExperimentResult::median_passage_ms, "%.1f"),
                          Cell(dc, &ExperimentResult::median_passage_ms, "%.1f"),
                          Cell(gsd, &ExperimentResult::median_passage_ms, "%.1f"), t.t_cc, t.t_dc, t.t_cc_gsd);
  }
  md += "\n## Robustness: N = 50, CC+GSD, the estimator assumes white noise\n\n"
        "| noise | error (ours) | error (thesis) | NEES (ours) | error after 40 passages (ours) |\n"
        "|---|---|---|---|---|\n";
  for (const ThesisRobustness& t : kThesisRobustness) {
    const Job* job = nullptr;
    for (const Job& j : jobs) {
      if (j.name == absl::StrCat("n50_cc-gsd_", t.noise)) job = &j;
    }
    const ExperimentResult* r = job && job->result.ok() ? &*job->result : nullptr;
    const std::string after40 = r && r->records.size() >= 40
                                    ? absl::StrFormat("%.3f", r->records[39].metrics.mean_dist_err_m)
                                    : std::string("n/a");
    absl::StrAppendFormat(&md, "| %s | %s | %.2f | %s | %s |\n", t.noise,
                          Cell(r, &ExperimentResult::final_mean_dist_err_m, "%.3f"), t.error,
                          Cell(r, &ExperimentResult::final_nees_per_dof, "%.2f"), after40);
  }
  md += "\nThesis: 1.99 m after 40 passages with ar1+yaw (field test: 1.90 m).\n";
  return md;
}

}  // namespace

absl::Status RunReproduction(const ReproduceOptions& o) {
  std::vector<Job> jobs;
  for (int n : {4, 25, 50, 75, 100}) {
    for (const char* strategy : {"cc", "dc", "cc-gsd"}) jobs.push_back(MakeJob(o, n, strategy, NoiseConfig::kWhite));
  }
  for (NoiseConfig noise : {NoiseConfig::kGnssAr1, NoiseConfig::kYawBias, NoiseConfig::kGnssAr1YawBias}) {
    jobs.push_back(MakeJob(o, 50, "cc-gsd", noise));
  }
  // Longest first, so that the two workers finish together.
  std::stable_sort(jobs.begin(), jobs.end(), [](const Job& a, const Job& b) {
    return a.options.scenario.landmarks > b.options.scenario.landmarks;
  });

  const auto start = std::chrono::steady_clock::now();
  std::atomic<size_t> next{0};
  std::atomic<int> done{0};
  std::mutex log_mutex;
  auto worker = [&] {
    for (size_t i = next++; i < jobs.size(); i = next++) {
      Job& job = jobs[i];
      job.result = RunExperiment(job.options);
      const std::string dir = (std::filesystem::path(o.out_dir) / job.name).string();
      absl::Status written = job.result.ok() ? WriteExperimentOutputs(job.options, *job.result, dir) : job.result.status();
      std::lock_guard<std::mutex> lock(log_mutex);
      const int finished = ++done;
      if (!written.ok()) {
        spdlog::error("[{}/{}] {}: {}", finished, jobs.size(), job.name, written.ToString());
      } else {
        spdlog::info("[{}/{}] {}: error={:.3f} m nees={:.2f} median_ms={:.1f}", finished, jobs.size(), job.name,
                     job.result->final_mean_dist_err_m, job.result->final_nees_per_dof, job.result->median_passage_ms);
      }
    }
  };
  std::vector<std::thread> threads;
  for (int t = 0; t < std::max(1, o.jobs); ++t) threads.emplace_back(worker);
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
