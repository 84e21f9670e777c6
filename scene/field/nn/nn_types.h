// Shared types of the extended field's cpu building blocks (docs/field.md, "Extended field
// modules"): row-major Eigen blocks (one row per Gaussian), shape checks, a status macro.
//
// Conventions of every op in scene/field/nn/:
// - a block of B rows (Gaussians); a row's T tokens of width D are stored [B, T*D] (token j of
//   row b at columns [j*D, (j+1)*D)), which is also a contiguous [B*T, D] matrix;
// - Forward(spec, params, inputs, output, cache) keeps in `cache` (required) what the backward
//   needs; composite ops also use it as the backward's scratch. A cache is reused across calls
//   (Eigen keeps the storage when the shape does not change: no allocation after the first block);
// - shapes are checked: a wrong one is an InvalidArgument naming the op, never a crash; a NaN
//   input gives NaN in its own row only (no value-dependent indexing anywhere);
// - Backward(spec, params, cache, dL/doutput, dL/dinputs, d_params) writes dL/dinputs (null: not
//   wanted) and ADDS dL/dparams into the flat gradient array (same layout as the parameters);
// - ops are single-threaded over the block: callers split Gaussians into chunks per thread and sum
//   per-thread parameter gradients, as the field does.
#pragma once

#include <string>

#include <Eigen/Core>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace streetsim::field::nn {

template <typename T>
using Mat = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <typename T>
using RowVec = Eigen::Matrix<T, 1, Eigen::Dynamic>;
template <typename T>
using ColVec = Eigen::Matrix<T, Eigen::Dynamic, 1>;
// Inputs: binds a Mat, a Map or a row-strided block without copying.
template <typename T>
using ConstRef = Eigen::Ref<const Mat<T>>;
// Outputs written in place into a (possibly row-strided) block.
template <typename T>
using MutRef = Eigen::Ref<Mat<T>>;
template <typename T>
using MatMap = Eigen::Map<Mat<T>>;
template <typename T>
using ConstMatMap = Eigen::Map<const Mat<T>>;

// d_params[0, cols) += the column sums of m (a bias gradient). Through an Eigen-allocated (so
// aligned) temporary: `Map(d_params) += m.colwise().sum()` peels columns up to the Map's runtime
// alignment and sums them in another order than the vectorised ones, so the last bits would
// follow where malloc put the gradient array (docs/training.md "Reproducibility").
template <typename T, typename Derived>
void AddColumnSums(const Eigen::DenseBase<Derived>& m, T* d_params) {
  const RowVec<T> sums = m.colwise().sum();
  Eigen::Map<RowVec<T>>(d_params, sums.size()) += sums;
}

#define STREETSIM_NN_RETURN_IF_ERROR(expr)   \
  do {                                       \
    absl::Status _nn_status = (expr);        \
    if (!_nn_status.ok()) return _nn_status; \
  } while (0)

// rows < 0: any number of rows.
inline absl::Status CheckShape(const char* op, const char* what, Eigen::Index rows, Eigen::Index cols,
                               Eigen::Index want_rows, Eigen::Index want_cols) {
  if ((want_rows >= 0 && rows != want_rows) || cols != want_cols) {
    return absl::InvalidArgumentError(absl::StrCat(op, ": ", what, " is ", rows, " x ", cols, ", expected ",
                                                   want_rows < 0 ? std::string("B") : absl::StrCat(want_rows),
                                                   " x ", want_cols));
  }
  return absl::OkStatus();
}

}  // namespace streetsim::field::nn
