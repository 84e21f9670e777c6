// NnKernels: pipelines, the gradient scratch, view checks, the Linear trio on the deformation
// field's GEMM shaders (../shaders/field_linear*.comp, field_reduce.comp), element-wise ops and
// column sums. The row ops, tokens, VAE, attention and GRU are in vk_nn_kernels_seq.cc.
#include <algorithm>
#include <limits>

#include "absl/strings/str_cat.h"
#include "render/vulkan/field/field_linear_push.h"
#include "render/vulkan/field/nn/vk_nn_impl.h"
#include "streetsim_spirv.h"

namespace streetsim::field::vknn {

namespace vk = vulkan;

namespace {

using vkgemm::GradPush, vkgemm::LinearPush, vkgemm::ReducePush;
using vkgemm::kAccum, vkgemm::kBias, vkgemm::kTrans;  // field_linear.comp flags
// Rows per partial sum: at least this many (fewer chunks to reduce), more when the scratch would
// pass the buffer range; at most kMaxRowsPerChunk (field_linear_grad.comp loops rows / 16 times,
// nn_colsum.comp rows / 4: far below lavapipe's 65 535) and kMaxChunks chunks (field_reduce.comp's
// loop).
constexpr uint32_t kMinRowsPerChunk = 1024;
constexpr uint32_t kMaxRowsPerChunk = 16384;
constexpr uint32_t kMaxChunks = 16384;

struct ColSumPush {
  uint32_t rows, cols, rows_per_chunk, has_b;
  OffStride a, b;
  uint32_t p_off, p_stride;
};
struct PointwisePush {
  uint32_t rows, cols, op, act, g_off;
  OffStride a, b, c;
};

uint32_t ActCode(nn::Activation a) {
  switch (a) {
    case nn::Activation::kRelu:
      return 0;
    case nn::Activation::kGelu:
      return 1;
    case nn::Activation::kSilu:
      return 2;
  }
  return 0;
}

}  // namespace

bool NnKernels::Impl::CheckViews(vk::Recorder& rec, const char* op, std::initializer_list<Named> views) const {
  if (!rec.status().ok()) return false;
  for (const Named& n : views) {
    const View& v = n.v;
    if (v.buffer == nullptr || !v.buffer->valid()) {
      rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": ", n.name, " has no buffer")));
      return false;
    }
    if (v.stride < v.cols) {
      rec.Fail(absl::InvalidArgumentError(
          absl::StrCat("vk nn ", op, ": ", n.name, " has stride ", v.stride, " < ", v.cols, " columns")));
      return false;
    }
    // Every index the kernels form (offset + r * stride + c) and rows * cols (the element-wise
    // grids) within 32 bits.
    const uint64_t end = v.rows == 0 ? v.offset : uint64_t{v.offset} + uint64_t{v.rows - 1} * v.stride + v.cols;
    const uint64_t span = uint64_t{v.offset} + uint64_t{v.rows} * v.stride;
    if (span > std::numeric_limits<uint32_t>::max() ||
        uint64_t{v.rows} * v.cols > std::numeric_limits<uint32_t>::max()) {
      rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": ", n.name, " (", v.rows, " x ", v.cols,
                                                       ", stride ", v.stride, ", offset ", v.offset,
                                                       ") has indices past 2^32 - 1: split the batch")));
      return false;
    }
    if (end * sizeof(float) > v.buffer->size()) {
      rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": ", n.name, " (", v.rows, " x ", v.cols,
                                                       ", stride ", v.stride, ", offset ", v.offset, ") ends at float ",
                                                       end, ", past its buffer '", v.buffer->name(), "' of ",
                                                       v.buffer->size() / sizeof(float), " floats")));
      return false;
    }
  }
  return true;
}

bool NnKernels::Impl::CheckShape(vk::Recorder& rec, const char* op, const Named& v, uint32_t want_rows,
                                 uint32_t want_cols) const {
  if (!rec.status().ok()) return false;
  if (v.v.rows != want_rows || v.v.cols != want_cols) {
    rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": ", v.name, " is ", v.v.rows, " x ", v.v.cols,
                                                     ", expected ", want_rows, " x ", want_cols)));
    return false;
  }
  return true;
}

bool NnKernels::Impl::CheckParams(vk::Recorder& rec, const char* op, const char* what, const vk::Buffer& b,
                                  uint64_t offset, uint64_t count) const {
  if (!rec.status().ok()) return false;
  if (!b.valid() || (offset + count) * sizeof(float) > b.size() ||
      offset + count > std::numeric_limits<uint32_t>::max()) {
    rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": ", what, " [", offset, ", ", offset + count,
                                                     ") is outside its buffer of ",
                                                     b.valid() ? b.size() / sizeof(float) : 0, " floats")));
    return false;
  }
  return true;
}

