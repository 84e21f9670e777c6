// Blend backward (shared body of blend_backward.comp and blend_backward_cas.comp): the 3DGS
// backward of the front-to-back blend, replayed per pixel back to front from the forward's
// n_contrib and final T (mirrors render/cpu/blend_backward_simd.inc; same math, and the same
// alpha arithmetic as blend.comp so that both agree on which splat contributes to which pixel).
//
// Layout as the forward (blend.comp): one workgroup per 16x16 tile, one pixel per invocation,
// no shared memory, no barriers; each subgroup covers a near-square pixel block and walks the
// tile list on its own, back to front, in batches of gl_SubgroupSize entries, starting at its
// pixels' largest n_contrib. Per batch every lane loads one entry and tests exactly whether the
// splat reaches the block (Reaches, as the forward); the reaching splats are replayed one per
// trip of a subgroup-uniform loop (uniform loads), every pixel computes its 10 gradient terms,
// subgroupAdd sums them over the block and the lane that loaded the splat keeps the sums. After
// the batch each lane adds its splat's sums with 10 float atomics, all lanes at once ("atomics
// per Gaussian per lane", the variant that ran best on lavapipe: ../shared/docs/cpu-vs-lavapipe.md).
//
// DETERMINISTIC (blend_backward_det.comp): no atomics. The subgroups of a tile walk the list in
// the same chunks of DET_SUB batches (aligned to the tile's largest n_contrib); every lane leaves
// its splat's subgroup sums of each batch in shared memory and, after a barrier, the chunk's
// entries are summed over the subgroups in subgroup order and written to the entry's own slot
// (the instance number emit.comp gave it). blend_backward_reduce.comp then sums each Gaussian's
// slots in emit order (row-major tiles). Every sum has a fixed shape, so the bits repeat run to
// run (docs/rendering.md "Deterministic mode", also on subgroupAdd). Loops per chunk stay short:
// llvmpipe ends an invocation's loops after 65535 back-edges in total (gallivm's loop limiter),
// so the sums over the subgroups are unrolled.
//
// Per pixel, back to front from its last contributor: T_i = T_{i+1} / (1 - alpha_i),
//   dL/dc_i     = g_c alpha_i T_i                          (c = r, g, b; depth likewise)
//   dL/dalpha_i = T_i sum_c g_c (c_i - S_c) + (g_alpha - g . bg) T_final / (1 - alpha_i)
//   S_c        <- alpha_i c_i + (1 - alpha_i) S_c          (colour of what lies behind)
// then alpha = min(0.99, o G): dL/dG = o dL/dalpha and dL/do = G dL/dalpha below the clamp,
// and G = exp(power) gives the mean2D and conic terms.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#if !defined(CAS_ATOMICS) && !defined(DETERMINISTIC)
#extension GL_EXT_shader_atomic_float : require
#endif
#include "common.glsl"

layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE) in;
layout(std430, binding = 0) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 1) readonly buffer List { uint inst_list[]; };  // rank j in the low bits
layout(std430, binding = 2) readonly buffer Splats { vec4 sorted_splats[]; };  // by depth rank
layout(std430, binding = 3) readonly buffer FinalT { float final_t[]; };
layout(std430, binding = 4) readonly buffer NContrib { uint n_contrib[]; };
// dL/d(outputs): rgb [3P], depth [P], alpha [P] (zeros where the caller gave none).
layout(std430, binding = 5) readonly buffer PixelGrads { float pixel_grads[]; };
// dL/d(splat) by depth rank (common.glsl: SPLAT_GRAD_STRIDE, SG_*), zeroed before.
#if defined(DETERMINISTIC)
// DET_SLOT_FLOATS per tile instance, by emit index, in SG_* order (every slot of the frame is
// written: reached entries with their sums, the rest with zeros).
layout(std430, binding = 6) writeonly buffer Slots { float slots[]; };
layout(std430, binding = 7) readonly buffer Ids { uint sorted_ids[]; };  // Gaussian id by rank
// The touched-tiles scan by rank (exclusive): a rank's first emit index.
layout(std430, binding = 8) readonly buffer Offsets { uint offsets[]; };
layout(std430, binding = 9) readonly buffer Rects { uvec2 rects[]; };  // by Gaussian id
#elif defined(CAS_ATOMICS)
layout(std430, binding = 6) buffer SplatGrads { uint splat_grads[]; };
#else
layout(std430, binding = 6) buffer SplatGrads { float splat_grads[]; };
#endif
layout(push_constant, std430) uniform Params {
  uint width;
  uint height;
  uint tiles_x;
  uint rank_mask;
  float bg_r, bg_g, bg_b;
#ifdef DETERMINISTIC
  uint slot_capacity;  // slots in the buffer (>= the frame's tile instances)
#endif
} pc;

