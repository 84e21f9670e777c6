// The serving form at one time, written into a Vulkan scene's parameter buffers: one invocation
// per moving Gaussian, reading its record (scene/field/serving_form_tables.h FormTables::
// RecordLayout) and writing what the form models. The cpu reference is FormTables::Evaluate; the
// arithmetic is the same, in the same order (the device may fuse a multiply-add where the host
// does not: a few ulps).
//
// The scene's layout (render/vulkan/stages.h): geometry 12 floats per Gaussian (mean, opacity
// logit, log-scales, pad, rotation), SH in four buffers of 4 coefficients x 3 channels.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Records { uint rec[]; };
// [blocks, ends, position_step, q_position, control points, then 10 words per block: groups,
// channels, rank, group_count and the word offsets of base_offset, base_step, scale, q_base,
// q_u, q_v] (VulkanServingForm::Create).
layout(std430, binding = 1) readonly buffer Desc { uint desc[]; };
layout(std430, binding = 2) buffer Geometry { float geo[]; };
layout(std430, binding = 3) buffer Sh0 { float sh0[]; };
layout(std430, binding = 4) buffer Sh1 { float sh1[]; };
layout(std430, binding = 5) buffer Sh2 { float sh2[]; };
layout(std430, binding = 6) buffer Sh3 { float sh3[]; };
layout(push_constant, std430) uniform Push {
  uint rows;          // records in this buffer
  uint record_words;
  uint k;             // the spline's first control point
  uint taps;          // degree + 1
  float w0, w1, w2, w3;
  float line;         // where on the line between the end points the taps fall
  uint s3_rank1;      // 1: one appearance block (DC + bands) at rank 1, S3Gaussian's default form
} pc;

#define MAX_RANK 8u  // kMaxAppearanceRank
#define GROUP_COLOUR 1u
#define GROUP_LOG_SCALE 2u
#define GROUP_ROTATION 3u
#define GROUP_OPACITY 4u
#define GROUP_SH_BANDS 5u

float W(uint t) { return t == 0u ? pc.w0 : (t == 1u ? pc.w1 : (t == 2u ? pc.w2 : pc.w3)); }

// int8 number `i` of the array starting at word `word` of the record at `base`.
float I8(uint base, uint word, uint i) {
  const uint v = rec[base + word + (i >> 2u)];
  return float(bitfieldExtract(int(v), int((i & 3u) * 8u), 8));
}
// bfloat16 number `i` of the array starting at word `word`.
float Bf16(uint base, uint word, uint i) {
  const uint v = rec[base + word + (i >> 1u)];
  return uintBitsToFloat(((i & 1u) == 0u ? (v & 0xffffu) : (v >> 16u)) << 16u);
}

void WriteSh(uint i, uint f, float v) {  // flat SH value f = 3 * coefficient + channel
  const uint at = i * 12u + f % 12u;
  const uint g = f / 12u;
  if (g == 0u) sh0[at] = v;
  else if (g == 1u) sh1[at] = v;
  else if (g == 2u) sh2[at] = v;
  else sh3[at] = v;
}

void Write(uint group, uint i, uint c, float v) {
  if (group == GROUP_COLOUR) WriteSh(i, c, v);
  else if (group == GROUP_SH_BANDS) WriteSh(i, 3u + c, v);
  else if (group == GROUP_LOG_SCALE) geo[i * 12u + 4u + c] = v;
  else if (group == GROUP_ROTATION) geo[i * 12u + 8u + c] = v;
  else geo[i * 12u + 3u] = v;  // GROUP_OPACITY
}

uint GroupChannels(uint g) {
  return g == GROUP_COLOUR ? 3u : (g == GROUP_LOG_SCALE ? 3u : (g == GROUP_ROTATION ? 4u : (g == GROUP_OPACITY ? 1u : 45u)));
}

