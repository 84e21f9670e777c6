#define STREETSIM_LIDAR_NS simd_avx2
#include "render/lidar/lidar_kernels.h"
#include "render/lidar/lidar_simd.inc"
#include "render/lidar/lidar_backward_simd.inc"