#ifdef DETERMINISTIC
#define NT (TILE_SIZE * TILE_SIZE)
// The device's subgroup size, specialised by the host, so that the subgroup count and every index
// below fold to constants (main() poisons the slots if the runtime size differs).
layout(constant_id = 0) const uint DET_S = 8u;
const uint NSG = NT / DET_S;
// Batches per chunk (one barrier pair per chunk: barriers are dear on llvmpipe). 30 KB of shared
// memory (stages.h: kDetSharedBytes, checked against the device's limit).
#define DET_SUB 3u
// [component][subgroup * chunk + batch * gl_SubgroupSize + lane]: one chunk's per-subgroup sums
// (the subgroup size is a power of two, so there are NT * DET_SUB columns).
shared float partial[DET_SLOT_FLOATS][NT * DET_SUB];
shared uint tile_last;

// The instance number emit.comp gave rank j's instance in this workgroup's tile (its rect is
// emitted row-major from offsets[j]).
uint EmitIndex(uint j) {
  const uvec2 r = rects[sorted_ids[j]];
  const uint x0 = r.x & 0xffffu, y0 = r.x >> 16u, x1 = r.y & 0xffffu;
  return offsets[j] + (gl_WorkGroupID.y - y0) * (x1 - x0) + (gl_WorkGroupID.x - x0);
}

// Column k's entry of component c summed over the subgroups 0, 1, 2, ... in order (unrolled:
// see the loop limiter above).
#define DET_ADD(s) if ((s) < NSG) sum += partial[c][(s) * DET_SUB * DET_S + k];
#define DET_ADD4(s) DET_ADD(s) DET_ADD((s) + 1u) DET_ADD((s) + 2u) DET_ADD((s) + 3u)
#define DET_ADD16(s) DET_ADD4(s) DET_ADD4((s) + 4u) DET_ADD4((s) + 8u) DET_ADD4((s) + 12u)
float SubgroupOrderSum(uint c, uint k) {
  float sum = partial[c][k];
  DET_ADD(1u) DET_ADD(2u) DET_ADD(3u) DET_ADD4(4u) DET_ADD4(8u) DET_ADD4(12u)
  DET_ADD16(16u) DET_ADD16(32u) DET_ADD16(48u)
  return sum;
}