bool NnKernels::Impl::CheckScratch(vk::Recorder& rec, const char* op, uint32_t rows, uint64_t floats) const {
  if (!rec.status().ok()) return false;
  if (rows > max_rows || floats > max_param_floats) {
    rec.Fail(absl::FailedPreconditionError(
        absl::StrCat("vk nn ", op, ": ", rows, " rows and ", floats, " parameter floats need a larger Reserve (have ",
                     max_rows, " rows, ", max_param_floats, " floats); call NnKernels::Reserve before recording")));
    return false;
  }
  return true;
}

void NnKernels::Impl::ColSumPartials(vk::Recorder& rec, View a, const View* b, uint32_t p_off,
                                     uint32_t p_stride) const {
  const ColSumPush push{a.rows, a.cols,  rows_per_chunk, b != nullptr ? 1u : 0u, Os(a), b ? Os(*b) : OffStride{},
                        p_off,  p_stride};
  rec.Dispatch(*colsum, {a.buffer, b ? b->buffer : a.buffer, &partials}, push,
               vk::GridFor(uint64_t{Chunks(a.rows)} * DivUp(a.cols, kTile)));
}

void NnKernels::Impl::Reduce(vk::Recorder& rec, uint32_t rows, uint32_t count, uint32_t src_off, uint32_t src_stride,
                             const vk::Buffer& d, uint32_t dst_off) const {
  const ReducePush push{count, Chunks(rows), src_off, src_stride, dst_off};
  rec.Dispatch(*reduce, {&partials, &d}, push, vk::GridFor(DivUp(count, kWg)));
}

void NnKernels::Impl::Pointwise(vk::Recorder& rec, uint32_t op, uint32_t act, View a, View b, View c,
                                const vk::Buffer* p, uint32_t g_off) const {
  if (c.rows == 0 || c.cols == 0) return;
  const PointwisePush push{c.rows, c.cols, op, act, g_off, Os(a), Os(b), Os(c)};
  rec.Dispatch(*pointwise, {a.buffer, b.buffer, c.buffer, p != nullptr ? p : c.buffer}, push,
               vk::GridFor(DivUp(uint64_t{c.rows} * c.cols, kWg)));
}

NnKernels::NnKernels(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
NnKernels::~NnKernels() = default;

absl::StatusOr<std::unique_ptr<NnKernels>> NnKernels::Create(const vk::Context& ctx) {
  auto impl = std::make_unique<Impl>();
  impl->ctx = &ctx;
  const vk::PipelineSpec specs[] = {
      {&impl->linear, "nn field_linear", spirv::field_linear, 4, sizeof(LinearPush), {}},
      {&impl->linear_grad, "nn field_linear_grad", spirv::field_linear_grad, 3, sizeof(GradPush), {}},
      {&impl->reduce, "nn field_reduce", spirv::field_reduce, 2, sizeof(ReducePush), {}},
      {&impl->pointwise, "nn_pointwise", spirv::nn_pointwise, 4, sizeof(PointwisePush), {}},
      {&impl->colsum, "nn_colsum", spirv::nn_colsum, 3, sizeof(ColSumPush), {}},
  };
  if (auto s = vk::CreatePipelines(ctx, specs); !s.ok()) return s;
  if (auto s = CreateSeqPipelines(*impl); !s.ok()) return s;
  return std::unique_ptr<NnKernels>(new NnKernels(std::move(impl)));
}

absl::Status NnKernels::Reserve(uint32_t max_rows, uint32_t max_param_floats) {
  Impl& m = *impl_;
  const uint64_t range_floats = m.ctx->limits().maxStorageBufferRange / sizeof(float);
  const uint32_t rows = std::max(max_rows, m.max_rows), floats = std::max({max_param_floats, m.max_param_floats, 1u});
  // Chunks of the scratch's size within the buffer range, and their count within kMaxChunks.
  uint64_t rpc = kMinRowsPerChunk;
  const uint64_t max_chunks = std::min<uint64_t>(kMaxChunks, range_floats / floats);
  if (max_chunks > 0) rpc = std::max<uint64_t>(rpc, (uint64_t{rows} + max_chunks - 1) / max_chunks);
  rpc = (rpc + 15) / 16 * 16;
  if (max_chunks == 0 || rpc > kMaxRowsPerChunk) {
    return absl::InvalidArgumentError(absl::StrCat("vk nn: Reserve(", rows, " rows, ", floats,
                                                   " parameter floats) needs partial sums past the device's buffer "
                                                   "range of ",
                                                   range_floats, " floats (at most ", kMaxRowsPerChunk,
                                                   " rows per chunk): use smaller batches"));
  }
  const uint64_t bytes = uint64_t{DivUp(rows, rpc)} * floats * sizeof(float);
  if (auto s = vk::EnsureBufferCapacity(*m.ctx, &m.partials, std::max<uint64_t>(bytes, 16), vk::Buffer::Kind::kDevice,
                                        "vk nn partials");
      !s.ok()) {
    return s;
  }
  m.max_rows = rows;
  m.max_param_floats = floats;
  m.rows_per_chunk = static_cast<uint32_t>(rpc);
  return absl::OkStatus();
}

// ---- Linear ----

void NnKernels::Linear(vk::Recorder& rec, const nn::LinearSpec& s, const vk::Buffer& params, View x, View y,
                       bool accumulate) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "linear", {{"x", x}, {"y", y}}) ||
      !m.CheckShape(rec, "linear", {"x", x}, x.rows, static_cast<uint32_t>(s.in)) ||
      !m.CheckShape(rec, "linear", {"y", y}, x.rows, static_cast<uint32_t>(s.out)) ||
      !m.CheckParams(rec, "linear", "W", params, s.w_offset, uint64_t(s.in) * s.out) ||
      (s.bias && !m.CheckParams(rec, "linear", "b", params, s.b_offset, s.out))) {
    return;
  }
  if (x.rows == 0) return;
  const uint32_t flags = (s.bias ? kBias : 0) | (accumulate ? kAccum : 0);
  const LinearPush push{x.rows,
                        x.cols,
                        y.cols,
                        static_cast<uint32_t>(s.w_offset),
                        s.bias ? static_cast<uint32_t>(s.b_offset) : 0u,
                        flags,
                        x.offset,
                        x.stride,
                        y.offset,
                        y.stride};
  rec.Dispatch(*m.linear, {x.buffer, &params, y.buffer, y.buffer}, push,
               vk::GridFor(uint64_t{DivUp(x.rows, kTile)} * DivUp(y.cols, kTile)));
}

