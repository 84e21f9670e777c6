// LiDAR stage h: front-to-back blending per ray, one workgroup per tile of 16 beams x 16 columns,
// one ray per invocation, then the outputs of docs/lidar.md: alpha, the unnormalised range and
// intensity sums, and where the ray returns (alpha >= threshold, or a Bernoulli(alpha) draw from
// the cpu renderer's splitmix64 hash) the normalised range and intensity.
//
// The camera blend's structure (blend.comp: why it is written this way for lavapipe): no shared
// memory or barriers; each subgroup walks the tile's list in batches of gl_SubgroupSize splats,
// every lane loads one splat and tests whether its opacity box reaches the subgroup's pixel box,
// and only those that do are blended, one per trip of a subgroup-uniform loop over the ballot's
// bits. The blend rules are the cpu reference's (lidar_renderer.cc: BlendScalar): only the rays
// inside a splat's opacity box are visited (an exact skip: outside it opacity * G < 1/255).
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_vote : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_EXT_control_flow_attributes : require
#include "lidar_common.glsl"

#define ROWS 4  // rays per invocation: consecutive beams of one column
layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE / ROWS) in;
layout(std430, binding = 0) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 1) readonly buffer List { uint inst_list[]; };  // rank j in the low bits
layout(std430, binding = 2) readonly buffer Splats { vec4 sorted_splats[]; };  // by range rank
// Five planes of beams x columns floats: alpha, range_sum, intensity_sum, range, intensity.
layout(std430, binding = 3) writeonly buffer Out { float out_planes[]; };
// Two planes of beams x columns words for the backward (lidar_blend_backward.glsl): the final
// transmittance's float bits, then the 1-based tile-list position of the last contributor (0:
// none). Written on every sweep: alpha = 1 - T loses T's low bits where the ray is opaque.
layout(std430, binding = 4) writeonly buffer RayState { uint out_state[]; };
layout(push_constant, std430) uniform Params {
  uint columns;
  uint beams;
  uint tiles_x;
  uint rank_mask;
  float return_alpha_threshold;
  uint sample_drop;
  uint seed_lo, seed_hi;
  // Records in sorted_splats: a frame whose drawn entries exceed it is rendered again with more
  // room (lidar_gather.comp), but its ranks must not read past the buffer meanwhile.
  uint splat_capacity;
} pc;

struct Ray {
  float px, py;  // column, beam
  float T;
  float D, I;    // range and reflectance sums
  uint last;     // 1-based list position of the last splat added
  bool done;
};

void Blend(inout Ray p, vec4 sa, vec4 sb, vec2 sc, bool valid, uint index) {
  // sa: x, y, op_w, op_h; sb: conic a, b, c, opacity; sc: reflectance, range.
  const bool in_box = p.px >= sa.x - sa.z && p.px <= sa.x + sa.z && p.py >= sa.y - sa.w &&
                      p.py <= sa.y + sa.w;
  const float dx = sa.x - p.px, dy = sa.y - p.py;
  const float power = -0.5 * (sb.x * dx * dx + sb.z * dy * dy) - sb.y * dx * dy;
  const float alpha = min(0.99, sb.w * exp(power));
  const bool live = valid && in_box && !p.done && !(power > 0.0) && !(alpha < 1.0 / 255.0);
  const float test_t = p.T * (1.0 - alpha);
  const bool saturate = live && test_t < 1e-4;
  const bool add = live && !saturate;
  const float w = add ? alpha * p.T : 0.0;
  p.D += w * sc.y;
  p.I += w * sc.x;
  p.T = add ? test_t : p.T;
  p.last = add ? index : p.last;
  p.done = p.done || saturate;
}

// Whether a splat's opacity box [x -+ op_w] x [y -+ op_h] holds a pixel of [lo, hi].
bool Reaches(vec4 sa, vec2 lo, vec2 hi) {
  return sa.x - sa.z <= hi.x && sa.x + sa.z >= lo.x && sa.y - sa.w <= hi.y && sa.y + sa.w >= lo.y;
}

