// Temporal tokens (method.md section 2 item 3): token j of a row is
// [sin(2^k pi t_j) for k < m, cos(2^k pi t_j) for k < m, features_j], where t_j is the token's time
// coordinate (t + j dt for the window around t, in the field's [-1, 1] time axis) and features_j
// the space-time plane features sampled at t_j. Each token carries its own time so that the
// attention (otherwise blind to order) knows where in the window it sits. No parameters.
#pragma once

#include <cstdint>

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

struct FourierTimeSpec {
  int frequencies = 0;  // m
  int tokens = 0;       // T = 2k + 1
  int feature_dim = 0;  // F, per token
  int token_dim() const { return 2 * frequencies + feature_dim; }
};

absl::StatusOr<FourierTimeSpec> MakeFourierTime(int frequencies, int tokens, int feature_dim);

template <typename T>
struct FourierTimeCache {
  Mat<T> sin, cos;  // [B, T*m]
};

// times [B, T], features [B, T*F] -> tokens [B, T*(2m+F)].
template <typename T>
absl::Status FourierTimeForward(const FourierTimeSpec& s, const ConstRef<T>& times, const ConstRef<T>& features,
                                Mat<T>* tokens, FourierTimeCache<T>* cache);
// d_tokens -> d_times [B, T] and d_features [B, T*F] (either may be null).
template <typename T>
absl::Status FourierTimeBackward(const FourierTimeSpec& s, const FourierTimeCache<T>& cache,
                                 const ConstRef<T>& d_tokens, Mat<T>* d_times, Mat<T>* d_features);

}  // namespace streetsim::field::nn
