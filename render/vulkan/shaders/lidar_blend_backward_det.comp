// LiDAR blend backward without atomics: per-tile-instance slots in fixed-order sums
// (lidar_blend_backward.glsl, DETERMINISTIC; lidar_det_rank_of.comp and lidar_det_reduce.comp
// finish the sums).
#version 460
#extension GL_GOOGLE_include_directive : require
#define DETERMINISTIC 1
#include "lidar_blend_backward.glsl"
