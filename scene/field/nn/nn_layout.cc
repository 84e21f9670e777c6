#include "scene/field/nn/nn_layout.h"

namespace streetsim::field::nn {

size_t NnLayout::Add(const std::string& name, size_t count) {
  const size_t offset = total_;
  blocks_.push_back({name, offset, count});
  total_ += count;
  return offset;
}

}  // namespace streetsim::field::nn
