// LiDAR blend backward (shared body of lidar_blend_backward.comp and lidar_blend_backward_cas.comp):
// the cpu backward's step 1 (render/lidar/lidar_backward.cc: BlendBackwardTile, docs/lidar.md
// "Backward pass") per ray, back to front from the forward's final T and last contributor
// (lidar_blend.comp writes both), with the forward's alpha arithmetic so that both agree on which
// splat contributes to which ray.
//
// Layout as the forward (lidar_blend.comp: 4 consecutive beams of one column per invocation, no
// shared memory, no barriers) and reduction as the camera's blend_backward.glsl: each subgroup
// walks the tile list back to front in batches of gl_SubgroupSize entries from its rays' largest
// last contributor; every lane tests one splat's opacity box against the subgroup's ray box, the
// reaching splats are replayed one per trip of a subgroup-uniform loop (uniform loads), each
// invocation sums its 4 rays' 8 terms, subgroupAdd sums them over the subgroup and the lane that
// loaded the splat keeps the sums; after the batch each lane adds them into its splat's Gaussian
// (a seam copy into its Gaussian too) with 8 float atomics, all lanes at once.
//
// DETERMINISTIC (lidar_blend_backward_det.comp), as the camera's (blend_backward.glsl): the
// subgroups walk the list in the same chunks of DET_SUB batches, leave their per-splat sums in
// shared memory, and after a barrier each chunk entry's sums over the subgroups, in subgroup
// order, go to the entry's own slot (its emit index); lidar_det_reduce.comp sums each Gaussian's
// slots (entry 2i's, then its seam copy's) in emit order. Loops are kept short for llvmpipe's loop
// limiter (65535 trips per invocation in total).
//
// Per ray, back to front: T_i = T / (1 - alpha), w = alpha T_i,
//   dL/d range_i += w gD,  dL/d refl_i += w gI,
//   dL/d alpha_i  = gA T_f / (1 - alpha) + T_i (gD (range_i - S_r) + gI (refl_i - S_i)),
//   S <- alpha x_i + (1 - alpha) S, T <- T_i; below the 0.99 clamp the opacity and conic terms.
#extension GL_GOOGLE_include_directive : require
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_EXT_control_flow_attributes : require
#if !defined(CAS_ATOMICS) && !defined(DETERMINISTIC)
#extension GL_EXT_shader_atomic_float : require
#endif
#include "lidar_common.glsl"

#define ROWS 4  // as lidar_blend.comp
#define GRAD_STRIDE 8u  // per Gaussian: u, v, a, b, c, opacity, range, reflectance (LidarSplatGrad)

layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE / ROWS) in;
layout(std430, binding = 0) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 1) readonly buffer List { uint inst_list[]; };  // rank j in the low bits
layout(std430, binding = 2) readonly buffer Splats { vec4 sorted_splats[]; };  // by range rank
layout(std430, binding = 3) readonly buffer SortedIds { uint sorted_ids[]; };  // rank -> entry
// lidar_blend.comp's ray state: final T bits [P], last contributor (1-based, 0: none) [P].
layout(std430, binding = 4) readonly buffer RayState { uint ray_state[]; };
// dL/d(range_sum) [P], dL/d(alpha) [P], dL/d(intensity_sum) [P] (zeros where the caller gave none).
layout(std430, binding = 5) readonly buffer RayGrads { float ray_grads[]; };
// dL/d(splat terms) per Gaussian (GRAD_STRIDE floats), zeroed before.
#if defined(DETERMINISTIC)
// GRAD_STRIDE floats per tile instance, by emit index (every slot of the sweep is written).
layout(std430, binding = 6) writeonly buffer Slots { float slots[]; };
// The touched-tiles scan by rank (exclusive): a rank's first emit index.
layout(std430, binding = 7) readonly buffer Offsets { uint offsets[]; };
layout(std430, binding = 8) readonly buffer Rects { uvec2 rects[]; };  // by entry
#elif defined(CAS_ATOMICS)
layout(std430, binding = 6) buffer SplatGrads { uint splat_grads[]; };
#else
layout(std430, binding = 6) buffer SplatGrads { float splat_grads[]; };
#endif
layout(push_constant, std430) uniform Params {
  uint columns;
  uint beams;
  uint tiles_x;
  uint rank_mask;
  uint splat_capacity;
#ifdef DETERMINISTIC
  uint slot_capacity;  // slots in the buffer (>= the sweep's tile instances)
#endif
} pc;

