// The VAE's sampling step and KL (scene/field/nn/vae_sampler.h), latent L:
//   forward (one invocation per row): z = mu + exp(logvar / 2) ⊙ eps (z = mu without eps),
//            kl = 1/2 sum_i (mu_i^2 + exp(logvar_i) - logvar_i - 1)
//   backward (one per row and latent i): d_mu = dz + w mu,
//            d_logvar = dz eps exp(logvar / 2) / 2 (0 without eps) + w (exp(logvar) - 1) / 2
// (w the KL weight). The KL's per-row loop is L iterations.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer ML { float ml[]; };    // [rows x 2L]: mu, logvar
layout(std430, binding = 1) readonly buffer Eps { float eps[]; };  // [rows x L] (has_eps)
layout(std430, binding = 2) buffer Z { float z[]; };               // forward: z; backward: dz
layout(std430, binding = 3) buffer KL { float kl[]; };             // forward: [rows x 1]; backward: d_mu_logvar
layout(push_constant, std430) uniform Push {
  uint rows, L, backward, has_eps;
  float kl_weight;
  uint m_off, m_stride, e_off, e_stride, z_off, z_stride, k_off, k_stride;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (pc.backward == 0u) {
    if (i >= pc.rows) return;
    const uint mb = pc.m_off + i * pc.m_stride;
    float s = 0.0;
    for (uint c = 0u; c < pc.L; ++c) {
      const float mu = ml[mb + c], lv = ml[mb + pc.L + c];
      float v = mu;
      if (pc.has_eps != 0u) v += exp(0.5 * lv) * eps[pc.e_off + i * pc.e_stride + c];
      z[pc.z_off + i * pc.z_stride + c] = v;
      s += mu * mu + exp(lv) - lv - 1.0;
    }
    kl[pc.k_off + i * pc.k_stride] = 0.5 * s;
    return;
  }
  if (i >= pc.rows * pc.L) return;  // the host keeps rows * L within 32 bits
  const uint r = i / pc.L, c = i % pc.L;
  const uint mb = pc.m_off + r * pc.m_stride;
  const float mu = ml[mb + c], lv = ml[mb + pc.L + c];
  const float dz = z[pc.z_off + r * pc.z_stride + c];
  float dlv = pc.kl_weight * 0.5 * (exp(lv) - 1.0);
  if (pc.has_eps != 0u) dlv += dz * eps[pc.e_off + r * pc.e_stride + c] * exp(0.5 * lv) * 0.5;
  const uint kb = pc.k_off + r * pc.k_stride;
  kl[kb + c] = dz + pc.kl_weight * mu;
  kl[kb + pc.L + c] = dlv;
}
