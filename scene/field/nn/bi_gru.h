// Memory (method.md section 2 item 5): a bidirectional GRU over the row's T fused tokens, both
// directions starting from h = 0; the forward direction reads tokens 0..T-1, the reverse one
// T-1..0. The output is the concatenation of the two last hidden states [h_fwd(T-1), h_rev(0)]
// (2H), projected by a Linear to out_dim: F_f = [h_f, h_r] Wp^T + bp.
#pragma once

#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/field/nn/gru_cell.h"
#include "scene/field/nn/linear.h"

namespace streetsim::field::nn {

struct BiGruSpec {
  int tokens = 0, input_dim = 0, hidden = 0, out_dim = 0;
  GruCellSpec fwd, rev;
  LinearSpec proj;
  int64_t Macs() const { return int64_t{tokens} * (fwd.Macs() + rev.Macs()) + proj.Macs(); }  // per row
};

absl::StatusOr<BiGruSpec> MakeBiGru(NnLayout* layout, const std::string& name, int tokens, int input_dim, int hidden,
                                    int out_dim);
template <typename T>
void InitBiGru(const BiGruSpec& s, std::mt19937_64& rng, T* params);

template <typename T>
struct BiGruCache {
  Mat<T> x;                 // tokens as [B*T, D]
  Mat<T> gi_fwd, gi_rev;    // input gates of every token [B*T, 3H] (row b*T + j)
  std::vector<GruStepCache<T>> fwd, rev;  // per step (step j of the reverse direction reads token T-1-j)
  std::vector<Mat<T>> h_fwd, h_rev;       // hidden state after each step [B, H]
  Mat<T> zero;              // initial hidden state [B, H]
  Mat<T> last;              // [h_fwd(T-1), h_rev(0)]  [B, 2H]
  // Backward scratch.
  Mat<T> d_last, dh, dh_prev, dgi_fwd, dgi_rev, dx;
};

// tokens [B, T*D] -> y [B, out_dim].
template <typename T>
absl::Status BiGruForward(const BiGruSpec& s, const T* params, const ConstRef<T>& tokens, Mat<T>* y,
                          BiGruCache<T>* cache);
// dy [B, out_dim] -> d_tokens [B, T*D] (null: not wanted); parameter gradients added.
template <typename T>
absl::Status BiGruBackward(const BiGruSpec& s, const T* params, BiGruCache<T>& cache, const ConstRef<T>& dy,
                           Mat<T>* d_tokens, T* d_params);

}  // namespace streetsim::field::nn
