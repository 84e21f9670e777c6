// The serving form's per-Gaussian tables (docs/field.md "Serving form"): each moving Gaussian's
// spline control points, stored in about 240 B for S3Gaussian's field so that a served dynamic
// scene holds little beyond the Gaussians themselves.
//
// - Position: the line between the first and the last control point (floats) plus each control
//   point's residual from it, int8 with one step per channel. A Gaussian that drives at a steady
//   speed has a small residual, so its quantisation step stays fine however far it travels.
// - The other modelled groups, in blocks: the appearance (DC colour and SH bands 1-3 together) and
//   each of the extended field's geometric groups on its own. A block is its time-mean per channel
//   (int8, an offset and step per group) plus a low-rank change over time, sum_j s_j u_j(t) v_j:
//   u_j per control point and v_j per channel, both int8. On trained KITTI scenes the appearance's
//   change over time is close to rank 1 (one colour direction that fades in and out), and rank 1
//   serves it as well as every channel kept per control point. A geometric block keeps rank =
//   its channels (no approximation beyond the quantisation).
//
// Steps and scales are bfloat16: they only scale a quantisation step, where 0.4 % does not matter.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

// The channel groups a form can model, in table order.
// kColour is the DC term, kShBands the SH bands 1-3 (S3Gaussian's field changes all of them, and on
// a trained KITTI scene their change over time is worth 1.2 dB of held-out PSNR).
enum class FormGroup : uint8_t {
  kPosition = 0,
  kColour = 1,
  kLogScale = 2,
  kRotation = 3,
  kOpacity = 4,
  kShBands = 5
};
inline constexpr int kFormGroups = 6;
inline constexpr int kFormGroupChannels[kFormGroups] = {3, 3, 3, 4, 1, 45};
// The appearance's groups (FormGroup bits): one block of the tables; every other group is geometry.
inline constexpr uint32_t kAppearanceGroups =
    (1u << static_cast<int>(FormGroup::kColour)) | (1u << static_cast<int>(FormGroup::kShBands));
inline constexpr int kDefaultAppearanceRank = 1;
inline constexpr int kMaxAppearanceRank = 8;

// Where group g's channels live in a store: data[i * stride + offset + c], c < kFormGroupChannels[g].
template <typename F>
struct GroupSpan {
  F* data;
  int stride, offset;
};
GroupSpan<float> SpanOf(FormGroup g, GaussianStore* s);
GroupSpan<const float> SpanOf(FormGroup g, const GaussianStore* s);

uint16_t ToBf16(float x);       // round to nearest
uint16_t Bf16AtLeast(float x);  // the smallest bfloat16 >= x (x >= 0 finite)
float FromBf16(uint16_t b);

class FormTables {
 public:
  FormTables() = default;
  // coef: [rows][control_points][3 + channels]: position, then the modelled groups' channels in
  // group order (the least-squares control points). groups: FormGroup bits, position included.
  static FormTables Quantise(const std::vector<float>& coef, size_t rows, int control_points, uint32_t groups,
                             int appearance_rank, ThreadPool& pool);

  // Writes the rows' modelled channels of `groups` (FormGroup bits; row r of the tables is Gaussian
  // rows[r] of `out`) at the spline's weights w[0..kTaps) of the control points k, k + 1, ...,
  // which fall at `line` on the line between the first and the last control point
  // (ServingForm::Spline).
  template <int kTaps>
  void Evaluate(int k, const float* w, float line, const uint32_t* rows, GaussianStore* out, ThreadPool& pool,
                uint32_t groups = ~0u) const;
  // The same values, every modelled channel, into an engine's planes (Engine::WritablePlanes) of
  // the same Gaussians; `rows` ascending. With `geometry`, the same pass also writes every group
  // but the appearance into that store (Evaluate's values: what the LiDAR reads). Returns false,
  // with the rows written or not, when a value came out non-finite or a rotation zero (what a
  // render must not read).
  template <int kTaps>
  bool EvaluateIntoPlanes(int k, const float* w, float line, const uint32_t* rows, const ScenePlanes& out,
                          ThreadPool& pool, GaussianStore* geometry = nullptr) const;

  size_t rows() const { return rows_; }
  int control_points() const { return control_points_; }
  int appearance_rank() const;  // 0 when the appearance is not modelled
  size_t bytes() const;         // host bytes of every table

  // The tables as fixed-size records of 32-bit words, one per moving Gaussian, for a device
  // kernel (render/vulkan/field/shaders/serving_form.comp reads this layout): record r holds
  // Gaussian rows[r]'s index, then row r's slice of every table above, each slice starting on a
  // word (floats as floats, bfloat16 two to a word, int8 four to a word, little end first). One
  // record per row keeps a row's reads together and lets the rows split into buffers anywhere.
  struct RecordLayout {
    uint32_t record_words = 0;
    uint32_t ends = 0, position_step = 0, q_position = 0;  // word offsets in a record (row index: 0)
    struct Block {
      uint32_t groups = 0, channels = 0, rank = 0, group_count = 0;
      uint32_t base_offset = 0, base_step = 0, scale = 0, q_base = 0, q_u = 0, q_v = 0;  // word offsets
    };
    std::vector<Block> blocks;
  };
  RecordLayout MakeRecordLayout() const;
  // Records [begin, end) of `layout` (MakeRecordLayout's) into out ((end - begin) * record_words).
  void PackRecords(const RecordLayout& layout, const uint32_t* rows, size_t begin, size_t end, uint32_t* out) const;

 private:
  friend class ServingFormCodec;  // serving_form_io.cc

  struct Block {
    uint32_t groups = 0;  // FormGroup bits
    int channels = 0;     // of its groups, in group order
    int rank = 0;
    std::vector<float> base_offset;    // [rows][groups in the block]
    std::vector<uint16_t> base_step;   // [rows][groups in the block], bfloat16
    std::vector<int8_t> q_base;        // [rows][channels]: the time-mean
    std::vector<uint16_t> scale;       // [rows][rank], bfloat16: s_j
    std::vector<int8_t> q_u;           // [rows][rank][control points]
    std::vector<int8_t> q_v;           // [rows][rank][channels]
    int group_count() const;
    void Resize(size_t rows, int control_points);
  };
  // The blocks a form of `groups` has, with their ranks (the codec rebuilds them from the file).
  static std::vector<Block> BlocksOf(uint32_t groups, int appearance_rank, int control_points);
  // One row's values at the spline (Evaluate's and EvaluateIntoPlanes's common parts): its
  // position; S3Gaussian's appearance at rank 1 (48 SH floats, store order); a block's channels.
  template <int kTaps>
  void PositionAt(size_t r, int k, const float* w, float line, float p[3]) const;
  template <int kTaps>
  void AppearanceRank1At(size_t r, int k, const float* w, float* sh48) const;
  template <int kTaps>
  void BlockAt(const Block& bl, size_t r, int k, const float* w, float* vals) const;
  // The one appearance block at rank 1 over SH degree 3 Gaussians (the fixed-count fast path).
  bool IsS3Rank1(int sh_degree) const;

  size_t rows_ = 0;
  int control_points_ = 0;
  uint32_t groups_ = 0;
  std::vector<float> position_ends_;     // [rows][2][3]: the first and last control points
  std::vector<uint16_t> position_step_;  // [rows][3], bfloat16
  std::vector<int8_t> q_position_;       // [rows][control points][3]: residual from the line
  std::vector<Block> blocks_;
};

}  // namespace streetsim::field
