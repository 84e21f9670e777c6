// Feature backward with compare-and-swap float adds, for devices without
// shaderBufferFloat32AtomicAdd (field_sample_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#define CAS_ATOMICS 1
#include "field_sample_backward.glsl"
