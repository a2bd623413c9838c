// A driver for the fuzz targets where libFuzzer is not linked (the GCC build, CI): it runs the
// target on its seeds, then on random mutations of them, for a fixed time and a fixed random seed,
// so that a run is reproducible. Coverage-guided runs use libFuzzer instead (README, "Fuzzing").
//
//   fuzz_TARGET [--seconds S] [--seed N] [FILE...]   run (FILEs: a crashing input to replay)
//   fuzz_TARGET --write-seeds DIR                    write the seeds as a libFuzzer corpus
#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include "tests/fuzz/fuzz_seeds.h"

namespace {

int Usage() {
  std::cerr << "usage: fuzz_TARGET [--seconds S] [--seed N] [FILE...] | --write-seeds DIR\n";
  return 2;
}

std::string Mutate(std::string input, std::mt19937_64& rng) {
  std::uniform_int_distribution<int> kind(0, 5);
  const int edits = 1 + static_cast<int>(rng() % 8);
  for (int e = 0; e < edits; ++e) {
    const size_t at = input.empty() ? 0 : rng() % input.size();
    switch (kind(rng)) {
      case 0:  // flip a bit
        if (!input.empty()) input[at] = static_cast<char>(input[at] ^ (1 << (rng() % 8)));
        break;
      case 1:  // a random byte
        if (!input.empty()) input[at] = static_cast<char>(rng());
        break;
      case 2:  // insert bytes
        input.insert(at, std::string(1 + rng() % 8, static_cast<char>(rng())));
        break;
      case 3:  // erase bytes
        if (!input.empty()) input.erase(at, 1 + rng() % 16);
        break;
      case 4:  // truncate
        input.resize(at);
        break;
      default:  // copy a slice elsewhere
        if (input.size() > 2) {
          const size_t from = rng() % input.size();
          input.insert(at, input.substr(from, 1 + rng() % 32));
        }
        break;
    }
  }
  return input;
}

const std::string* current = nullptr;

// A failing input is kept in ./fuzz-failure-input, to replay: fuzz_TARGET fuzz-failure-input.
void KeepFailingInput(int signal) {
  if (current != nullptr) {
    const int fd = ::open("fuzz-failure-input", O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) {
      (void)!::write(fd, current->data(), current->size());
      ::close(fd);
    }
    static const char kMessage[] = "fuzz: failure; input written to fuzz-failure-input\n";
    (void)!::write(2, kMessage, sizeof kMessage - 1);
  }
  std::signal(signal, SIG_DFL);
  std::raise(signal);
}

void Run(const std::string& input) {
  current = &input;
  LLVMFuzzerTestOneInput(reinterpret_cast<const uint8_t*>(input.data()), input.size());
  current = nullptr;
}

}  // namespace

int main(int argc, char** argv) {
  double seconds = 10.0;
  uint64_t seed = 1;
  std::vector<std::string> files;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if ((arg == "--seconds" || arg == "--seed" || arg == "--write-seeds") && i + 1 >= argc) return Usage();
    if (arg == "--seconds") {
      seconds = std::atof(argv[++i]);
    } else if (arg == "--seed") {
      seed = std::strtoull(argv[++i], nullptr, 10);
    } else if (arg == "--write-seeds") {
      const std::filesystem::path dir = argv[++i];
      std::filesystem::create_directories(dir);
      const std::vector<std::string> seeds = crowdmap::FuzzSeeds();
      for (size_t k = 0; k < seeds.size(); ++k) {
        std::ofstream(dir / ("seed-" + std::to_string(k)), std::ios::binary) << seeds[k];
      }
      std::cout << "wrote " << seeds.size() << " seeds to " << dir << "\n";
      return 0;
    } else if (arg == "--help" || arg == "-h") {
      Usage();
      return 0;
    } else if (!arg.empty() && arg[0] == '-') {
      return Usage();
    } else {
      files.push_back(arg);
    }
  }
  if (!files.empty()) {  // replay
    for (const std::string& file : files) {
      std::ifstream in(file, std::ios::binary);
      if (!in) {
        std::cerr << "cannot read " << file << "\n";
        return 2;
      }
      Run(std::string(std::istreambuf_iterator<char>(in), {}));
      std::cout << "ran " << file << "\n";
    }
    return 0;
  }
  for (int signal : {SIGABRT, SIGSEGV, SIGFPE, SIGBUS, SIGILL}) std::signal(signal, KeepFailingInput);
  const std::vector<std::string> seeds = crowdmap::FuzzSeeds();
  for (const std::string& s : seeds) Run(s);
  std::mt19937_64 rng(seed);
  const auto start = std::chrono::steady_clock::now();
  const auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };
  int64_t runs = 0;
  double next_report = 5.0;
  while (elapsed() < seconds) {
    std::string input;
    if (seeds.empty() || rng() % 8 == 0) {
      input.resize(rng() % 256);
      for (char& c : input) c = static_cast<char>(rng());
    } else {
      input = Mutate(seeds[rng() % seeds.size()], rng);
    }
    Run(input);
    ++runs;
    if (elapsed() >= next_report) {
      std::cout << "fuzz: " << runs << " inputs in " << static_cast<int>(elapsed()) << " s\n" << std::flush;
      next_report += 5.0;
    }
  }
  std::cout << "fuzz: " << runs << " inputs in " << elapsed() << " s (seed " << seed << "), no failure\n";
  return 0;
}
