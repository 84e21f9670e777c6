#include "scene/field/nn/gru_cell.h"

#include <cmath>

namespace streetsim::field::nn {

absl::StatusOr<GruCellSpec> MakeGruCell(NnLayout* layout, const std::string& name, int input_dim, int hidden) {
  if (input_dim <= 0 || hidden <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("gru_cell ", name, ": sizes must be positive, got input ", input_dim, ", hidden ", hidden));
  }
  GruCellSpec s;
  s.input_dim = input_dim;
  s.hidden = hidden;
  s.w_ih = layout->Add(name + ".weight_ih", 3 * size_t(hidden) * input_dim);
  s.w_hh = layout->Add(name + ".weight_hh", 3 * size_t(hidden) * hidden);
  s.b_ih = layout->Add(name + ".bias_ih", 3 * size_t(hidden));
  s.b_hh = layout->Add(name + ".bias_hh", 3 * size_t(hidden));
  return s;
}

template <typename T>
void InitGruCell(const GruCellSpec& s, std::mt19937_64& rng, T* params) {
  const double b = 1.0 / std::sqrt(static_cast<double>(s.hidden));
  const size_t h3 = 3 * size_t(s.hidden);
  FillUniform(params, s.w_ih, h3 * s.input_dim, -b, b, rng);
  FillUniform(params, s.w_hh, h3 * s.hidden, -b, b, rng);
  FillUniform(params, s.b_ih, h3, -b, b, rng);
  FillUniform(params, s.b_hh, h3, -b, b, rng);
}

template <typename T>
absl::Status GruStepForward(const GruCellSpec& s, const T* params, const ConstRef<T>& gi, const ConstRef<T>& h_prev,
                            Mat<T>* h, GruStepCache<T>* c) {
  const Eigen::Index rows = h_prev.rows();
  const int nh = s.hidden;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("gru", "h_prev", rows, h_prev.cols(), -1, nh));
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("gru", "input gates", gi.rows(), gi.cols(), rows, 3 * nh));
  c->h_prev = h_prev;
  const ConstMatMap<T> w_hh(params + s.w_hh, 3 * nh, nh);
  const Eigen::Map<const RowVec<T>> b_hh(params + s.b_hh, 3 * nh);
  // gh = h W_hh^T + b_hh, kept in dgh's storage until the backward needs it.
  Mat<T>& gh = c->dgh;
  gh.resize(rows, 3 * nh);
  gh.noalias() = h_prev * w_hh.transpose();
  gh.rowwise() += b_hh;
  // Eigen's vectorised logistic / tanh (float: rational approximations within a few ulp; NaN
  // propagates): per-element std::exp / std::tanh made these gates most of a Bi-GRU's time.
  c->r = (gi.leftCols(nh) + gh.leftCols(nh)).array().logistic();
  c->z = (gi.middleCols(nh, nh) + gh.middleCols(nh, nh)).array().logistic();
  c->hn = gh.rightCols(nh);
  c->n = (gi.rightCols(nh).array() + c->r.array() * c->hn.array()).tanh();
  h->resize(rows, nh);
  h->array() = (T(1) - c->z.array()) * c->n.array() + c->z.array() * c->h_prev.array();
  return absl::OkStatus();
}

template <typename T>
absl::Status GruStepBackward(const GruCellSpec& s, const T* params, GruStepCache<T>& c, const ConstRef<T>& dh,
                             MutRef<T> dgi, Mat<T>* dh_prev, T* d_params) {
  const Eigen::Index rows = c.h_prev.rows();
  const int nh = s.hidden;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("gru backward", "dh", dh.rows(), dh.cols(), rows, nh));
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("gru backward", "dgi", dgi.rows(), dgi.cols(), rows, 3 * nh));
  Mat<T>& dgh = c.dgh;
  dgh.resize(rows, 3 * nh);
  const auto r = c.r.array(), z = c.z.array(), n = c.n.array();
  auto dr_pre = dgi.leftCols(nh).array();
  auto dz_pre = dgi.middleCols(nh, nh).array();
  auto dn_pre = dgi.rightCols(nh).array();
  dn_pre = dh.array() * (T(1) - z) * (T(1) - n * n);
  dz_pre = dh.array() * (c.h_prev.array() - n) * z * (T(1) - z);
  dr_pre = dn_pre * c.hn.array() * r * (T(1) - r);
  dgh.leftCols(2 * nh) = dgi.leftCols(2 * nh);
  dgh.rightCols(nh).array() = dn_pre * r;
  MatMap<T>(d_params + s.w_hh, 3 * nh, nh).noalias() += dgh.transpose() * c.h_prev;
  AddColumnSums(dgh, d_params + s.b_hh);
  if (dh_prev != nullptr) {
    const ConstMatMap<T> w_hh(params + s.w_hh, 3 * nh, nh);
    dh_prev->resize(rows, nh);
    dh_prev->noalias() = dgh * w_hh;
    dh_prev->array() += dh.array() * c.z.array();  // the z ⊙ h path
  }
  return absl::OkStatus();
}

template <typename T>
absl::Status GruCellForward(const GruCellSpec& s, const T* params, const ConstRef<T>& x, const ConstRef<T>& h_prev,
                            Mat<T>* h, GruCellCache<T>* c) {
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("gru_cell", "x", x.rows(), x.cols(), h_prev.rows(), s.input_dim));
  c->x = x;
  const ConstMatMap<T> w_ih(params + s.w_ih, 3 * s.hidden, s.input_dim);
  c->gi.resize(x.rows(), 3 * s.hidden);
  c->gi.noalias() = c->x * w_ih.transpose();
  c->gi.rowwise() += Eigen::Map<const RowVec<T>>(params + s.b_ih, 3 * s.hidden);
  return GruStepForward<T>(s, params, c->gi, h_prev, h, &c->step);
}

template <typename T>
absl::Status GruCellBackward(const GruCellSpec& s, const T* params, GruCellCache<T>& c, const ConstRef<T>& dh,
                             Mat<T>* dx, Mat<T>* dh_prev, T* d_params) {
  c.dgi.resize(c.x.rows(), 3 * s.hidden);
  STREETSIM_NN_RETURN_IF_ERROR(GruStepBackward<T>(s, params, c.step, dh, c.dgi, dh_prev, d_params));
  MatMap<T>(d_params + s.w_ih, 3 * s.hidden, s.input_dim).noalias() += c.dgi.transpose() * c.x;
  AddColumnSums(c.dgi, d_params + s.b_ih);
  if (dx != nullptr) {
    dx->resize(c.x.rows(), s.input_dim);
    dx->noalias() = c.dgi * ConstMatMap<T>(params + s.w_ih, 3 * s.hidden, s.input_dim);
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                             \
  template void InitGruCell<T>(const GruCellSpec&, std::mt19937_64&, T*);                                      \
  template absl::Status GruStepForward<T>(const GruCellSpec&, const T*, const ConstRef<T>&, const ConstRef<T>&, \
                                          Mat<T>*, GruStepCache<T>*);                                          \
  template absl::Status GruStepBackward<T>(const GruCellSpec&, const T*, GruStepCache<T>&, const ConstRef<T>&,  \
                                           MutRef<T>, Mat<T>*, T*);                                            \
  template absl::Status GruCellForward<T>(const GruCellSpec&, const T*, const ConstRef<T>&, const ConstRef<T>&, \
                                          Mat<T>*, GruCellCache<T>*);                                          \
  template absl::Status GruCellBackward<T>(const GruCellSpec&, const T*, GruCellCache<T>&, const ConstRef<T>&,  \
                                           Mat<T>*, Mat<T>*, T*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
