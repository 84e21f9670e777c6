// Feature backward with VK_EXT_shader_atomic_float adds (field_sample_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_sample_backward.glsl"
