#define STREETSIM_PROJECT_NS project_avx2
#include "render/cpu/project.h"
#include "render/cpu/project_simd.inc"
