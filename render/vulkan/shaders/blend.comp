// Stage h: front-to-back blending, one workgroup per 16x16 tile, one pixel per invocation.
//
// Written for lavapipe (see docs/cpu-vs-lavapipe.md): no shared memory and no barriers. Each
// subgroup walks the tile's list on its own in batches of gl_SubgroupSize splats and leaves as
// soon as all of its pixels are saturated.
//
// Per batch, every lane loads one splat's position, conic and opacity and tests exactly whether
// its opacity ellipse (o G >= 1/255) reaches any pixel of the subgroup's bounding box (Reaches);
// only the splats that do are blended, one per trip of a subgroup-uniform loop over the ballot's
// set bits, each loaded with a subgroup-uniform index. llvmpipe executes both sides of an `if`
// masked, so the skip has to be a loop trip count: a do-while, because the exiting trip of a
// NIR loop runs its body masked. A lane-varying SSBO load costs llvmpipe a scalar loop over the
// lanes per component (measured: more than all the blend arithmetic of a batch), so only what the
// test needs is lane-loaded; the blended splat is loaded in its trip with a uniform index.
// Invocations are mapped so that a subgroup covers a near-square block of pixels (4x2 with 8
// lanes), which makes the skip tighter than a 1-pixel-high row. On the street scene (500k
// Gaussians, 1242x375) about 35% of the (splat, subgroup) pairs reach; the blend ran ~1.7x faster
// than blending every splat of the list (unrolled broadcast loop).
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_vote : require
#extension GL_KHR_shader_subgroup_ballot : require
#include "common.glsl"

layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE) in;
layout(std430, binding = 0) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 1) readonly buffer List { uint inst_list[]; };  // rank j in the low bits
layout(std430, binding = 2) readonly buffer Splats { vec4 sorted_splats[]; };  // by depth rank
layout(std430, binding = 3) writeonly buffer Rgb { float out_rgb[]; };
layout(std430, binding = 4) writeonly buffer Depth { float out_depth[]; };
layout(std430, binding = 5) writeonly buffer Alpha { float out_alpha[]; };
layout(std430, binding = 6) writeonly buffer FinalT { float out_final_t[]; };
layout(std430, binding = 7) writeonly buffer NContrib { uint out_n_contrib[]; };
layout(push_constant, std430) uniform Params {
  uint width;
  uint height;
  uint tiles_x;
  uint rank_mask;
  float bg_r, bg_g, bg_b;
} pc;

struct Pixel {
  float px, py;
  float T;
  vec3 C;
  float D;
  uint last;
  bool done;
};

// The 3DGS rules for one splat, branch-free. `index` is the splat's 1-based position in the tile
// list (n_contrib); `valid` is false past the end of the list.
void Blend(inout Pixel p, vec4 sa, vec4 sb, vec2 sc, bool valid, uint index) {
  const float dx = sa.x - p.px, dy = sa.y - p.py;  // sa: x, y, conic a, conic b
  const float power = -0.5 * (sa.z * dx * dx + sb.x * dy * dy) - sa.w * dx * dy;
  const float alpha = min(0.99, sb.y * exp(power));  // sb: conic c, opacity, r, g
  const bool live = valid && !p.done && !(power > 0.0) && !(alpha < 1.0 / 255.0);
  const float test_t = p.T * (1.0 - alpha);
  const bool saturate = live && test_t < 1e-4;
  const bool add = live && !saturate;
  const float w = add ? alpha * p.T : 0.0;
  p.C += w * vec3(sb.z, sb.w, sc.x);  // sc: b, depth
  p.D += w * sc.y;
  p.T = add ? test_t : p.T;
  p.last = add ? index : p.last;
  p.done = p.done || saturate;
}

