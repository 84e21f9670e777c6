// Blend backward with VK_EXT_shader_atomic_float adds (blend_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "blend_backward.glsl"
