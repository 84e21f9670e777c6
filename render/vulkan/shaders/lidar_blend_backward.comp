// LiDAR blend backward with VK_EXT_shader_atomic_float adds (lidar_blend_backward.glsl).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_blend_backward.glsl"
