#include "scene/field/nn/bi_gru.h"

namespace streetsim::field::nn {

namespace {

using StridedMap = Eigen::OuterStride<>;

// Rows {b*T + j : b} of a [B*T, C] matrix: token j of every row, as a strided [B, C] block.
template <typename T>
Eigen::Map<const Mat<T>, 0, StridedMap> TokenRows(const Mat<T>& m, int tokens, int j) {
  return {m.data() + Eigen::Index{j} * m.cols(), m.rows() / tokens, m.cols(), StridedMap(m.cols() * tokens)};
}
template <typename T>
Eigen::Map<Mat<T>, 0, StridedMap> TokenRows(Mat<T>& m, int tokens, int j) {
  return {m.data() + Eigen::Index{j} * m.cols(), m.rows() / tokens, m.cols(), StridedMap(m.cols() * tokens)};
}

template <typename T>
void InputGates(const GruCellSpec& cell, const T* params, const Mat<T>& x, Mat<T>* gi) {
  const ConstMatMap<T> w_ih(params + cell.w_ih, 3 * cell.hidden, cell.input_dim);
  gi->resize(x.rows(), 3 * cell.hidden);
  gi->noalias() = x * w_ih.transpose();
  gi->rowwise() += Eigen::Map<const RowVec<T>>(params + cell.b_ih, 3 * cell.hidden);
}

template <typename T>
void InputGatesGrad(const GruCellSpec& cell, const T* params, const Mat<T>& x, const Mat<T>& dgi, Mat<T>* dx,
                    bool accumulate, T* d_params) {
  MatMap<T>(d_params + cell.w_ih, 3 * cell.hidden, cell.input_dim).noalias() += dgi.transpose() * x;
  AddColumnSums(dgi, d_params + cell.b_ih);
  if (dx == nullptr) return;
  const ConstMatMap<T> w_ih(params + cell.w_ih, 3 * cell.hidden, cell.input_dim);
  if (accumulate) {
    dx->noalias() += dgi * w_ih;
  } else {
    dx->resize(x.rows(), cell.input_dim);
    dx->noalias() = dgi * w_ih;
  }
}

}  // namespace

absl::StatusOr<BiGruSpec> MakeBiGru(NnLayout* layout, const std::string& name, int tokens, int input_dim, int hidden,
                                    int out_dim) {
  if (tokens <= 0) return absl::InvalidArgumentError(absl::StrCat("bi_gru ", name, ": tokens must be positive"));
  BiGruSpec s;
  s.tokens = tokens;
  s.input_dim = input_dim;
  s.hidden = hidden;
  s.out_dim = out_dim;
  absl::StatusOr<GruCellSpec> f = MakeGruCell(layout, name + ".fwd", input_dim, hidden);
  if (!f.ok()) return f.status();
  absl::StatusOr<GruCellSpec> r = MakeGruCell(layout, name + ".rev", input_dim, hidden);
  if (!r.ok()) return r.status();
  absl::StatusOr<LinearSpec> p = MakeLinear(layout, name + ".proj", 2 * hidden, out_dim);
  if (!p.ok()) return p.status();
  s.fwd = *f;
  s.rev = *r;
  s.proj = *p;
  return s;
}

template <typename T>
void InitBiGru(const BiGruSpec& s, std::mt19937_64& rng, T* params) {
  InitGruCell(s.fwd, rng, params);
  InitGruCell(s.rev, rng, params);
  InitLinear(s.proj, rng, params);
}

template <typename T>
absl::Status BiGruForward(const BiGruSpec& s, const T* params, const ConstRef<T>& tokens, Mat<T>* y,
                          BiGruCache<T>* c) {
  const Eigen::Index rows = tokens.rows();
  const int nt = s.tokens, nh = s.hidden;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("bi_gru", "tokens", rows, tokens.cols(), -1, int64_t{nt} * s.input_dim));
  c->x.resize(rows * nt, s.input_dim);
  for (Eigen::Index r = 0; r < rows; ++r)
    MatMap<T>(c->x.row(r * nt).data(), nt, s.input_dim) = ConstMatMap<T>(tokens.row(r).data(), nt, s.input_dim);
  InputGates(s.fwd, params, c->x, &c->gi_fwd);
  InputGates(s.rev, params, c->x, &c->gi_rev);
  c->fwd.resize(nt);
  c->rev.resize(nt);
  c->h_fwd.resize(nt);
  c->h_rev.resize(nt);
  c->zero.setZero(rows, nh);
  const Mat<T>& zero = c->zero;
  for (int j = 0; j < nt; ++j) {
    const Mat<T>& hf = j == 0 ? zero : c->h_fwd[j - 1];
    STREETSIM_NN_RETURN_IF_ERROR(
        GruStepForward<T>(s.fwd, params, TokenRows(c->gi_fwd, nt, j), hf, &c->h_fwd[j], &c->fwd[j]));
    const Mat<T>& hr = j == 0 ? zero : c->h_rev[j - 1];
    STREETSIM_NN_RETURN_IF_ERROR(
        GruStepForward<T>(s.rev, params, TokenRows(c->gi_rev, nt, nt - 1 - j), hr, &c->h_rev[j], &c->rev[j]));
  }
  c->last.resize(rows, 2 * nh);
  c->last.leftCols(nh) = c->h_fwd[nt - 1];
  c->last.rightCols(nh) = c->h_rev[nt - 1];
  return LinearApply<T>(s.proj, params, c->last, y);
}

