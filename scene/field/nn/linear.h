// Linear layer y = x W^T + b over a block of rows; W row-major [out x in] (PyTorch's layout, as
// the field's DenseInfo).
#pragma once

#include <cstdint>
#include <random>
#include <string>

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_layout.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

struct LinearSpec {
  int in = 0, out = 0;
  bool bias = true;
  size_t w_offset = 0, b_offset = 0;  // b_offset: only with bias
  int64_t Macs() const { return int64_t{in} * out; }  // per row, forward
};

absl::StatusOr<LinearSpec> MakeLinear(NnLayout* layout, const std::string& name, int in, int out, bool bias = true);

// Xavier-uniform weights, bias U(-1/sqrt(in), 1/sqrt(in)) (the field's init).
template <typename T>
void InitLinear(const LinearSpec& s, std::mt19937_64& rng, T* params);

template <typename T>
struct LinearCache {
  Mat<T> x;
};

// x [B, in] -> y [B, out].
template <typename T>
absl::Status LinearForward(const LinearSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y,
                           LinearCache<T>* cache);
// dy [B, out] -> dx [B, in] (null: not wanted); dW, db added to d_params.
template <typename T>
absl::Status LinearBackward(const LinearSpec& s, const T* params, const LinearCache<T>& cache, const ConstRef<T>& dy,
                            Mat<T>* dx, T* d_params);

// The same without the cache copy, for the composite ops that keep x themselves. dx, when
// non-null, is overwritten (accumulate = false) or added to (accumulate = true).
template <typename T>
absl::Status LinearApply(const LinearSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y);
template <typename T>
absl::Status LinearGrad(const LinearSpec& s, const T* params, const ConstRef<T>& x, const ConstRef<T>& dy,
                        Mat<T>* dx, bool accumulate, T* d_params);

}  // namespace streetsim::field::nn
