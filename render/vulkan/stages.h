// The frame's stages as recording functions over a Recorder (internal). One function per stage
// file: project.cc (a, b), scan.cc, radix_sort.cc (c, f), binning.cc (d, e, g), blend.cc (h).
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <memory>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/camera.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::vulkan {

// Mirrors shaders/common.glsl; change both together.
inline constexpr uint32_t kWorkgroupSize = 256;
inline constexpr uint32_t kScanBlock = 1024;
inline constexpr uint32_t kSortBlock = 8192;
inline constexpr uint32_t kRadix = 16;
inline constexpr uint32_t kRadixBits = 4;
inline constexpr uint32_t kTileSize = 16;
inline constexpr uint32_t kMaxScanLevels = 4;
inline constexpr int kShGroup = 4;      // SH coefficients per buffer (common.glsl: SH_GROUP)
inline constexpr int kMaxShGroups = 4;  // 16 coefficients at degree 3
// Floats per Gaussian in SH group g for K coefficients per channel.
inline int ShGroupFloats(int K, int g) { return 3 * std::clamp(K - g * kShGroup, 0, kShGroup); }

enum CountIndex : uint32_t {
  kCountN = 0,
  kCountV = 1,
  kCountI = 2,
  kCountIc = 3,
  kCountDepthHist = 4,
  kCountTileHist = 5,
  kCountSink = 6,
  kNumCounts = 16,
};
enum ArgsSlot : uint32_t {
  kArgsVScan = 0,
  kArgsDepthSort = 4,
  kArgsDepthHistScan = 5,
  kArgsVThreads = 9,
  kArgsTileSort = 10,
  kArgsTileHistScan = 11,
  kArgsIcThreads = 15,
  kNumArgs = 16,
};
inline constexpr VkDeviceSize kArgsSlotBytes = 16;  // uvec4: VkDispatchIndirectCommand + pad

inline uint64_t DivUp(uint64_t a, uint64_t b) { return (a + b - 1) / b; }

// Every compute pipeline of the frame, built once per engine.
struct Kernels {
  std::unique_ptr<ComputePipeline> project, compact, setup_args;
  std::unique_ptr<ComputePipeline> scan_block, scan_block_saturating, scan_add, scan_add_saturating;
  std::unique_ptr<ComputePipeline> radix_hist, radix_scatter, radix_scatter_keys_only;
  std::unique_ptr<ComputePipeline> gather_sorted, emit, tile_ranges, blend;
  // Backward (backward.cc). blend_backward is null on devices without subgroup arithmetic; it is
  // the float-atomic variant when the device has shaderBufferFloat32AtomicAdd, else the
  // compare-and-swap one.
  // project_backward: one pipeline per SH degree (specialization constant).
  std::unique_ptr<ComputePipeline> blend_backward;
  // Deterministic mode (BackwardOptions::deterministic): per-tile-instance slots summed in a
  // fixed order, no atomics; built on first use (EnsureDeterministicKernels).
  std::unique_ptr<ComputePipeline> blend_backward_det, blend_backward_reduce;
  std::array<std::unique_ptr<ComputePipeline>, 4> project_backward;

  static absl::StatusOr<std::unique_ptr<Kernels>> Create(const Context& ctx);
};

// How a stage learns its grid: from the host (element count known at record time) or from a slot
// of the args buffer written on the device by setup_args.
struct Launch {
  const Buffer* args = nullptr;  // null: direct
  uint32_t slot = 0;             // first args slot (scans use slot + level)
  uint64_t n = 0;                // direct: element count
};

// Scratch for the block sums of the upper scan levels, shared by every scan of a frame (they run
// one after another).
class ScanScratch {
 public:
  // Sizes the levels for scans of up to `max_elements`.
  absl::Status Ensure(const Context& ctx, uint64_t max_elements);
  const Buffer& level(int k) const { return levels_[k - 1]; }  // k = 1..kMaxScanLevels-1

 private:
  std::array<Buffer, kMaxScanLevels - 1> levels_;
};

// Number of scan levels for up to `capacity` elements (the top level is a single block).
int ScanLevels(uint64_t capacity);

// --- scan.cc -------------------------------------------------------------------------------------
// Exclusive prefix sum in place over data[0, counts[n_index]); the total goes to
// counts[total_index]. `capacity` bounds counts[n_index] and fixes the number of levels.
void RecordScan(Recorder& rec, const Kernels& k, const ScanScratch& scratch, const Buffer& data,
                const Buffer& counts, uint32_t n_index, uint64_t capacity, uint32_t total_index,
                bool saturate, const Launch& launch);

// --- radix_sort.cc -------------------------------------------------------------------------------
struct SortBuffers {
  const Buffer* keys[2];
  const Buffer* vals[2];  // null: keys-only sort
  const Buffer* hist;     // >= kRadix * DivUp(capacity, kSortBlock) uints
};
// Stable LSD sort of (keys[0], vals[0])[0, counts[n_index]) by key bits [first_bit,
// first_bit + bits), 4 bits per pass. Returns which pair holds the result (0 or 1). `blocks`
// gives the grid of the histogram and scatter kernels, `hist_scan` that of the histogram scan
// (over counts[hist_n_index] = 16 * blocks elements).
int RecordRadixSort(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                    const SortBuffers& bufs, const Buffer& counts, uint32_t n_index,
                    uint32_t hist_n_index, uint64_t capacity, int first_bit, int bits,
                    const Launch& blocks, const Launch& hist_scan);
int RadixPasses(int bits);

// --- project.cc ----------------------------------------------------------------------------------
// Packs (mean, logit), (log-scale, 0), quaternion as the 3 vec4 per Gaussian that the projection
// kernels read with aligned loads (the camera scene's and the LiDAR's layout) into `gauss`
// (>= 48 bytes per Gaussian).
absl::Status UploadGaussianGeometry(const Context& ctx, const Buffer& gauss, const GaussianStore& store);
struct ProjectPush {
  float R[9];
  float t[3];
  float c[3];
  float fx, fy, cx, cy;
  int32_t width, height, tiles_x, tiles_y;
  uint32_t n;
  int32_t sh_degree;
};
static_assert(sizeof(ProjectPush) == 100);
ProjectPush MakeProjectPush(const PinholeCamera& camera, uint32_t n, int sh_degree);

struct SceneBuffers {
  const Buffer* gauss;             // 3 vec4 per Gaussian
  const Buffer* sh[kMaxShGroups];  // ShGroupFloats per Gaussian each; unused groups: any buffer
  const Buffer* splats;            // 3 vec4 per Gaussian, by Gaussian id
  const Buffer* sorted_splats;     // 3 vec4 per visible Gaussian, by depth rank
  const Buffer* rects;             // uvec2 per Gaussian
  const Buffer* flags;             // uint per Gaussian: visibility, scanned in place to offsets
  const Buffer* touched;           // uint per Gaussian
  const Buffer* depth_keys[2];     // uint per Gaussian (sort ping-pong)
  const Buffer* ids[2];            // uint per Gaussian (sort ping-pong)
  const Buffer* touched_sorted;    // uint per Gaussian: touched in depth order, scanned to offsets
};
// Stages a + b: projection, visibility scan, compaction (V -> counts[kCountV]), then setup_args
// mode 0 (the dispatch sizes that depend on V).
void RecordProjectAndCompact(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                             const SceneBuffers& scene, const Buffer& counts, const Buffer& args,
                             const ProjectPush& push);

// --- binning.cc ----------------------------------------------------------------------------------
// Tile instances name a visible Gaussian by its depth rank j. When the tile id and j fit one
// uint together (the usual case: 11 + 19 bits for 1242x375 and 500k Gaussians), an instance is
// the single key tile << rank_bits | j and the tile sort moves keys only; else (pair mode,
// rank_bits = 0) key = tile and value = j.
int TileBits(uint32_t num_tiles);
uint32_t RankBits(uint32_t num_gaussians, uint32_t num_tiles);  // 0: pair mode

struct BinningBuffers {
  const Buffer* inst_keys[2];
  const Buffer* inst_vals[2];  // pair mode only
  const Buffer* hist;
  const Buffer* ranges;  // uvec2 per tile
};
struct BinningResult {
  const Buffer* list;  // tile-sorted instances: depth rank j in the low bits (& rank_mask)
  uint32_t rank_mask;
  const Buffer* sorted_ids;  // Gaussian id by depth rank (the depth sort's result)
};
// Stages c..g: depth sort, touched-tiles scan (I -> counts[kCountI]), emit, tile sort, tile
// ranges. rank_bits: RankBits() (or 0 to force pair mode).
BinningResult RecordSortAndBin(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                               const SceneBuffers& scene, const BinningBuffers& bins,
                               const Buffer& counts, const Buffer& args, uint32_t num_gaussians,
                               uint64_t instance_capacity, uint32_t tiles_x, uint32_t tiles_y,
                               uint32_t rank_bits);
// The tail of stages d..g, shared with the LiDAR sweep (lidar_stages_vk.cc): touched-tiles scan
// of the gathered entries (I -> counts[kCountI], saturating), emit, stable tile sort by the tile
// bits, tile ranges (cleared by the caller).
struct EmitSources {
  const Buffer* sorted_ids;      // entry id by sort rank
  const Buffer* touched_sorted;  // tiles touched, by sort rank (scanned in place to offsets)
  const Buffer* rects;           // uvec2 per entry
};
BinningResult RecordEmitAndBin(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                               const EmitSources& src, const BinningBuffers& bins, const Buffer& counts,
                               const Buffer& args, uint32_t num_entries, uint64_t instance_capacity,
                               uint32_t tiles_x, uint32_t tiles_y, uint32_t rank_bits);

// --- blend.cc ------------------------------------------------------------------------------------
struct ImageBuffers {
  const Buffer* rgb;        // 3 floats per pixel
  const Buffer* depth;      // float per pixel
  const Buffer* alpha;      // float per pixel
  const Buffer* final_t;    // float per pixel
  const Buffer* n_contrib;  // uint per pixel
};
struct BlendParams {
  uint32_t width, height, tiles_x, tiles_y;
  float background[3];
};
void RecordBlend(Recorder& rec, const Kernels& k, const Buffer& ranges, const BinningResult& bins,
                 const Buffer& sorted_splats, const ImageBuffers& image, const BlendParams& params);

// --- backward.cc ---------------------------------------------------------------------------------
inline constexpr uint32_t kSplatGradFloats = 12;  // common.glsl: SPLAT_GRAD_STRIDE
inline constexpr uint32_t kParamGradFloats = 16;  // 4 vec4 per Gaussian (common.glsl)

struct BackwardBuffers {
  const Buffer* pixel_grads;                 // rgb [3P] | depth [P] | alpha [P]
  const Buffer* splat_grads;                 // kSplatGradFloats per depth rank, zeroed here
  const Buffer* param_grads;                 // kParamGradFloats per Gaussian, zeroed here
  const Buffer* sh_grads[kMaxShGroups];      // scene SH group layout; unused groups: any buffer
  VkDeviceSize sh_grad_bytes[kMaxShGroups];  // bytes to zero per group (0: unused)
  // Deterministic mode: kDetSlotFloats per tile instance of the kept frame (>= its I slots);
  // null: float atomics.
  const Buffer* det_slots = nullptr;
  uint64_t det_slot_capacity = 0;  // slots of det_slots in use (the blend writes every one)
};
inline constexpr uint32_t kDetSlotFloats = 10;  // common.glsl: DET_SLOT_FLOATS
// Shared memory of blend_backward_det (blend_backward.glsl: partial, tile_last).
inline constexpr uint32_t kDetSharedBytes = kDetSlotFloats * 256 * 3 * 4 + 4;
// Builds k's deterministic-mode pipelines unless built: FailedPrecondition on a device that
// cannot run them (no subgroup arithmetic, less than kDetSharedBytes of shared memory, a
// subgroup size outside [4, 64]).
absl::Status EnsureDeterministicKernels(const Context& ctx, Kernels* k);
// The blend backward (per tile, back to front) then the projection backward (per visible
// Gaussian, indirect over V) of the frame recorded last with these buffers; `push` is that
// frame's camera. With bwd.det_slots the blend backward is the deterministic pair
// (blend_backward_det + blend_backward_reduce).
void RecordBackward(Recorder& rec, const Kernels& k, const SceneBuffers& scene,
                    const Buffer& ranges, const BinningResult& bins, const ImageBuffers& image,
                    const BlendParams& params, const Buffer& counts, const Buffer& args,
                    const ProjectPush& push, const BackwardBuffers& bwd);

}  // namespace streetsim::vulkan
