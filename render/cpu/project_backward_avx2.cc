#define STREETSIM_PBWD_NS pbwd_avx2
#include "render/cpu/project_bwd.h"
#include "render/cpu/project_backward.h"
#include "render/cpu/project_backward_simd.inc"
