#ifndef CROWDMAP_TESTS_FUZZ_FUZZ_INPUT_H_
#define CROWDMAP_TESTS_FUZZ_FUZZ_INPUT_H_

// Reads typed values off a fuzzer's input bytes; past the end every read is zero.
#include <cstddef>
#include <cstdint>
#include <cstring>

namespace crowdmap {

class FuzzInput {
 public:
  FuzzInput(const uint8_t* data, size_t size) : data_(data), size_(size) {}

  bool empty() const { return at_ >= size_; }
  uint8_t Byte() { return at_ < size_ ? data_[at_++] : 0; }
  uint32_t U32() {
    uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v = (v << 8) | Byte();
    return v;
  }
  // An index in [0, n); 0 when n is 0.
  size_t Index(size_t n) { return n == 0 ? 0 : U32() % n; }
  // Any double, NaN and infinities included, half of the time; otherwise a value of ordinary
  // size in [-scale, scale], the kind that passes validation and reaches the estimator.
  double Double(double scale) {
    if (Byte() & 1) {
      uint64_t bits = 0;
      for (int i = 0; i < 8; ++i) bits = (bits << 8) | Byte();
      double v;
      std::memcpy(&v, &bits, sizeof v);
      return v;
    }
    return scale * (static_cast<double>(U32()) / 2147483647.5 - 1.0);
  }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t at_ = 0;
};

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_FUZZ_FUZZ_INPUT_H_