void NnKernels::LinearInputGrad(vk::Recorder& rec, const nn::LinearSpec& s, const vk::Buffer& params, View dy, View dx,
                                bool accumulate) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "linear input grad", {{"dy", dy}, {"dx", dx}}) ||
      !m.CheckShape(rec, "linear input grad", {"dy", dy}, dy.rows, static_cast<uint32_t>(s.out)) ||
      !m.CheckShape(rec, "linear input grad", {"dx", dx}, dy.rows, static_cast<uint32_t>(s.in)) ||
      !m.CheckParams(rec, "linear input grad", "W", params, s.w_offset, uint64_t(s.in) * s.out)) {
    return;
  }
  if (dy.rows == 0) return;
  // dx = dy W: the transposed form, W [K = out x N = in].
  const LinearPush push{dy.rows,   dy.cols,
                        dx.cols,   static_cast<uint32_t>(s.w_offset),
                        0u,        kTrans | (accumulate ? kAccum : 0),
                        dy.offset, dy.stride,
                        dx.offset, dx.stride};
  rec.Dispatch(*m.linear, {dy.buffer, &params, dx.buffer, dx.buffer}, push,
               vk::GridFor(uint64_t{DivUp(dy.rows, kTile)} * DivUp(dx.cols, kTile)));
}

void NnKernels::LinearParamGrad(vk::Recorder& rec, const nn::LinearSpec& s, View x, View dy,
                                const vk::Buffer& d_params) {
  const Impl& m = *impl_;
  const uint32_t in = static_cast<uint32_t>(s.in), out = static_cast<uint32_t>(s.out), w = in * out;
  const uint32_t block = w + (s.bias ? out : 0);
  if (!m.CheckViews(rec, "linear param grad", {{"x", x}, {"dy", dy}}) ||
      !m.CheckShape(rec, "linear param grad", {"x", x}, x.rows, in) ||
      !m.CheckShape(rec, "linear param grad", {"dy", dy}, x.rows, out) ||
      !m.CheckParams(rec, "linear param grad", "dW", d_params, s.w_offset, w) ||
      (s.bias && !m.CheckParams(rec, "linear param grad", "db", d_params, s.b_offset, out)) ||
      !m.CheckScratch(rec, "linear param grad", x.rows, block)) {
    return;
  }
  if (x.rows == 0) return;
  // The chunk's block: W at 0, b at in * out.
  const GradPush push{x.rows, out, in,        m.rows_per_chunk, 0u,       s.bias ? w : vkgemm::kNoBias,
                      block,  0u,  dy.offset, dy.stride,        x.offset, x.stride};
  rec.Dispatch(*m.linear_grad, {dy.buffer, x.buffer, &m.partials}, push,
               vk::GridFor(uint64_t{m.Chunks(x.rows)} * DivUp(out, kTile) * DivUp(in + 1, kTile)));
  rec.Barrier();
  if (s.bias && s.b_offset == s.w_offset + w) {
    m.Reduce(rec, x.rows, block, 0, block, d_params, static_cast<uint32_t>(s.w_offset));
  } else {
    m.Reduce(rec, x.rows, w, 0, block, d_params, static_cast<uint32_t>(s.w_offset));
    if (s.bias) m.Reduce(rec, x.rows, out, w, block, d_params, static_cast<uint32_t>(s.b_offset));
  }
  rec.Barrier();
}

