#include "render/vulkan/testing.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "render/vulkan/engine_impl.h"

namespace streetsim::vulkan_testing {
namespace {

using vulkan::Buffer;

absl::StatusOr<const vulkan::VulkanEngine*> AsVulkan(const Engine& engine) {
  const auto* v = dynamic_cast<const vulkan::VulkanEngine*>(&engine);
  if (v == nullptr) return absl::InvalidArgumentError("not a vulkan engine");
  return v;
}

absl::StatusOr<Buffer> DeviceBuffer(const vulkan::Context& ctx, size_t bytes, const char* name) {
  return Buffer::Create(ctx, bytes, Buffer::Kind::kDevice, name);
}

// Runs `record` in one submit with the counts/args buffers prepared: counts[index] = n.
absl::Status Run(const vulkan::VulkanEngine& engine, const Buffer& counts, uint32_t index,
                 uint32_t n, const std::function<void(vulkan::Recorder&)>& record) {
  vulkan::DescriptorArena arena(engine.context().device());
  absl::Status status;
  absl::Status submit = engine.context().SubmitAndWait([&](VkCommandBuffer cmd) {
    vulkan::Recorder rec(engine.context(), cmd, &arena);
    uint32_t init[vulkan::kNumCounts] = {};
    init[index] = n;
    rec.Update(counts, 0, init);
    rec.Barrier();
    record(rec);
    status = rec.status();
  });
  if (!status.ok()) return status;
  return submit;
}

}  // namespace

absl::StatusOr<std::vector<uint32_t>> ExclusiveScan(Engine& engine,
                                                    std::span<const uint32_t> values, bool indirect,
                                                    bool saturate, uint32_t* total) {
  auto v = AsVulkan(engine);
  if (!v.ok()) return v.status();
  const vulkan::Context& ctx = (*v)->context();
  const uint32_t n = static_cast<uint32_t>(values.size());
  auto data = DeviceBuffer(ctx, values.size_bytes(), "test_data");
  auto counts = DeviceBuffer(ctx, vulkan::kNumCounts * 4, "test_counts");
  auto args = DeviceBuffer(ctx, vulkan::kNumArgs * vulkan::kArgsSlotBytes, "test_args");
  for (const auto* b : {&data, &counts, &args}) {
    if (!b->ok()) return b->status();
  }
  vulkan::ScanScratch scratch;
  if (absl::Status s = scratch.Ensure(ctx, n); !s.ok()) return s;
  if (absl::Status s = vulkan::UploadBytes(ctx, *data, values.data(), values.size_bytes());
      !s.ok()) {
    return s;
  }
  const uint32_t n_index = indirect ? vulkan::kCountV : vulkan::kCountN;
  absl::Status s = Run(**v, *counts, n_index, n, [&](vulkan::Recorder& rec) {
    const vulkan::Kernels& k = (*v)->kernels();
    if (indirect) {
      const uint32_t setup[2] = {0, 0};
      rec.Dispatch(*k.setup_args, {&*counts, &*args}, setup, vulkan::Grid{1, 1});
      rec.Barrier();
      vulkan::RecordScan(rec, k, scratch, *data, *counts, n_index, n, vulkan::kCountI, saturate,
                         vulkan::Launch{&*args, vulkan::kArgsVScan, 0});
    } else {
      vulkan::RecordScan(rec, k, scratch, *data, *counts, n_index, n, vulkan::kCountI, saturate,
                         vulkan::Launch{nullptr, 0, n});
    }
  });
  if (!s.ok()) return s;
  std::vector<uint32_t> out(n);
  if (s = vulkan::DownloadBytes(ctx, *data, out.data(), values.size_bytes()); !s.ok()) return s;
  uint32_t c[vulkan::kNumCounts];
  if (s = vulkan::DownloadBytes(ctx, *counts, c, sizeof(c)); !s.ok()) return s;
  if (total != nullptr) *total = c[vulkan::kCountI];
  return out;
}

absl::Status SortPairs(Engine& engine, int bits, std::vector<uint32_t>* keys,
                       std::vector<uint32_t>* values) {
  auto v = AsVulkan(engine);
  if (!v.ok()) return v.status();
  if (keys->size() != values->size()) return absl::InvalidArgumentError("size mismatch");
  const vulkan::Context& ctx = (*v)->context();
  const uint32_t n = static_cast<uint32_t>(keys->size());
  const size_t bytes = keys->size() * 4;
  auto k0 = DeviceBuffer(ctx, bytes, "k0"), k1 = DeviceBuffer(ctx, bytes, "k1");
  auto v0 = DeviceBuffer(ctx, bytes, "v0"), v1 = DeviceBuffer(ctx, bytes, "v1");
  auto hist = DeviceBuffer(ctx, vulkan::kRadix * vulkan::DivUp(n, vulkan::kSortBlock) * 4, "hist");
  auto counts = DeviceBuffer(ctx, vulkan::kNumCounts * 4, "test_counts");
  auto args = DeviceBuffer(ctx, vulkan::kNumArgs * vulkan::kArgsSlotBytes, "test_args");
  for (const auto* b : {&k0, &k1, &v0, &v1, &hist, &counts, &args}) {
    if (!b->ok()) return b->status();
  }
  vulkan::ScanScratch scratch;
  if (absl::Status s = scratch.Ensure(ctx, vulkan::kRadix * vulkan::DivUp(n, vulkan::kSortBlock));
      !s.ok()) {
    return s;
  }
  if (absl::Status s = vulkan::UploadBytes(ctx, *k0, keys->data(), bytes); !s.ok()) return s;
  if (absl::Status s = vulkan::UploadBytes(ctx, *v0, values->data(), bytes); !s.ok()) return s;
  int result = 0;
  absl::Status s = Run(**v, *counts, vulkan::kCountV, n, [&](vulkan::Recorder& rec) {
    const vulkan::Kernels& k = (*v)->kernels();
    const uint32_t setup[2] = {0, 0};
    rec.Dispatch(*k.setup_args, {&*counts, &*args}, setup, vulkan::Grid{1, 1});
    rec.Barrier();
    const vulkan::SortBuffers bufs{{&*k0, &*k1}, {&*v0, &*v1}, &*hist};
    result = vulkan::RecordRadixSort(rec, k, scratch, bufs, *counts, vulkan::kCountV,
                                     vulkan::kCountDepthHist, n, 0, bits,
                                     vulkan::Launch{&*args, vulkan::kArgsDepthSort, 0},
                                     vulkan::Launch{&*args, vulkan::kArgsDepthHistScan, 0});
  });
  if (!s.ok()) return s;
  if (s = vulkan::DownloadBytes(ctx, result ? *k1 : *k0, keys->data(), bytes); !s.ok()) return s;
  return vulkan::DownloadBytes(ctx, result ? *v1 : *v0, values->data(), bytes);
}

absl::StatusOr<PixelState> LastPixelState(Engine& engine, int width, int height) {
  auto v = AsVulkan(engine);
  if (!v.ok()) return v.status();
  const size_t pixels = static_cast<size_t>(width) * height;
  if ((*v)->final_t().size() < pixels * 4) return absl::FailedPreconditionError("no such frame");
  PixelState state;
  state.final_t.resize(pixels);
  state.n_contrib.resize(pixels);
  const vulkan::Context& ctx = (*v)->context();
  if (absl::Status s =
          vulkan::DownloadBytes(ctx, (*v)->final_t(), state.final_t.data(), pixels * 4);
      !s.ok()) {
    return s;
  }
  if (absl::Status s =
          vulkan::DownloadBytes(ctx, (*v)->n_contrib(), state.n_contrib.data(), pixels * 4);
      !s.ok()) {
    return s;
  }
  return state;
}

void ForcePairMode(Engine& engine, bool force) {
  if (auto* v = dynamic_cast<vulkan::VulkanEngine*>(&engine)) v->set_force_pair_mode(force);
}

void SetDeterministicSlotLimit(Engine& engine, uint64_t bytes) {
  if (auto* v = dynamic_cast<vulkan::VulkanEngine*>(&engine)) v->set_det_slot_limit_bytes(bytes);
}

int Rerenders(const Engine& engine) {
  auto v = AsVulkan(engine);
  return v.ok() ? (*v)->rerenders() : -1;
}

uint64_t InstanceCapacity(const Engine& engine) {
  auto v = AsVulkan(engine);
  return v.ok() ? (*v)->instance_capacity() : 0;
}

int ValidationMessages(const Engine& engine) {
  auto v = AsVulkan(engine);
  return v.ok() ? (*v)->context().validation_messages() : -1;
}

uint32_t SubgroupSize(const Engine& engine) {
  auto v = AsVulkan(engine);
  return v.ok() ? (*v)->context().subgroup().size : 0;
}

}  // namespace streetsim::vulkan_testing
