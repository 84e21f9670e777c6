// GRU cell, PyTorch's nn.GRUCell convention (gate rows r, z, n in W_ih [3H x D], W_hh [3H x H]):
//   r = sigmoid(x W_ir^T + b_ir + h W_hr^T + b_hr)
//   z = sigmoid(x W_iz^T + b_iz + h W_hz^T + b_hz)
//   n = tanh(x W_in^T + b_in + r ⊙ (h W_hn^T + b_hn))
//   h' = (1 - z) ⊙ n + z ⊙ h
// The step functions take the input gates gi = x W_ih^T + b_ih precomputed, so that a sequence
// (bi_gru.h) projects all its tokens in one GEMM.
#pragma once

#include <cstdint>
#include <random>
#include <string>

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_layout.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

struct GruCellSpec {
  int input_dim = 0, hidden = 0;
  size_t w_ih = 0, w_hh = 0, b_ih = 0, b_hh = 0;
  int64_t Macs() const { return 3 * int64_t{hidden} * (input_dim + hidden); }  // per row and step
};

absl::StatusOr<GruCellSpec> MakeGruCell(NnLayout* layout, const std::string& name, int input_dim, int hidden);
// PyTorch's init: every parameter U(-1/sqrt(H), 1/sqrt(H)).
template <typename T>
void InitGruCell(const GruCellSpec& s, std::mt19937_64& rng, T* params);

template <typename T>
struct GruStepCache {
  Mat<T> h_prev, r, z, n, hn;  // [B, H]; hn = h W_hn^T + b_hn
  Mat<T> dgh;                  // backward scratch [B, 3H]
};

// gi [B, 3H] (row-strided blocks allowed), h_prev [B, H] -> h [B, H].
template <typename T>
absl::Status GruStepForward(const GruCellSpec& s, const T* params, const ConstRef<T>& gi, const ConstRef<T>& h_prev,
                            Mat<T>* h, GruStepCache<T>* cache);
// dh [B, H] -> dgi [B, 3H] (written; may be a row-strided block), dh_prev [B, H] (written; null:
// not wanted); W_hh and b_hh gradients added to d_params (W_ih, b_ih are the caller's: dgi).
template <typename T>
absl::Status GruStepBackward(const GruCellSpec& s, const T* params, GruStepCache<T>& cache, const ConstRef<T>& dh,
                             MutRef<T> dgi, Mat<T>* dh_prev, T* d_params);

template <typename T>
struct GruCellCache {
  Mat<T> x, gi, dgi;
  GruStepCache<T> step;
};

// One step as a standalone op: x [B, D], h_prev [B, H] -> h [B, H].
template <typename T>
absl::Status GruCellForward(const GruCellSpec& s, const T* params, const ConstRef<T>& x, const ConstRef<T>& h_prev,
                            Mat<T>* h, GruCellCache<T>* cache);
template <typename T>
absl::Status GruCellBackward(const GruCellSpec& s, const T* params, GruCellCache<T>& cache, const ConstRef<T>& dh,
                             Mat<T>* dx, Mat<T>* dh_prev, T* d_params);

}  // namespace streetsim::field::nn
