#define STREETSIM_BLEND_NS simd_avx2
#include "render/cpu/blend.h"
#include "render/cpu/blend_simd.inc"
