// Token backward with VK_EXT_shader_atomic_float adds (ext_sample_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "ext_sample_backward.glsl"
