// Plane buffers and the plane table (bindings 0..4) of the sampling kernels.
#ifndef STREETSIM_FIELD_PLANES_GLSL_
#define STREETSIM_FIELD_PLANES_GLSL_

// The layout's channels and levels as specialisation constants: the (Gaussian, feature) index
// splits become divisions by constants.
layout(constant_id = 0) const uint CHANNELS = 32u;
layout(constant_id = 1) const uint LEVELS = 4u;

layout(std430, binding = 0) readonly buffer Planes0 { float planes0[]; };
layout(std430, binding = 1) readonly buffer Planes1 { float planes1[]; };
layout(std430, binding = 2) readonly buffer Planes2 { float planes2[]; };
layout(std430, binding = 3) readonly buffer Planes3 { float planes3[]; };
// Per plane (level-major, 6 per level): (group, float offset in the group, width, height).
layout(std430, binding = 4) readonly buffer PlaneTable { uvec4 plane_table[]; };

float LoadPlane(uint group, uint i) {
  switch (group) {
    case 0u: return planes0[i];
    case 1u: return planes1[i];
    case 2u: return planes2[i];
    default: return planes3[i];
  }
}

// The four taps of one plane sample of channel k (as internal::MakePlaneTaps).
struct PlaneTaps {
  uint group, off00, row;  // row: offset from v0 to v1 (width * channels)
  float w00, w01, w10, w11;
};
PlaneTaps MakePlaneTaps(uvec4 info, Tap a, Tap b, uint C, uint k) {
  PlaneTaps t;
  t.group = info.x;
  t.row = info.z * C;
  t.off00 = info.y + b.i0 * t.row + a.i0 * C + k;
  t.w00 = (1.0 - a.w) * (1.0 - b.w);
  t.w01 = a.w * (1.0 - b.w);
  t.w10 = (1.0 - a.w) * b.w;
  t.w11 = a.w * b.w;
  return t;
}

#endif  // STREETSIM_FIELD_PLANES_GLSL_
