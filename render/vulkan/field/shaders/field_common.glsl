// Shared pieces of the deformation field's kernels (render/vulkan/field/vulkan_field.h; the cpu
// reference is scene/field/hexplane_kernels.h + field_eval.cc, the formulas docs/field.md).
//
// The planes live in up to 4 storage buffers ("plane groups"): one buffer cannot hold the spec's
// 136 MiB on devices whose maxStorageBufferRange is 128 MiB (lavapipe). The plane table gives
// every plane its group, its float offset in that group and its size; a plane never straddles
// two groups. Group selection is a switch, uniform per plane.
#ifndef STREETSIM_FIELD_COMMON_GLSL_
#define STREETSIM_FIELD_COMMON_GLSL_

#define FIELD_WG 256u
#define PLANES_PER_LEVEL 6u

uint linear_group_id() { return gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x; }

// Coordinates (u, v) of plane c in xy, xz, xt, yz, yt, zt; 3 = time.
uint PlaneU(uint c) { return c < 3u ? 0u : (c < 5u ? 1u : 2u); }
uint PlaneV(uint c) { return c == 0u ? 1u : (c == 1u ? 2u : (c == 3u ? 2u : 3u)); }

// Sampling parameters of every sampling kernel (push constants): p = a * x + b per axis (the
// spec's reversed map, computed in double on the host as the cpu does), the time coordinate.
#define SAMPLE_PUSH                                            \
  layout(push_constant, std430) uniform SamplePush {           \
    float ax, ay, az, bx, by, bz, time_coord;                  \
    uint rows;         /* Gaussians in this batch */          \
    uint time_res;                                             \
  } pc;

// grid_sample's rule (align_corners, border): as internal::MakeTap. Written so that NaN lands on
// 0 (ordered comparisons with NaN are false); the index is clamped again as an integer so that
// no input, however the driver treats NaN, reads outside the plane.
struct Tap {
  uint i0;
  float w;    // weight of the upper texel
  float dpx;  // d(px)/d(p): (R - 1) / 2 inside, 0 where clamped
};
// The tap at the continuous texel coordinate px (the extended field's dilated taps shift px by
// whole texels before the clamp, as internal::MakeTapPx).
float TexelCoord(float p, uint R) { return (p + 1.0) * 0.5 * float(R - 1u); }
Tap MakeTapPx(float px, uint R) {
  const float rm1 = float(R - 1u);
  Tap t;
  t.dpx = (px > 0.0 && px < rm1) ? rm1 * 0.5 : 0.0;
  px = px > 0.0 ? px : 0.0;
  px = px < rm1 ? px : rm1;
  int i0 = int(px);
  i0 = clamp(i0, 0, int(R) - 2);
  t.i0 = uint(i0);
  t.w = clamp(px - float(i0), 0.0, 1.0);
  return t;
}
Tap MakeTap(float p, uint R) { return MakeTapPx(TexelCoord(p, R), R); }

#endif  // STREETSIM_FIELD_COMMON_GLSL_