#ifdef DETERMINISTIC
#define NT (TILE_SIZE * TILE_SIZE / ROWS)  // invocations per tile
#define DET_SUB 4u                          // batches per chunk (one barrier pair each)
// The device's subgroup size, specialised by the host so that the subgroup count and the indices
// below fold to constants (main() poisons the slots if the runtime size differs).
layout(constant_id = 0) const uint DET_S = 8u;
const uint NSG = NT / DET_S;
// [component][subgroup * chunk + batch * gl_SubgroupSize + lane]: 8 KB.
shared float partial[GRAD_STRIDE][NT * DET_SUB];
shared uint tile_last;

// The instance number emit.comp gave rank j's instance in this workgroup's tile.
uint EmitIndex(uint j) {
  const uvec2 r = rects[sorted_ids[j]];
  const uint x0 = r.x & 0xffffu, y0 = r.x >> 16u, x1 = r.y & 0xffffu;
  return offsets[j] + (gl_WorkGroupID.y - y0) * (x1 - x0) + (gl_WorkGroupID.x - x0);
}

// Summed over subgroups 0, 1, ... in order, unrolled (16 subgroups of 4 at most).
#define DET_ADD(s) if ((s) < NSG) sum += partial[c][(s) * DET_SUB * DET_S + k];
#define DET_ADD4(s) DET_ADD(s) DET_ADD((s) + 1u) DET_ADD((s) + 2u) DET_ADD((s) + 3u)
float SubgroupOrderSum(uint c, uint k) {
  float sum = partial[c][k];
  DET_ADD(1u) DET_ADD(2u) DET_ADD(3u) DET_ADD4(4u) DET_ADD4(8u) DET_ADD4(12u)
  return sum;
}

void WriteTask(uint t, uint end, uint range_begin) {
  const uint k = t / GRAD_STRIDE, c = t % GRAD_STRIDE;
  const uint j = min(inst_list[range_begin + end - 1u - k] & pc.rank_mask, pc.splat_capacity - 1u);
  const uint e = EmitIndex(j);
  const float sum = SubgroupOrderSum(c, k);
  if (e < pc.slot_capacity) slots[e * GRAD_STRIDE + c] = sum;
}
#else
void AtomicAddF(uint index, float value) {
#ifdef CAS_ATOMICS
  uint old = splat_grads[index];
  for (;;) {
    const uint prev =
        atomicCompSwap(splat_grads[index], old, floatBitsToUint(uintBitsToFloat(old) + value));
    if (prev == old) break;
    old = prev;
  }
#else
  atomicAdd(splat_grads[index], value);
#endif
}
#endif

// As lidar_blend.comp's Reaches (keep the two identical).
bool Reaches(vec4 sa, vec2 lo, vec2 hi) {
  return sa.x - sa.z <= hi.x && sa.x + sa.z >= lo.x && sa.y - sa.w <= hi.y && sa.y + sa.w >= lo.y;
}

struct Ray {
  float py;
  float T, SD, SI;     // T walking back from the final value; range and reflectance behind
  float gD, gI, gAT;   // upstream: range_sum, intensity_sum, alpha x final T
  uint last;
};

