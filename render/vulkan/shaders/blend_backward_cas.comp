// Blend backward with compare-and-swap float adds, for devices without
// shaderBufferFloat32AtomicAdd (blend_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#define CAS_ATOMICS 1
#include "blend_backward.glsl"