// Task t = k * DET_SLOT_FLOATS + c of a chunk of B entries ending at `end`: entry end - 1 - k,
// component c.
void WriteTask(uint t, uint end, uint range_begin) {
  const uint k = t / DET_SLOT_FLOATS, c = t % DET_SLOT_FLOATS;
  const uint e = EmitIndex(inst_list[range_begin + end - 1u - k] & pc.rank_mask);
  const float sum = SubgroupOrderSum(c, k);
  if (e < pc.slot_capacity) slots[e * DET_SLOT_FLOATS + c] = sum;
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

// As blend.comp's Reaches (keep the two identical).
bool Reaches(vec4 sa, vec2 sb, float x0, float x1, float y0, float y1) {
  const float a = sa.z, b = sa.w, c = sb.x;
  const float d2 = 2.0 * log(255.0 * sb.y), inv_a = 1.0 / a;
  const float lo = sa.x - x1, hi = sa.x - x0;
  bool hit = false;
  for (float y = y0; y <= y1; y += 1.0) {
    const float dy = sa.y - y;
    const float dx = clamp(-b * dy * inv_a, lo, hi);
    const float qa = a * dx * dx, qb = 2.0 * b * dx * dy, qc = c * dy * dy;
    hit = hit || qa + qb + qc <= d2 + 1e-4 * (qa + abs(qb) + qc) + 1e-3;
  }
  return hit;
}

void main() {
  // Pixel mapping as blend.comp (a subgroup covers a near-square block).
  const uint S = gl_SubgroupSize, l = gl_LocalInvocationIndex, lane_id = gl_SubgroupInvocationID;
  const uint bw = 1u << ((findMSB(S) + 1) / 2);
  const uint bh = S / bw;
  const uint lane_in = l % S, block = l / S, blocks_x = TILE_SIZE / bw;
  const uint u = gl_WorkGroupID.x * TILE_SIZE + (block % blocks_x) * bw + lane_in % bw;
  const uint v = gl_WorkGroupID.y * TILE_SIZE + (block / blocks_x) * bh + lane_in / bw;
  const bool inside = u < pc.width && v < pc.height;
  const uvec2 range = ranges[gl_WorkGroupID.y * pc.tiles_x + gl_WorkGroupID.x];
  const uint P = pc.width * pc.height;
  const uint pix = inside ? v * pc.width + u : 0u;

  float T = 1.0, gT = 0.0, gd = 0.0, Sd = 0.0;
  vec3 g = vec3(0.0), Sc = vec3(0.0);
  uint last = 0u;
  if (inside) {
    const float Tf = final_t[pix];
    T = Tf;
    last = n_contrib[pix];
    g = vec3(pixel_grads[3u * pix], pixel_grads[3u * pix + 1u], pixel_grads[3u * pix + 2u]);
    gd = pixel_grads[3u * P + pix];
    const float ga = pixel_grads[4u * P + pix];
    gT = (ga - (g.x * pc.bg_r + g.y * pc.bg_g + g.z * pc.bg_b)) * Tf;
  }
  const float px = float(u), py = float(v);
  const vec2 lo = vec2(subgroupMin(uvec2(u, v))), hi = vec2(subgroupMax(uvec2(u, v)));
  const uint max_last = subgroupMax(last);

  // Lane k of a batch holds list entry end - 1 - k, so lanes in ascending order (FindLSB) walk
  // the list back to front.
#ifdef DETERMINISTIC
  // A subgroup size other than the specialised one would garble the sums: poison them (NaN
  // gradients, which the tests catch) rather than return wrong numbers quietly.
  if (S != DET_S || gl_NumSubgroups != NSG) {
    for (uint i = range.x + l; i < range.y; i += NT) {
      const uint e = EmitIndex(inst_list[i] & pc.rank_mask);
      if (e < pc.slot_capacity) slots[e * DET_SLOT_FLOATS] = uintBitsToFloat(0x7fc00000u);
    }
    return;
  }
  // The tile's largest n_contrib, so that every subgroup walks the same chunks.
  if (l == 0u) tile_last = 0u;
  barrier();
  atomicMax(tile_last, last);
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
    const uint j = inst_list[range.x + idx] & pc.rank_mask;
    const bool reach = has && Reaches(sorted_splats[3u * j], sorted_splats[3u * j + 1u].xy, lo.x,
                                      hi.x, lo.y, hi.y);
    uvec4 todo = subgroupBallot(reach);
    uint n = subgroupBallotBitCount(todo);
    vec4 acc0 = vec4(0.0), acc1 = vec4(0.0);  // this lane's splat: (x, y, a, b), (c, o, r, g)
    vec2 acc2 = vec2(0.0);                    // (b, depth)
    // max(1, n) trips: with n == 0 the one trip changes nothing (valid = false).
#ifdef DETERMINISTIC
    // Most of a subgroup's batches lie past its own pixels' last contributor here (the tile's
    // chunks are shared): skip the empty trip where a branch skips (llvmpipe runs it masked).
    if (n != 0u)
#endif
    do {
      const uint lane = n == 0u ? 0u : subgroupBallotFindLSB(todo);
      todo[lane >> 5u] &= ~(1u << (lane & 31u));
      const uint jj = subgroupBroadcast(j, lane);  // subgroup-uniform index
      const uint entry = end - 1u - lane;
      const vec4 sa = sorted_splats[3u * jj], sb = sorted_splats[3u * jj + 1u];
      const vec2 sc = sorted_splats[3u * jj + 2u].xy;
      // The forward's alpha, operation for operation (blend.comp: Blend).
      const float dx = sa.x - px, dy = sa.y - py;
      const float power = -0.5 * (sa.z * dx * dx + sb.x * dy * dy) - sa.w * dx * dy;
      const float G = exp(power);
      const float oG = sb.y * G;
      const float alpha = min(0.99, oG);
      const bool valid = n != 0u && entry < last && !(power > 0.0) && !(alpha < 1.0 / 255.0);
      const float inv_om = 1.0 / (1.0 - alpha);
      const float t_i = T * inv_om;
      const float w = valid ? alpha * t_i : 0.0;
      const vec3 col = vec3(sb.z, sb.w, sc.x);
      const float d_alpha = t_i * (dot(g, col - Sc) + gd * (sc.y - Sd)) + gT * inv_om;
      const float d_oG = (valid && oG < 0.99) ? d_alpha : 0.0;
      const float d_power = d_oG * sb.y * G;
      const vec4 t0 = vec4(d_power * -(sa.z * dx + sa.w * dy), d_power * -(sb.x * dy + sa.w * dx),
                           d_power * (-0.5 * dx * dx), d_power * (-dx * dy));
      const vec4 t1 = vec4(d_power * (-0.5 * dy * dy), d_oG * G, w * g.x, w * g.y);
      const vec2 t2 = vec2(w * g.z, w * gd);
      const float va = valid ? alpha : 0.0;
      Sc += va * (col - Sc);
      Sd += va * (sc.y - Sd);
      T = valid ? t_i : T;
      const vec4 s0 = subgroupAdd(t0), s1 = subgroupAdd(t1);
      const vec2 s2 = subgroupAdd(t2);
      const bool mine = lane == lane_id;
      acc0 = mine ? s0 : acc0;
      acc1 = mine ? s1 : acc1;
      acc2 = mine ? s2 : acc2;
      n = n == 0u ? 0u : n - 1u;
    } while (n != 0u);
#ifdef DETERMINISTIC
    // This lane's splat's sums over the subgroup's pixels (zeros when it reached none).
    partial[SG_X][column] = reach ? acc0.x : 0.0;
    partial[SG_Y][column] = reach ? acc0.y : 0.0;
    partial[SG_A][column] = reach ? acc0.z : 0.0;
    partial[SG_B][column] = reach ? acc0.w : 0.0;
    partial[SG_C][column] = reach ? acc1.x : 0.0;
    partial[SG_O][column] = reach ? acc1.y : 0.0;
    partial[SG_R][column] = reach ? acc1.z : 0.0;
    partial[SG_G][column] = reach ? acc1.w : 0.0;
    partial[SG_BL][column] = reach ? acc2.x : 0.0;
    partial[SG_DEPTH][column] = reach ? acc2.y : 0.0;
  }  // batches of the chunk
    barrier();
    const uint tasks = min(chunk_end, B) * DET_SLOT_FLOATS;
    for (uint t = l; t < tasks; t += NT) WriteTask(t, chunk_end, range.x);
    barrier();  // the next chunk overwrites partial
#else
    if (reach) {
      const uint o = j * SPLAT_GRAD_STRIDE;
      AtomicAddF(o + SG_X, acc0.x);
      AtomicAddF(o + SG_Y, acc0.y);
      AtomicAddF(o + SG_A, acc0.z);
      AtomicAddF(o + SG_B, acc0.w);
      AtomicAddF(o + SG_C, acc1.x);
      AtomicAddF(o + SG_O, acc1.y);
      AtomicAddF(o + SG_R, acc1.z);
      AtomicAddF(o + SG_G, acc1.w);
      AtomicAddF(o + SG_BL, acc2.x);
      AtomicAddF(o + SG_DEPTH, acc2.y);
    }
#endif
  }
#ifdef DETERMINISTIC
  // Entries past every pixel's last contributor reach nothing: their slots get zeros.
  for (uint i = wg_last + l; i < range.y - range.x; i += NT) {
    const uint e = EmitIndex(inst_list[range.x + i] & pc.rank_mask);
    if (e < pc.slot_capacity) {
      for (uint c = 0u; c < DET_SLOT_FLOATS; ++c) slots[e * DET_SLOT_FLOATS + c] = 0.0;
    }
  }
#endif
}
