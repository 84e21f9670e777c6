// Blend backward without atomics: per-tile-instance slots in fixed-order sums
// (blend_backward.glsl, DETERMINISTIC; blend_backward_reduce.comp finishes the sums).
#version 460
#extension GL_GOOGLE_include_directive : require
#define DETERMINISTIC 1
#include "blend_backward.glsl"
