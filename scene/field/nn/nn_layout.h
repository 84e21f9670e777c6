// Where the parameters of the extended field's modules live in one flat array (the field's
// FieldLayout idea, scene/field/field_config.h): every op's Make* function takes its blocks from an
// NnLayout and remembers their offsets; gradients use the same layout.
#pragma once

#include <cstddef>
#include <random>
#include <string>
#include <vector>

namespace streetsim::field::nn {

struct NnParamBlock {
  std::string name;  // e.g. "attn.q.weight"
  size_t offset = 0;
  size_t count = 0;
};

class NnLayout {
 public:
  // Appends a block of `count` parameters; returns its offset.
  size_t Add(const std::string& name, size_t count);
  size_t total() const { return total_; }
  const std::vector<NnParamBlock>& blocks() const { return blocks_; }

 private:
  std::vector<NnParamBlock> blocks_;
  size_t total_ = 0;
};

// U(lo, hi) into params[offset, offset + count).
template <typename T>
void FillUniform(T* params, size_t offset, size_t count, double lo, double hi, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(lo, hi);
  for (size_t i = 0; i < count; ++i) params[offset + i] = static_cast<T>(u(rng));
}

template <typename T>
void FillConstant(T* params, size_t offset, size_t count, double value) {
  for (size_t i = 0; i < count; ++i) params[offset + i] = static_cast<T>(value);
}

}  // namespace streetsim::field::nn
