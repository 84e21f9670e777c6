// Token backward with compare-and-swap float adds (ext_sample_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#define CAS_ATOMICS 1
#include "ext_sample_backward.glsl"
