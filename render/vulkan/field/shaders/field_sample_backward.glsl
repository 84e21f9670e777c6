// Backward of the HexPlane features (shared body of field_sample_backward.comp and its
// compare-and-swap twin): given dL/dF, the plane-texel gradients (bilinear splat, added with float
// atomics) and dL/d(canonical mean) through the sampling coordinates (zero where clamped), as
// field_eval.cc's FeatureRowBackward + ScatterPlane.
//
// 32 invocations per Gaussian (8 per workgroup; nothing assumes a subgroup size): invocation
// `lane` takes features lane, lane + 32, ... (neighbouring lanes: neighbouring channels of the same
// texels). Per feature it re-samples the level's 6 planes, forms dL/d(sample) with prefix/suffix
// products (no division: a sample can be 0), splats it onto the 4 texels of each plane and adds
// its share of the coordinate gradient; the 32 shares are summed in shared memory (fixed order:
// d_means is deterministic, the plane gradients are not, their atomics land in any order).
#extension GL_GOOGLE_include_directive : require
#include "field_sample_backward_head.glsl"

layout(std430, binding = 6) readonly buffer DFeatures { float d_features[]; };  // [rows * D]
SAMPLE_PUSH
#include "field_plane_grads.glsl"

void main() {
  const uint C = CHANNELS;
  const uint D = LEVELS * C;
  const uint tid = gl_LocalInvocationID.x;
  const uint lane = tid % LANES;
  const uint g = linear_group_id() * (FIELD_WG / LANES) + tid / LANES;
  float dp[3] = float[3](0.0, 0.0, 0.0);
  if (g < pc.rows) {
    const float p[3] = SampleCoords(g);
    const Tap tt = MakeTap(pc.time_coord, pc.time_res);
    for (uint d = lane; d < D; d += LANES) {
      const float df = d_features[g * D + d];
      if (df == 0.0) continue;  // every dL/d(sample) of this feature is 0
      const uint l = d / C, k = d - l * C;
      const uint R = plane_table[l * PLANES_PER_LEVEL].z;
      const Tap taps[4] = Tap[4](MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R), tt);
      PlaneTaps pts[6];
      float v[6][4];
      float s[6];
      for (uint c = 0u; c < PLANES_PER_LEVEL; ++c) {
        pts[c] = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], taps[PlaneU(c)], taps[PlaneV(c)], C, k);
        s[c] = LoadSample(pts[c], v[c]);
      }
      float suf[6];
      suf[5] = 1.0;
      for (int c = 4; c >= 0; --c) suf[c] = suf[c + 1] * s[c + 1];
      float pre = df;
      for (uint c = 0u; c < PLANES_PER_LEVEL; ++c) {
        const float gc = pre * suf[c];
        pre *= s[c];
        const uint cu = PlaneU(c), cv = PlaneV(c);
        const vec2 duv = SplatSample(pts[c], v[c], taps[cu].w, taps[cv].w, gc);
        dp[cu] += duv.x * taps[cu].dpx;
        if (cv != 3u) dp[cv] += duv.y * taps[cv].dpx;  // time is not a parameter
      }
    }
  }
  WriteMeanGrads(tid, lane, g, dp);
}