void main() {
  const uint S = gl_SubgroupSize, lane_id = gl_SubgroupInvocationID;
  const uint u = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
  const uint v0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * ROWS;
  const uvec2 range = ranges[gl_WorkGroupID.y * pc.tiles_x + gl_WorkGroupID.x];
  const uint P = pc.columns * pc.beams;
  const float px = float(u);
  Ray p[ROWS];
  uint my_last = 0u;
  [[unroll]] for (uint k = 0u; k < ROWS; ++k) {
    p[k] = Ray(float(v0 + k), 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0u);
    if (u < pc.columns && v0 + k < pc.beams) {
      const uint pix = (v0 + k) * pc.columns + u;
      const float Tf = uintBitsToFloat(ray_state[pix]);
      p[k].T = Tf;
      p[k].last = ray_state[P + pix];
      p[k].gD = ray_grads[pix];
      p[k].gAT = ray_grads[P + pix] * Tf;
      p[k].gI = ray_grads[2u * P + pix];
      my_last = max(my_last, p[k].last);
    }
  }
  const vec2 lo = vec2(subgroupMin(uvec2(u, v0)));
  const vec2 hi = vec2(subgroupMax(uvec2(u, v0))) + vec2(0.0, float(ROWS - 1));
  const uint max_last = subgroupMax(my_last);

  // Lane k of a batch holds list position end - 1 - k, so lanes in ascending order (FindLSB) walk
  // the list back to front.
#ifdef DETERMINISTIC
  const uint l = gl_LocalInvocationIndex;
  // A subgroup size other than the specialised one would garble the sums: poison them (NaN
  // gradients, which the tests catch) rather than return wrong numbers quietly.
  if (S != DET_S || gl_NumSubgroups != NSG) {
    for (uint i = range.x + l; i < range.y; i += NT) {
      const uint e = EmitIndex(min(inst_list[i] & pc.rank_mask, pc.splat_capacity - 1u));
      if (e < pc.slot_capacity) slots[e * GRAD_STRIDE] = uintBitsToFloat(0x7fc00000u);
    }
    return;
  }
  if (l == 0u) tile_last = 0u;
  barrier();
  atomicMax(tile_last, my_last);
  barrier();
  const uint wg_last = tile_last;
  const uint B = DET_SUB * DET_S;
  for (uint chunk_end = wg_last; chunk_end > 0u; chunk_end -= min(chunk_end, B)) {
  for (uint h = 0u; h < DET_SUB; ++h) {
    const uint end = chunk_end > h * DET_S ? chunk_end - h * DET_S : 0u;  // [end - S, end)
    const uint column = gl_SubgroupID * B + h * DET_S + lane_id;
    const bool has = lane_id < end && end - 1u - lane_id < max_last;
#else
  for (uint end = max_last; end > 0u; end -= min(end, S)) {
    const bool has = lane_id < end;
#endif
    const uint idx = has ? end - 1u - lane_id : 0u;
    const uint j = min(inst_list[range.x + idx] & pc.rank_mask, pc.splat_capacity - 1u);
    const bool reach = has && Reaches(sorted_splats[3u * j], lo, hi);
    uvec4 todo = subgroupBallot(reach);
    uint n = subgroupBallotBitCount(todo);
    vec4 acc0 = vec4(0.0), acc1 = vec4(0.0);  // this lane's splat: (u, v, a, b), (c, o, range, refl)
    // max(1, n) trips: with n == 0 the one trip changes nothing (valid = false).
#ifdef DETERMINISTIC
    // Many of a subgroup's batches lie past its own rays' last contributor here (the tile's
    // chunks are shared): skip the empty trip where a branch skips (llvmpipe runs it masked).
    if (n != 0u)
#endif
    do {
      const uint lane = n == 0u ? 0u : subgroupBallotFindLSB(todo);
      todo[lane >> 5u] &= ~(1u << (lane & 31u));
      const uint jj = subgroupBroadcast(j, lane);  // subgroup-uniform index
      const uint entry = end - 1u - lane;          // 0-based list position
      const vec4 sa = sorted_splats[3u * jj], sb = sorted_splats[3u * jj + 1u];
      const vec2 sc = sorted_splats[3u * jj + 2u].xy;  // reflectance, range
      vec4 t0 = vec4(0.0), t1 = vec4(0.0);
      [[unroll]] for (uint k = 0u; k < ROWS; ++k) {
        // The forward's tests and alpha, operation for operation (lidar_blend.comp: Blend).
        const float py = p[k].py;
        const bool in_box = px >= sa.x - sa.z && px <= sa.x + sa.z && py >= sa.y - sa.w &&
                            py <= sa.y + sa.w;
        const float dx = sa.x - px, dy = sa.y - py;
        const float power = -0.5 * (sb.x * dx * dx + sb.z * dy * dy) - sb.y * dx * dy;
        const float G = exp(power);
        const float oG = sb.w * G;
        const float alpha = min(0.99, oG);
        const bool valid = n != 0u && in_box && entry < p[k].last && !(power > 0.0) &&
                           !(alpha < 1.0 / 255.0);
        const float inv_om = 1.0 / (1.0 - alpha);
        const float t_i = p[k].T * inv_om;
        const float w = valid ? alpha * t_i : 0.0;
        const float d_alpha = p[k].gAT * inv_om +
                              t_i * (p[k].gD * (sc.y - p[k].SD) + p[k].gI * (sc.x - p[k].SI));
        const float d_oG = (valid && oG < 0.99) ? d_alpha : 0.0;
        const float d_power = d_oG * sb.w * G;
        t0 += vec4(d_power * -(sb.x * dx + sb.y * dy), d_power * -(sb.z * dy + sb.y * dx),
                   d_power * (-0.5 * dx * dx), d_power * (-dx * dy));
        t1 += vec4(d_power * (-0.5 * dy * dy), d_oG * G, w * p[k].gD, w * p[k].gI);
        const float va = valid ? alpha : 0.0;
        p[k].SD += va * (sc.y - p[k].SD);
        p[k].SI += va * (sc.x - p[k].SI);
        p[k].T = valid ? t_i : p[k].T;
      }
      const vec4 s0 = subgroupAdd(t0), s1 = subgroupAdd(t1);
      const bool mine = lane == lane_id;
      acc0 = mine ? s0 : acc0;
      acc1 = mine ? s1 : acc1;
      n = n == 0u ? 0u : n - 1u;
    } while (n != 0u);
#ifdef DETERMINISTIC
    partial[0][column] = reach ? acc0.x : 0.0;
    partial[1][column] = reach ? acc0.y : 0.0;
    partial[2][column] = reach ? acc0.z : 0.0;
    partial[3][column] = reach ? acc0.w : 0.0;
    partial[4][column] = reach ? acc1.x : 0.0;
    partial[5][column] = reach ? acc1.y : 0.0;
    partial[6][column] = reach ? acc1.z : 0.0;
    partial[7][column] = reach ? acc1.w : 0.0;
  }  // batches of the chunk
    barrier();
    const uint tasks = min(chunk_end, B) * GRAD_STRIDE;
    for (uint t = l; t < tasks; t += NT) WriteTask(t, chunk_end, range.x);
    barrier();  // the next chunk overwrites partial
#else
    if (reach) {
      const uint o = (sorted_ids[j] >> 1u) * GRAD_STRIDE;  // entry 2i / 2i + 1 -> Gaussian i
      AtomicAddF(o, acc0.x);
      AtomicAddF(o + 1u, acc0.y);
      AtomicAddF(o + 2u, acc0.z);
      AtomicAddF(o + 3u, acc0.w);
      AtomicAddF(o + 4u, acc1.x);
      AtomicAddF(o + 5u, acc1.y);
      AtomicAddF(o + 6u, acc1.z);
      AtomicAddF(o + 7u, acc1.w);
    }
#endif
  }
#ifdef DETERMINISTIC
  // Entries past every ray's last contributor reach nothing: their slots get zeros.
  for (uint i = wg_last + l; i < range.y - range.x; i += NT) {
    const uint j = min(inst_list[range.x + i] & pc.rank_mask, pc.splat_capacity - 1u);
    const uint e = EmitIndex(j);
    if (e < pc.slot_capacity) {
      for (uint c = 0u; c < GRAD_STRIDE; ++c) slots[e * GRAD_STRIDE + c] = 0.0;
    }
  }
#endif
}