void main() {
  const uint r = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (r >= pc.rows) return;
  const uint base = r * pc.record_words;
  const uint i = rec[base];
  const uint ends = desc[1], pstep = desc[2], qpos = desc[3], M = desc[4];
  for (uint c = 0u; c < 3u; ++c) {
    float s = 0.0;
    for (uint t = 0u; t < pc.taps; ++t) s += W(t) * I8(base, qpos, (pc.k + t) * 3u + c);
    const float e0 = uintBitsToFloat(rec[base + ends + c]), e1 = uintBitsToFloat(rec[base + ends + 3u + c]);
    geo[i * 12u + c] = e0 + (e1 - e0) * pc.line + Bf16(base, pstep, c) * s;
  }
  if (pc.s3_rank1 != 0u) {
    // S3Gaussian's default form: 48 appearance channels = 12 words of int8 per table, one word of
    // q_base and q_v read for 4 channels, each SH buffer written with fixed indices (the general
    // path below reads a word per byte and branches per channel).
    const uint d = 5u;
    const uint w_off = desc[d + 4u], w_step = desc[d + 5u], w_scale = desc[d + 6u];
    const uint w_qb = desc[d + 7u], w_qu = desc[d + 8u], w_qv = desc[d + 9u];
    float s = 0.0;
    for (uint t = 0u; t < pc.taps; ++t) s += W(t) * I8(base, w_qu, pc.k + t);
    const float a = Bf16(base, w_scale, 0u) * s;
    const float off0 = uintBitsToFloat(rec[base + w_off]), st0 = Bf16(base, w_step, 0u);
    const float off1 = uintBitsToFloat(rec[base + w_off + 1u]), st1 = Bf16(base, w_step, 1u);
    float v[48];
    for (uint wd = 0u; wd < 12u; ++wd) {
      const int qb = int(rec[base + w_qb + wd]), qv = int(rec[base + w_qv + wd]);
      for (uint b = 0u; b < 4u; ++b) {
        const uint c = wd * 4u + b;
        const float base_value = c < 3u ? off0 + st0 * float(bitfieldExtract(qb, int(b * 8u), 8))
                                        : off1 + st1 * float(bitfieldExtract(qb, int(b * 8u), 8));
        v[c] = base_value + a * float(bitfieldExtract(qv, int(b * 8u), 8));
      }
    }
    for (uint c = 0u; c < 12u; ++c) {
      sh0[i * 12u + c] = v[c];
      sh1[i * 12u + c] = v[12u + c];
      sh2[i * 12u + c] = v[24u + c];
      sh3[i * 12u + c] = v[36u + c];
    }
    return;
  }
  float ut[MAX_RANK];
  const uint blocks = desc[0];
  for (uint b = 0u; b < blocks; ++b) {
    const uint d = 5u + b * 10u;
    const uint groups = desc[d], n = desc[d + 1u], R = desc[d + 2u], G = desc[d + 3u];
    const uint w_off = desc[d + 4u], w_step = desc[d + 5u], w_scale = desc[d + 6u];
    const uint w_qb = desc[d + 7u], w_qu = desc[d + 8u], w_qv = desc[d + 9u];
    for (uint j = 0u; j < R; ++j) {
      float s = 0.0;
      for (uint t = 0u; t < pc.taps; ++t) s += W(t) * I8(base, w_qu, j * M + pc.k + t);
      ut[j] = Bf16(base, w_scale, j) * s;
    }
    uint c0 = 0u, gi = 0u;
    for (uint g = 1u; g < 6u; ++g) {
      if ((groups & (1u << g)) == 0u) continue;
      const uint count = GroupChannels(g);
      const float off = uintBitsToFloat(rec[base + w_off + gi]), step = Bf16(base, w_step, gi);
      for (uint c = 0u; c < count; ++c) {
        float v = off + step * I8(base, w_qb, c0 + c);
        for (uint j = 0u; j < R; ++j) v += ut[j] * I8(base, w_qv, j * n + c0 + c);
        Write(g, i, c, v);
      }
      c0 += count;
      ++gi;
    }
  }
}
