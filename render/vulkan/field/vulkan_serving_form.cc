#include "render/vulkan/field/vulkan_serving_form.h"

#include <algorithm>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/engine_impl.h"
#include "render/vulkan/pipeline.h"
#include "streetsim_spirv.h"

namespace streetsim::field {

namespace vk = vulkan;

namespace {

constexpr uint32_t kServingFormWg = 256;  // serving_form.comp: local_size_x (FIELD_WG)

struct FormPush {
  uint32_t rows, record_words, k, taps;
  float w[4];
  float line;
  uint32_t s3_rank1;  // serving_form.comp's fast path
};

}  // namespace

struct VulkanServingForm::Impl {
  // Declared first: destroyed last, after the buffers and the pipeline of its device.
  std::shared_ptr<const vk::Context> ctx;
  vk::VulkanEngine* engine = nullptr;
  std::unique_ptr<vk::ComputePipeline> pipeline;
  vk::Buffer desc;
  std::vector<vk::Buffer> tables;
  std::vector<uint32_t> table_rows;  // records per buffer
  uint32_t record_words = 0;
  bool s3_rank1 = false;
  size_t bytes = 0;
  // The spline's time axis, copied so that the form need not outlive this.
  ServingForm::SplineAxis axis;
};

VulkanServingForm::VulkanServingForm(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
VulkanServingForm::~VulkanServingForm() = default;

absl::StatusOr<std::unique_ptr<VulkanServingForm>> VulkanServingForm::Create(Engine& engine, const ServingForm& form,
                                                                             size_t max_buffer_bytes) {
  auto* vengine = dynamic_cast<vk::VulkanEngine*>(&engine);
  if (vengine == nullptr) {
    return absl::FailedPreconditionError("the serving form's kernel needs a Vulkan engine");
  }
  auto impl = std::make_unique<Impl>();
  impl->ctx = vengine->shared_context();
  impl->engine = vengine;
  impl->axis = form.spline_axis();
  const vk::Context& c = *impl->ctx;
  const FormTables& t = form.tables();
  const FormTables::RecordLayout layout = t.MakeRecordLayout();
  impl->record_words = layout.record_words;
  impl->s3_rank1 =
      layout.blocks.size() == 1 && layout.blocks[0].groups == kAppearanceGroups && layout.blocks[0].rank == 1;

  std::vector<uint32_t> desc = {static_cast<uint32_t>(layout.blocks.size()), layout.ends, layout.position_step,
                                layout.q_position, static_cast<uint32_t>(t.control_points())};
  for (const FormTables::RecordLayout::Block& b : layout.blocks) {
    desc.insert(desc.end(), {b.groups, b.channels, b.rank, b.group_count, b.base_offset, b.base_step, b.scale,
                             b.q_base, b.q_u, b.q_v});
  }
  if (auto b = vk::Buffer::Create(c, desc.size() * 4, vk::Buffer::Kind::kDevice, "serving form desc"); b.ok()) {
    impl->desc = *std::move(b);
  } else {
    return b.status();
  }
  if (absl::Status s = vk::UploadBytes(c, impl->desc, desc.data(), desc.size() * 4); !s.ok()) return s;

  // The records in buffers of at most max_buffer_bytes (whole workgroups of records each).
  const size_t record_bytes = size_t{layout.record_words} * 4;
  size_t cap = c.limits().maxStorageBufferRange;
  if (max_buffer_bytes > 0) cap = std::min(cap, max_buffer_bytes);
  const size_t per_buffer = std::max<size_t>(1, cap / record_bytes);
  const std::vector<uint32_t>& rows = form.moving_rows();
  for (size_t begin = 0; begin < rows.size(); begin += per_buffer) {
    const size_t end = std::min(rows.size(), begin + per_buffer);
    absl::StatusOr<vk::Buffer> b = vk::Buffer::Create(c, (end - begin) * record_bytes, vk::Buffer::Kind::kDevice,
                                                     absl::StrCat("serving form tables ", impl->tables.size()));
    if (!b.ok()) return b.status();
    // Packed straight into the staging chunks (granularity: whole records).
    absl::Status s = vk::UploadWith(c, *b, (end - begin) * record_bytes, record_bytes,
                                    [&](size_t from, size_t to, std::byte* out) {
                                      t.PackRecords(layout, rows.data(), begin + from / record_bytes,
                                                    begin + to / record_bytes, reinterpret_cast<uint32_t*>(out));
                                    });
    if (!s.ok()) return s;
    impl->tables.push_back(*std::move(b));
    impl->table_rows.push_back(static_cast<uint32_t>(end - begin));
    impl->bytes += (end - begin) * record_bytes;
  }
  const vk::PipelineSpec specs[] = {
      {&impl->pipeline, "serving_form", spirv::serving_form, 7, sizeof(FormPush), {}}};
  if (absl::Status s = vk::CreatePipelines(c, specs); !s.ok()) return s;
  return std::unique_ptr<VulkanServingForm>(new VulkanServingForm(std::move(impl)));
}

absl::Status VulkanServingForm::WriteAt(int64_t time_us, DeviceScene* scene) {
  Impl& m = *impl_;
  if (scene == nullptr || scene->sh_degree() != 3) {
    return absl::InvalidArgumentError("serving form on Vulkan: a scene with SH degree 3 Gaussians expected");
  }
  FormPush push{};
  const ServingForm::Spline spline = m.axis.At(time_us);
  push.record_words = m.record_words;
  push.k = static_cast<uint32_t>(spline.k);
  push.taps = static_cast<uint32_t>(spline.taps);
  std::copy_n(spline.w, 4, push.w);
  push.line = spline.line;
  push.s3_rank1 = m.s3_rank1 ? 1u : 0u;
  return m.engine->WriteSceneOnDevice(scene, [&](vk::Recorder& rec, const vk::VulkanScene& s) {
    const vk::SceneBuffers sb = s.view();
    for (size_t b = 0; b < m.tables.size(); ++b) {
      push.rows = m.table_rows[b];
      rec.Dispatch(*m.pipeline, {&m.tables[b], &m.desc, sb.gauss, sb.sh[0], sb.sh[1], sb.sh[2], sb.sh[3]}, push,
                   vk::GridFor((push.rows + kServingFormWg - 1) / kServingFormWg));
    }
  });
}

std::string VulkanServingForm::device() const { return "vulkan"; }

size_t VulkanServingForm::device_bytes() const { return impl_->bytes; }
int VulkanServingForm::table_buffers() const { return static_cast<int>(impl_->tables.size()); }
std::string VulkanServingForm::device_description() const { return impl_->ctx->description(); }

}  // namespace streetsim::field