template <typename T>
absl::Status BiGruBackward(const BiGruSpec& s, const T* params, BiGruCache<T>& c, const ConstRef<T>& dy,
                           Mat<T>* d_tokens, T* d_params) {
  const Eigen::Index rows = c.last.rows();
  const int nt = s.tokens, nh = s.hidden;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("bi_gru backward", "dy", dy.rows(), dy.cols(), rows, s.out_dim));
  STREETSIM_NN_RETURN_IF_ERROR(LinearGrad<T>(s.proj, params, c.last, dy, &c.d_last, false, d_params));
  c.dgi_fwd.resize(rows * nt, 3 * nh);
  c.dgi_rev.resize(rows * nt, 3 * nh);
  // Back through time, one direction after the other.
  const struct {
    const GruCellSpec* cell;
    std::vector<GruStepCache<T>>* steps;
    Mat<T>* dgi;
    int col;
    bool reversed;
  } dirs[2] = {{&s.fwd, &c.fwd, &c.dgi_fwd, 0, false}, {&s.rev, &c.rev, &c.dgi_rev, nh, true}};
  for (const auto& d : dirs) {
    c.dh = c.d_last.middleCols(d.col, nh);
    for (int j = nt - 1; j >= 0; --j) {
      const int token = d.reversed ? nt - 1 - j : j;
      STREETSIM_NN_RETURN_IF_ERROR(GruStepBackward<T>(*d.cell, params, (*d.steps)[j], c.dh,
                                                      TokenRows(*d.dgi, nt, token), &c.dh_prev, d_params));
      c.dh.swap(c.dh_prev);
    }
  }
  Mat<T>* dx = d_tokens != nullptr ? &c.dx : nullptr;
  InputGatesGrad(s.fwd, params, c.x, c.dgi_fwd, dx, false, d_params);
  InputGatesGrad(s.rev, params, c.x, c.dgi_rev, dx, true, d_params);
  if (d_tokens != nullptr) {
    d_tokens->resize(rows, int64_t{nt} * s.input_dim);
    for (Eigen::Index r = 0; r < rows; ++r)
      MatMap<T>(d_tokens->row(r).data(), nt, s.input_dim) = ConstMatMap<T>(c.dx.row(r * nt).data(), nt, s.input_dim);
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                          \
  template void InitBiGru<T>(const BiGruSpec&, std::mt19937_64&, T*);                                       \
  template absl::Status BiGruForward<T>(const BiGruSpec&, const T*, const ConstRef<T>&, Mat<T>*, BiGruCache<T>*); \
  template absl::Status BiGruBackward<T>(const BiGruSpec&, const T*, BiGruCache<T>&, const ConstRef<T>&, Mat<T>*, T*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
