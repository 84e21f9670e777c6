// Forward HexPlane features: F[g][l * C + k] = prod over the level's 6 planes of the bilinear
// sample of channel k (as field_eval.cc's FeatureChunk). One invocation per (Gaussian, feature):
// neighbouring invocations read neighbouring channels of the same texels.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"
#include "field_planes.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 5) readonly buffer Means { float means[]; };  // [rows * 3]
layout(std430, binding = 6) writeonly buffer Features { float features[]; };  // [rows * D]
SAMPLE_PUSH

void main() {
  const uint C = CHANNELS;
  const uint D = LEVELS * C;
  const uint t = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (t >= pc.rows * D) return;
  const uint g = t / D, d = t - g * D;
  const uint l = d / C, k = d - l * C;
  const float p[3] = float[3](pc.ax * means[g * 3u] + pc.bx, pc.ay * means[g * 3u + 1u] + pc.by,
                              pc.az * means[g * 3u + 2u] + pc.bz);
  const uint R = plane_table[l * PLANES_PER_LEVEL].z;
  const Tap taps[4] = Tap[4](MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R),
                             MakeTap(pc.time_coord, pc.time_res));
  float f = 1.0;
  for (uint c = 0u; c < PLANES_PER_LEVEL; ++c) {
    const PlaneTaps pt = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], taps[PlaneU(c)],
                                       taps[PlaneV(c)], C, k);
    const float s = pt.w00 * LoadPlane(pt.group, pt.off00) + pt.w01 * LoadPlane(pt.group, pt.off00 + C) +
                    pt.w10 * LoadPlane(pt.group, pt.off00 + pt.row) +
                    pt.w11 * LoadPlane(pt.group, pt.off00 + pt.row + C);
    f *= s;
  }
  features[t] = f;
}
