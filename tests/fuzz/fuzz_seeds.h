#ifndef CROWDMAP_TESTS_FUZZ_FUZZ_SEEDS_H_
#define CROWDMAP_TESTS_FUZZ_FUZZ_SEEDS_H_

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace crowdmap {

// Inputs a fuzz target starts from (each target defines it): the standalone driver mutates them,
// and `--write-seeds DIR` writes them as a corpus for libFuzzer.
std::vector<std::string> FuzzSeeds();

}  // namespace crowdmap

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

#endif  // CROWDMAP_TESTS_FUZZ_FUZZ_SEEDS_H_
