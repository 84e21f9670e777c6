// Test hooks into the vulkan engine's stages (internal; for tests/render/vulkan_*_test.cc only).
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/engine.h"

namespace streetsim::vulkan_testing {

// Exclusive prefix sum of `values` with the engine's scan kernels. indirect: grids come from the
// setup_args kernel as in a frame; else from the host. saturate: clamp sums at 0xffffffff.
absl::StatusOr<std::vector<uint32_t>> ExclusiveScan(Engine& engine,
                                                    std::span<const uint32_t> values, bool indirect,
                                                    bool saturate, uint32_t* total);

// Stable radix sort of (keys, values) by the low `bits` bits of the keys, through the frame's
// indirect path (the depth sort's args slots).
absl::Status SortPairs(Engine& engine, int bits, std::vector<uint32_t>* keys,
                       std::vector<uint32_t>* values);

// Per-pixel state of the last Render, kept on the device for a backward pass.
struct PixelState {
  std::vector<float> final_t;
  std::vector<uint32_t> n_contrib;
};
absl::StatusOr<PixelState> LastPixelState(Engine& engine, int width, int height);

// Tile instances as (key, value) pairs even when they would pack into one uint (stages.h).
void ForcePairMode(Engine& engine, bool force);

// Caps the deterministic backward's slot buffer (bytes; 0: the device's storage buffer range).
void SetDeterministicSlotLimit(Engine& engine, uint64_t bytes);

int Rerenders(const Engine& engine);  // frames rendered twice to grow instance buffers
uint64_t InstanceCapacity(const Engine& engine);
int ValidationMessages(const Engine& engine);  // 0 unless validation is on and complained
uint32_t SubgroupSize(const Engine& engine);

}  // namespace streetsim::vulkan_testing
