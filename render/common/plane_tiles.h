// Row-major values into planes (value v of row i at plane v, index i), the layout the cpu
// renderer reads: a scene's SH upload (render/cpu/scene_soa.cc) and the serving form written
// straight into an engine's copy (scene/field/serving_form_tables.cc) both go through here.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace streetsim::planes {

// 1 where the float is inf or nan (exponent all ones); integer test, immune to -ffast-math.
inline uint32_t NonFinite(float v) {
  uint32_t b;
  std::memcpy(&b, &v, 4);
  return (b & 0x7f800000u) == 0x7f800000u;
}

#if defined(__AVX2__)
// Rows 0..7 (row k at rows + k * stride), values v0 .. v0+7, transposed: out[j] holds value v0 + j
// of the eight rows. Flags a non-finite value in `bad`.
inline void Transpose8x8(const float* rows, size_t stride, int v0, __m256 out[8], __m256i& bad) {
  const __m256i exp_mask = _mm256_set1_epi32(0x7f800000);
  __m256 r[8];
  for (int k = 0; k < 8; ++k) {
    r[k] = _mm256_loadu_ps(rows + k * stride + v0);
    const __m256i e = _mm256_and_si256(_mm256_castps_si256(r[k]), exp_mask);
    bad = _mm256_or_si256(bad, _mm256_cmpeq_epi32(e, exp_mask));
  }
  const __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
  const __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
  const __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
  const __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
  // Per 128-bit half h: u_j = column 4h + j of rows 0-3 (u0..u3) and rows 4-7 (u4..u7).
  const __m256 u0 = _mm256_shuffle_ps(t0, t2, 0x44), u1 = _mm256_shuffle_ps(t0, t2, 0xee);
  const __m256 u2 = _mm256_shuffle_ps(t1, t3, 0x44), u3 = _mm256_shuffle_ps(t1, t3, 0xee);
  const __m256 u4 = _mm256_shuffle_ps(t4, t6, 0x44), u5 = _mm256_shuffle_ps(t4, t6, 0xee);
  const __m256 u6 = _mm256_shuffle_ps(t5, t7, 0x44), u7 = _mm256_shuffle_ps(t5, t7, 0xee);
  out[0] = _mm256_permute2f128_ps(u0, u4, 0x20);
  out[1] = _mm256_permute2f128_ps(u1, u5, 0x20);
  out[2] = _mm256_permute2f128_ps(u2, u6, 0x20);
  out[3] = _mm256_permute2f128_ps(u3, u7, 0x20);
  out[4] = _mm256_permute2f128_ps(u0, u4, 0x31);
  out[5] = _mm256_permute2f128_ps(u1, u5, 0x31);
  out[6] = _mm256_permute2f128_ps(u2, u6, 0x31);
  out[7] = _mm256_permute2f128_ps(u3, u7, 0x31);
}

// Values [0, values) (a multiple of 8) of `count` rows (a multiple of 8; row r at rows + r *
// stride) into planes: dst[v * plane + r], 8 x 8 at a time through registers. Returns 1 if any
// moved value is inf or nan.
inline uint32_t TransposeRows8(const float* rows, size_t stride, int count, int values, float* dst, size_t plane) {
  __m256i bad = _mm256_setzero_si256();
  for (int g = 0; g < count; g += 8) {
    for (int v0 = 0; v0 < values; v0 += 8) {
      __m256 t[8];
      Transpose8x8(rows + g * stride, stride, v0, t, bad);
      float* d = dst + static_cast<size_t>(v0) * plane + g;
      for (int j = 0; j < 8; ++j) _mm256_storeu_ps(d + j * plane, t[j]);
    }
  }
  return _mm256_testz_si256(bad, bad) ? 0u : 1u;
}

// Sixteen rows into their planes, values [0, values) (a multiple of 8), where dst (plane 0 at
// the first row) and plane make each plane's sixteen one whole, aligned cache line: written with
// streaming stores. A served scene's new time is ~100 MB that the render reads back from memory
// anyway; streaming skips reading every destination line first. The caller fences (_mm_sfence)
// before the planes are read. Returns 1 if any value is inf or nan.
inline uint32_t StreamRows16(const float* rows, size_t stride, int values, float* dst, size_t plane) {
  __m256i bad = _mm256_setzero_si256();
  for (int v0 = 0; v0 < values; v0 += 8) {
    __m256 lo[8], hi[8];
    Transpose8x8(rows, stride, v0, lo, bad);
    Transpose8x8(rows + 8 * stride, stride, v0, hi, bad);
    float* d = dst + static_cast<size_t>(v0) * plane;
    for (int j = 0; j < 8; ++j) {
      _mm256_stream_ps(d + j * plane, lo[j]);
      _mm256_stream_ps(d + j * plane + 8, hi[j]);
    }
  }
  return _mm256_testz_si256(bad, bad) ? 0u : 1u;
}
#endif

}  // namespace streetsim::planes
