// LiDAR blend backward with compare-and-swap float adds, for devices without
// shaderBufferFloat32AtomicAdd (lidar_blend_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#define CAS_ATOMICS 1
#include "lidar_blend_backward.glsl"
