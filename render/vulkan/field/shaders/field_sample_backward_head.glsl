// The head of the two sample-backward kernels: the base field's feature backward
// (field_sample_backward.glsl) and the extended field's token backward
// (render/vulkan/field/ext/shaders/ext_sample_backward.glsl). Float atomics unless CAS_ATOMICS,
// the plane sampling code, LANES invocations per Gaussian in 256-wide workgroups, the Gaussians'
// means (binding 5) and dL/d(mean) (binding 7, written). Include it first (an #extension must
// precede every declaration); then declare binding 6 and the push constants `pc`, and include
// field_plane_grads.glsl.
#ifndef STREETSIM_FIELD_SAMPLE_BACKWARD_HEAD_GLSL_
#define STREETSIM_FIELD_SAMPLE_BACKWARD_HEAD_GLSL_

#ifndef CAS_ATOMICS
#extension GL_EXT_shader_atomic_float : require
#endif
#include "field_common.glsl"
#include "field_planes.glsl"

#define LANES 32u

layout(local_size_x = 256) in;
layout(std430, binding = 5) readonly buffer Means { float means[]; };      // [rows * 3]
layout(std430, binding = 7) writeonly buffer DMeans { float d_means[]; };  // [rows * 3]

#endif  // STREETSIM_FIELD_SAMPLE_BACKWARD_HEAD_GLSL_