// splitmix64 on (lo, hi) uint pairs (render/lidar/lidar_renderer.cc: SplitMix64), so that no
// 64-bit integer support is needed.
uvec2 Add64(uvec2 a, uvec2 b) {
  uint carry;
  const uint lo = uaddCarry(a.x, b.x, carry);
  return uvec2(lo, a.y + b.y + carry);
}
uvec2 Mul64(uvec2 a, uvec2 b) {
  uint hi, lo;
  umulExtended(a.x, b.x, hi, lo);
  return uvec2(lo, hi + a.x * b.y + a.y * b.x);
}
uvec2 XorShift(uvec2 a, uint s) {  // a ^ (a >> s), 0 < s < 32
  return a ^ uvec2((a.x >> s) | (a.y << (32u - s)), a.y >> s);
}
uvec2 SplitMix64(uvec2 x) {
  x = Add64(x, uvec2(0x7f4a7c15u, 0x9e3779b9u));
  x = Mul64(XorShift(x, 30u), uvec2(0x1ce4e5b9u, 0xbf58476du));
  x = Mul64(XorShift(x, 27u), uvec2(0x133111ebu, 0x94d049bbu));
  return XorShift(x, 31u);
}

// Writes ray p's outputs (alpha, the sums, and the normalised range and intensity where it returns).
void Finish(Ray p, uint u, uint v) {
  const uint pix = v * pc.columns + u;
  const uint P = pc.columns * pc.beams;
  const float a = 1.0 - p.T;
  bool ret;
  if (pc.sample_drop != 0u) {
    // u = (h >> 40) / 2^24 with h = splitmix64(seed ^ splitmix64(pixel + 1)): 24 bits, exact in float.
    const uvec2 h = SplitMix64(uvec2(pc.seed_lo, pc.seed_hi) ^ SplitMix64(uvec2(pix + 1u, 0u)));
    ret = float(h.y >> 8u) * (1.0 / 16777216.0) < a;
  } else {
    ret = a >= pc.return_alpha_threshold;
  }
  const bool valid = ret && a > 0.0;
  out_planes[pix] = a;
  out_planes[P + pix] = p.D;
  out_planes[2u * P + pix] = p.I;
  out_planes[3u * P + pix] = valid ? p.D / a : 0.0;
  out_planes[4u * P + pix] = valid ? p.I / a : 0.0;
  out_state[pix] = floatBitsToUint(p.T);
  out_state[P + pix] = p.last;
}

void main() {
  // Invocation (x, y) holds the ROWS rays of column x, beams ROWS y .. ROWS y + ROWS - 1 of the
  // tile; a subgroup is consecutive columns of one row group (8 lanes: 8 columns x ROWS beams).
  const uint S = gl_SubgroupSize;
  const uint u = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
  const uint v0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * ROWS;
  const uvec2 range = ranges[gl_WorkGroupID.y * pc.tiles_x + gl_WorkGroupID.x];
  Ray p[ROWS];
  [[unroll]] for (uint k = 0u; k < ROWS; ++k) {
    p[k] = Ray(float(u), float(v0 + k), 1.0, 0.0, 0.0, 0u, !(u < pc.columns && v0 + k < pc.beams));
  }
  uvec2 box_lo = uvec2(u, v0), box_hi = box_lo;
  for (uint lane = 0u; lane < S; ++lane) {
    const uvec2 q = subgroupBroadcast(uvec2(u, v0), lane);
    box_lo = min(box_lo, q);
    box_hi = max(box_hi, q);
  }
  const vec2 lo = vec2(box_lo), hi = vec2(box_hi) + vec2(0.0, float(ROWS - 1));

  for (uint base = range.x; base < range.y; base += S) {
    bool all_done = true;
    [[unroll]] for (uint k = 0u; k < ROWS; ++k) all_done = all_done && p[k].done;
    if (subgroupAll(all_done)) break;
    const uint mine = min(base + gl_SubgroupInvocationID, range.y - 1u);
    const uint j = min(inst_list[mine] & pc.rank_mask, pc.splat_capacity - 1u);
    const bool reach = base + gl_SubgroupInvocationID < range.y &&
                       Reaches(sorted_splats[3u * j], lo, hi);
    uvec4 todo = subgroupBallot(reach);
    uint n = subgroupBallotBitCount(todo);
    do {
      const uint lane = n == 0u ? 0u : subgroupBallotFindLSB(todo);
      todo[lane >> 5u] &= ~(1u << (lane & 31u));
      const uint jj = subgroupBroadcast(j, lane);
      const vec4 sa = sorted_splats[3u * jj], sb = sorted_splats[3u * jj + 1u];
      const vec2 sc = sorted_splats[3u * jj + 2u].xy;
      [[unroll]] for (uint k = 0u; k < ROWS; ++k) {
        Blend(p[k], sa, sb, sc, n != 0u, base - range.x + 1u + lane);
      }
      n = n == 0u ? 0u : n - 1u;
    } while (n != 0u);
  }
  [[unroll]] for (uint k = 0u; k < ROWS; ++k) {
    if (u < pc.columns && v0 + k < pc.beams) Finish(p[k], u, v0 + k);
  }
}
