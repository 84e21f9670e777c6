// Stage h: front-to-back blending, one workgroup per 16x16 tile, one pixel per invocation.
//
// Written for lavapipe (see docs/cpu-vs-lavapipe.md): no shared memory and no barriers. Each
// subgroup walks the tile's list on its own in batches of gl_SubgroupSize: every lane loads one
// splat, then the batch is consumed by broadcasting the lane-loaded values, with a branch-free
// body. The subgroup leaves as soon as all of its pixels are saturated.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_vote : require
#extension GL_KHR_shader_subgroup_ballot : require
#include "common.glsl"

layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE) in;
layout(std430, binding = 0) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 1) readonly buffer Vals { uint inst_vals[]; };
layout(std430, binding = 2) readonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 3) writeonly buffer Rgb { float out_rgb[]; };
layout(std430, binding = 4) writeonly buffer Depth { float out_depth[]; };
layout(std430, binding = 5) writeonly buffer Alpha { float out_alpha[]; };
layout(std430, binding = 6) writeonly buffer FinalT { float out_final_t[]; };
layout(std430, binding = 7) writeonly buffer NContrib { uint out_n_contrib[]; };
layout(push_constant, std430) uniform Params {
  uint width;
  uint height;
  uint tiles_x;
  float bg_r, bg_g, bg_b;
} pc;

void main() {
  const uint u = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
  const uint v = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y;
  const bool inside = u < pc.width && v < pc.height;
  const uvec2 range = ranges[gl_WorkGroupID.y * pc.tiles_x + gl_WorkGroupID.x];
  const float px = float(u), py = float(v);
  const float min_alpha = 1.0 / 255.0;

  float T = 1.0;
  vec3 C = vec3(0.0);
  float D = 0.0;
  uint last = 0u;
  bool done = !inside;
  for (uint base = range.x; base < range.y; base += gl_SubgroupSize) {
    if (subgroupAll(done)) break;
    const uint mine = base + gl_SubgroupInvocationID;
    vec4 a = vec4(0.0), b = vec4(0.0), c = vec4(0.0);
    if (mine < range.y) {
      const uint gid = inst_vals[mine];
      a = splats[3u * gid];
      b = splats[3u * gid + 1u];
      c = splats[3u * gid + 2u];
    }
    const uint count = min(gl_SubgroupSize, range.y - base);
    for (uint j = 0u; j < count; ++j) {
      const vec4 sa = subgroupBroadcast(a, j);  // x, y, conic a, conic b
      const vec4 sb = subgroupBroadcast(b, j);  // conic c, opacity, depth, -
      const vec3 rgb = subgroupBroadcast(c.xyz, j);
      const float dx = sa.x - px, dy = sa.y - py;
      const float power = -0.5 * (sa.z * dx * dx + sb.x * dy * dy) - sa.w * dx * dy;
      const float alpha = min(0.99, sb.y * exp(power));
      const bool live = !done && !(power > 0.0) && !(alpha < min_alpha);
      const float test_t = T * (1.0 - alpha);
      const bool saturate = live && test_t < 1e-4;
      const bool add = live && !saturate;
      const float w = add ? alpha * T : 0.0;
      C += w * rgb;
      D += w * sb.z;
      T = add ? test_t : T;
      last = add ? base - range.x + j + 1u : last;
      done = done || saturate;
    }
  }
  if (!inside) return;
  const uint pix = v * pc.width + u;
  out_rgb[3u * pix] = C.x + T * pc.bg_r;
  out_rgb[3u * pix + 1u] = C.y + T * pc.bg_g;
  out_rgb[3u * pix + 2u] = C.z + T * pc.bg_b;
  out_depth[pix] = D;
  out_alpha[pix] = 1.0 - T;
  out_final_t[pix] = T;
  out_n_contrib[pix] = last;
}