// Whether a splat (centre x_s, y_s; conic a, b, c; opacity o) reaches o G >= 1/255 at some
// pixel of the box [x0, x1] x [y0, y1] (pixel coordinates; one to a few rows). Per row (dy = y_s
// - y) the form Q(dx) = a dx^2 + 2b dx dy + c dy^2 is convex in dx (a > 0), so its minimum over
// the row's columns (dx in [x_s - x1, x_s - x0]) is at the unconstrained minimiser -b dy / a
// clamped to that interval; the splat reaches the row iff that minimum is <= d2 = 2 ln(255 o).
// The margins (relative to the terms' magnitudes, and absolute) cover the rounding of this test,
// of the blend's own power and of exp, so the test never drops a splat the blend would use.
bool Reaches(vec4 sa, vec2 sb, float x0, float x1, float y0, float y1) {
  const float a = sa.z, b = sa.w, c = sb.x;  // sa: x, y, conic a, conic b; sb: conic c, opacity
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
  // Subgroup k of the workgroup covers block k of W x H pixels (W H = gl_SubgroupSize, W >= H,
  // both dividing TILE_SIZE), blocks row-major. Only a heuristic: Reaches uses the pixels the
  // subgroup actually holds.
  const uint S = gl_SubgroupSize, l = gl_LocalInvocationIndex;
  const uint bw = 1u << ((findMSB(S) + 1) / 2);  // 8 -> 4x2, 16 -> 4x4, 32 -> 8x4
  const uint bh = S / bw;
  const uint lane_in = l % S, block = l / S, blocks_x = TILE_SIZE / bw;
  const uint u = gl_WorkGroupID.x * TILE_SIZE + (block % blocks_x) * bw + lane_in % bw;
  const uint v = gl_WorkGroupID.y * TILE_SIZE + (block / blocks_x) * bh + lane_in / bw;
  const bool inside = u < pc.width && v < pc.height;
  const uvec2 range = ranges[gl_WorkGroupID.y * pc.tiles_x + gl_WorkGroupID.x];
  Pixel p = Pixel(float(u), float(v), 1.0, vec3(0.0), 0.0, 0u, !inside);
  // The subgroup's pixel bounding box, subgroup-uniform (broadcasts, once: subgroupMin/Max would
  // need the arithmetic subgroup feature).
  uvec2 box_lo = uvec2(u, v), box_hi = box_lo;
  for (uint lane = 0u; lane < S; ++lane) {
    const uvec2 q = subgroupBroadcast(uvec2(u, v), lane);
    box_lo = min(box_lo, q);
    box_hi = max(box_hi, q);
  }
  const vec2 lo = vec2(box_lo), hi = vec2(box_hi);

  for (uint base = range.x; base < range.y; base += S) {
    if (subgroupAll(p.done)) break;
    // Every lane loads (past the end: the last entry again), so that no load sits under a
    // data-dependent mask; past the end it does not reach.
    const uint mine = min(base + gl_SubgroupInvocationID, range.y - 1u);
    const uint j = inst_list[mine] & pc.rank_mask;
    const bool reach = base + gl_SubgroupInvocationID < range.y &&
                       Reaches(sorted_splats[3u * j], sorted_splats[3u * j + 1u].xy, lo.x, hi.x,
                               lo.y, hi.y);
    uvec4 todo = subgroupBallot(reach);
    uint n = subgroupBallotBitCount(todo);
    // max(1, n) trips: with n == 0 the one trip changes nothing (valid = false).
    do {
      const uint lane = n == 0u ? 0u : subgroupBallotFindLSB(todo);
      todo[lane >> 5u] &= ~(1u << (lane & 31u));
      const uint jj = subgroupBroadcast(j, lane);  // subgroup-uniform index
      Blend(p, sorted_splats[3u * jj], sorted_splats[3u * jj + 1u], sorted_splats[3u * jj + 2u].xy,
            n != 0u, base - range.x + 1u + lane);
      n = n == 0u ? 0u : n - 1u;
    } while (n != 0u);
  }
  if (!inside) return;
  const uint pix = v * pc.width + u;
  out_rgb[3u * pix] = p.C.x + p.T * pc.bg_r;
  out_rgb[3u * pix + 1u] = p.C.y + p.T * pc.bg_g;
  out_rgb[3u * pix + 2u] = p.C.z + p.T * pc.bg_b;
  out_depth[pix] = p.D;
  out_alpha[pix] = 1.0 - p.T;
  out_final_t[pix] = p.T;
  out_n_contrib[pix] = p.last;
}
