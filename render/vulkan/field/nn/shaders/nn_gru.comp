// One GRU step (scene/field/nn/gru_cell.h, PyTorch's gate order r, z, n), one invocation per row
// and hidden unit i, from the input and hidden gates gi, gh = [r | z | n] pre-activations:
//   forward:  r = sigmoid(gi_r + gh_r), z = sigmoid(gi_z + gh_z), n = tanh(gi_n + r gh_n),
//             h = (1 - z) n + z h_prev                           (writes h and rzn = [r | z | n])
//   backward: dn = dh (1 - z) (1 - n^2), dz = dh (h_prev - n) z (1 - z), dr = dn gh_n r (1 - r),
//             dgi = [dr | dz | dn], dgh = [dr | dz | dn r], dh_prev = z dh
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer GI { float gi[]; };    // forward
layout(std430, binding = 1) readonly buffer GH { float gh[]; };
layout(std430, binding = 2) readonly buffer HP { float hp[]; };    // h_prev
layout(std430, binding = 3) buffer RZN { float rzn[]; };           // forward: written; backward: read
layout(std430, binding = 4) buffer Hb { float hb[]; };             // forward: h; backward: dh (read)
layout(std430, binding = 5) writeonly buffer DGI { float dgi[]; };
layout(std430, binding = 6) writeonly buffer DGH { float dgh[]; };
layout(std430, binding = 7) writeonly buffer DHP { float dhp[]; };
layout(push_constant, std430) uniform Push {
  uint rows, H, backward;
  uint gi_off, gi_stride, gh_off, gh_stride, hp_off, hp_stride, g_off, g_stride, h_off, h_stride;
  uint dgi_off, dgi_stride, dgh_off, dgh_stride, dhp_off, dhp_stride;
} pc;

void main() {
  const uint idx = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (idx >= pc.rows * pc.H) return;  // the host keeps rows * H within 32 bits
  const uint b = idx / pc.H, i = idx % pc.H, H = pc.H;
  const uint ghb = pc.gh_off + b * pc.gh_stride;
  const uint gb = pc.g_off + b * pc.g_stride;
  const float h_prev = hp[pc.hp_off + b * pc.hp_stride + i];
  if (pc.backward == 0u) {
    const uint gib = pc.gi_off + b * pc.gi_stride;
    const float r = Sigmoid(gi[gib + i] + gh[ghb + i]);
    const float z = Sigmoid(gi[gib + H + i] + gh[ghb + H + i]);
    const float n = SafeTanh(gi[gib + 2u * H + i] + r * gh[ghb + 2u * H + i]);
    rzn[gb + i] = r;
    rzn[gb + H + i] = z;
    rzn[gb + 2u * H + i] = n;
    hb[pc.h_off + b * pc.h_stride + i] = (1.0 - z) * n + z * h_prev;
    return;
  }
  const float r = rzn[gb + i], z = rzn[gb + H + i], n = rzn[gb + 2u * H + i];
  const float dh = hb[pc.h_off + b * pc.h_stride + i];
  const float dn = dh * (1.0 - z) * (1.0 - n * n);
  const float dz = dh * (h_prev - n) * z * (1.0 - z);
  const float dr = dn * gh[ghb + 2u * H + i] * r * (1.0 - r);
  const uint dib = pc.dgi_off + b * pc.dgi_stride, dhb = pc.dgh_off + b * pc.dgh_stride;
  dgi[dib + i] = dr;
  dgi[dib + H + i] = dz;
  dgi[dib + 2u * H + i] = dn;
  dgh[dhb + i] = dr;
  dgh[dhb + H + i] = dz;
  dgh[dhb + 2u * H + i] = dn * r;
  dhp[pc.dhp_off + b * pc.dhp_stride + i] = z * dh;
}
