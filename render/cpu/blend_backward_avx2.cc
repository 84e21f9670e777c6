#define STREETSIM_BWD_NS bwd_avx2
#include "render/cpu/blend_backward.h"
#include "render/cpu/blend_backward_simd.inc"