// ---- Element-wise ops and column sums ----

void NnKernels::Activation(vk::Recorder& rec, nn::Activation a, View x, View y) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "activation", {{"x", x}, {"y", y}}) ||
      !m.CheckShape(rec, "activation", {"y", y}, x.rows, x.cols)) {
    return;
  }
  m.Pointwise(rec, kOpAct, ActCode(a), x, x, y, nullptr, 0);
}

void NnKernels::ActivationGrad(vk::Recorder& rec, nn::Activation a, View x_pre, View dy, View dx) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "activation grad", {{"x_pre", x_pre}, {"dy", dy}, {"dx", dx}}) ||
      !m.CheckShape(rec, "activation grad", {"dy", dy}, x_pre.rows, x_pre.cols) ||
      !m.CheckShape(rec, "activation grad", {"dx", dx}, x_pre.rows, x_pre.cols)) {
    return;
  }
  m.Pointwise(rec, kOpActGrad, ActCode(a), x_pre, dy, dx, nullptr, 0);
}

void NnKernels::Add(vk::Recorder& rec, View x, View y) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "add", {{"x", x}, {"y", y}}) || !m.CheckShape(rec, "add", {"y", y}, x.rows, x.cols)) return;
  m.Pointwise(rec, kOpAdd, 0, x, x, y, nullptr, 0);
}

void NnKernels::ColumnSums(vk::Recorder& rec, View x, const vk::Buffer& d_params, uint32_t offset) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "column sums", {{"x", x}}) ||
      !m.CheckParams(rec, "column sums", "the sums", d_params, offset, x.cols) ||
      !m.CheckScratch(rec, "column sums", x.rows, x.cols)) {
    return;
  }
  if (x.rows == 0 || x.cols == 0) return;
  m.ColSumPartials(rec, x, nullptr, 0, x.cols);
  rec.Barrier();
  m.Reduce(rec, x.rows, x.cols, 0, x.cols, d_params, offset);
  rec.Barrier();
}

void NnKernels::Gate(vk::Recorder& rec, const vk::Buffer& params, uint32_t gate_offset, View h0, View r, View h) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "gate", {{"h0", h0}, {"r", r}, {"h", h}}) ||
      !m.CheckShape(rec, "gate", {"r", r}, h0.rows, h0.cols) ||
      !m.CheckShape(rec, "gate", {"h", h}, h0.rows, h0.cols) ||
      !m.CheckParams(rec, "gate", "g", params, gate_offset, h0.cols)) {
    return;
  }
  m.Pointwise(rec, kOpGate, 0, h0, r, h, &params, gate_offset);
}

void NnKernels::GateGrad(vk::Recorder& rec, const vk::Buffer& params, uint32_t gate_offset, View dh, View r, View dr,
                         const vk::Buffer& d_params) {
  const Impl& m = *impl_;
  if (!m.CheckViews(rec, "gate grad", {{"dh", dh}, {"r", r}, {"dr", dr}}) ||
      !m.CheckShape(rec, "gate grad", {"r", r}, dh.rows, dh.cols) ||
      !m.CheckShape(rec, "gate grad", {"dr", dr}, dh.rows, dh.cols) ||
      !m.CheckParams(rec, "gate grad", "g", params, gate_offset, dh.cols) ||
      !m.CheckParams(rec, "gate grad", "dg", d_params, gate_offset, dh.cols) ||
      !m.CheckScratch(rec, "gate grad", dh.rows, dh.cols)) {
    return;
  }
  if (dh.rows == 0 || dh.cols == 0) return;
  m.ColSumPartials(rec, dh, &r, 0, dh.cols);
  rec.Barrier();  // dr may be dh or r
  m.Pointwise(rec, kOpGateGrad, 0, dh, dh, dr, &params, gate_offset);
  m.Reduce(rec, dh.rows, dh.cols, 0, dh.cols, d_params, gate_offset);
  rec.Barrier();
}

}  // namespace streetsim::field::vknn
