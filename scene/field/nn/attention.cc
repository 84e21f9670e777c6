#include "scene/field/nn/attention.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace streetsim::field::nn {

namespace {
constexpr int kMaxTokens = 256;  // the backward keeps one row's softmax gradient on the stack
}  // namespace

int64_t AttentionSpec::Macs() const {
  // Projections, scores, weighted sum of values, output projection.
  return q.Macs() + int64_t{tokens} * (k.Macs() + v.Macs()) + 2 * int64_t{tokens} * model_dim + o.Macs();
}

absl::StatusOr<AttentionSpec> MakeAttention(NnLayout* layout, const std::string& name, int query_dim, int token_dim,
                                            int tokens, int heads, int model_dim, bool residual_norm) {
  if (query_dim <= 0 || token_dim <= 0 || tokens <= 0 || tokens > kMaxTokens || heads <= 0 || model_dim <= 0 ||
      model_dim % heads != 0) {
    return absl::InvalidArgumentError(absl::StrCat("attention ", name,
                                                   ": sizes must be positive, tokens <= 256 and model_dim a "
                                                   "multiple of heads, got query ", query_dim, ", token ", token_dim,
                                                   ", tokens ", tokens, ", heads ", heads, ", model ", model_dim));
  }
  if (residual_norm && query_dim != model_dim) {
    return absl::InvalidArgumentError(absl::StrCat("attention ", name, ": the residual needs query_dim (", query_dim,
                                                   ") == model_dim (", model_dim, ")"));
  }
  AttentionSpec s;
  s.query_dim = query_dim;
  s.token_dim = token_dim;
  s.tokens = tokens;
  s.heads = heads;
  s.model_dim = model_dim;
  s.residual_norm = residual_norm;
  auto lin = [&](const char* part, int in, int out, LinearSpec* spec, bool bias = true) -> absl::Status {
    absl::StatusOr<LinearSpec> l = MakeLinear(layout, name + "." + part, in, out, bias);
    if (!l.ok()) return l.status();
    *spec = *l;
    return absl::OkStatus();
  };
  STREETSIM_NN_RETURN_IF_ERROR(lin("q", query_dim, model_dim, &s.q));
  // No key bias: it adds Q . b_k to every score of a head, which the softmax cancels exactly (its
  // gradient is zero; a dead parameter).
  STREETSIM_NN_RETURN_IF_ERROR(lin("k", token_dim, model_dim, &s.k, /*bias=*/false));
  STREETSIM_NN_RETURN_IF_ERROR(lin("v", token_dim, model_dim, &s.v));
  STREETSIM_NN_RETURN_IF_ERROR(lin("o", model_dim, model_dim, &s.o));
  if (residual_norm) {
    absl::StatusOr<LayerNormSpec> n = MakeLayerNorm(layout, name + ".norm", model_dim);
    if (!n.ok()) return n.status();
    s.norm = *n;
  }
  return s;
}

template <typename T>
void InitAttention(const AttentionSpec& s, std::mt19937_64& rng, T* params) {
  for (const LinearSpec* l : {&s.q, &s.k, &s.v, &s.o}) InitLinear(*l, rng, params);
  if (s.residual_norm) InitLayerNorm(s.norm, params);
}

template <typename T>
absl::Status AttentionForward(const AttentionSpec& s, const T* params, const ConstRef<T>& query,
                              const ConstRef<T>& tokens, Mat<T>* y, AttentionCache<T>* c) {
  const Eigen::Index rows = query.rows();
  const int nt = s.tokens, nh = s.heads, dh = s.head_dim(), m = s.model_dim;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("attention", "query", rows, query.cols(), -1, s.query_dim));
  STREETSIM_NN_RETURN_IF_ERROR(
      CheckShape("attention", "tokens", tokens.rows(), tokens.cols(), rows, int64_t{nt} * s.token_dim));
  c->query = query;
  c->x.resize(rows * nt, s.token_dim);
  for (Eigen::Index r = 0; r < rows; ++r)
    MatMap<T>(c->x.row(r * nt).data(), nt, s.token_dim) = ConstMatMap<T>(tokens.row(r).data(), nt, s.token_dim);
  STREETSIM_NN_RETURN_IF_ERROR(LinearApply<T>(s.q, params, c->query, &c->Q));
  STREETSIM_NN_RETURN_IF_ERROR(LinearApply<T>(s.k, params, c->x, &c->K));
  STREETSIM_NN_RETURN_IF_ERROR(LinearApply<T>(s.v, params, c->x, &c->V));
  c->A.resize(rows, nh * nt);
  c->O.setZero(rows, m);
  const T scale = T(1) / std::sqrt(static_cast<T>(dh));
  for (Eigen::Index r = 0; r < rows; ++r) {
    for (int h = 0; h < nh; ++h) {
      const T* qh = c->Q.row(r).data() + h * dh;
      T* a = c->A.row(r).data() + h * nt;
      T mx = -std::numeric_limits<T>::infinity();
      for (int j = 0; j < nt; ++j) {
        const T* kj = c->K.row(r * nt + j).data() + h * dh;
        T dot = 0;
        for (int d = 0; d < dh; ++d) dot += qh[d] * kj[d];
        a[j] = dot * scale;
        mx = std::max(mx, a[j]);
      }
      T sum = 0;
      for (int j = 0; j < nt; ++j) {
        a[j] = std::exp(a[j] - mx);
        sum += a[j];
      }
      const T inv = T(1) / sum;
      T* oh = c->O.row(r).data() + h * dh;
      for (int j = 0; j < nt; ++j) {
        a[j] *= inv;
        const T* vj = c->V.row(r * nt + j).data() + h * dh;
        for (int d = 0; d < dh; ++d) oh[d] += a[j] * vj[d];
      }
    }
  }
  STREETSIM_NN_RETURN_IF_ERROR(LinearApply<T>(s.o, params, c->O, &c->u));
  if (!s.residual_norm) {
    *y = c->u;
    return absl::OkStatus();
  }
  c->u += c->query;
  return LayerNormForward<T>(s.norm, params, c->u, y, &c->norm);
}

template <typename T>
absl::Status AttentionBackward(const AttentionSpec& s, const T* params, AttentionCache<T>& c, const ConstRef<T>& dy,
                               Mat<T>* d_query, Mat<T>* d_tokens, T* d_params) {
  const Eigen::Index rows = c.query.rows();
  const int nt = s.tokens, nh = s.heads, dh = s.head_dim(), m = s.model_dim;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("attention backward", "dy", dy.rows(), dy.cols(), rows, m));
  if (s.residual_norm) {
    STREETSIM_NN_RETURN_IF_ERROR(LayerNormBackward<T>(s.norm, params, c.norm, dy, &c.dz, d_params));
  } else {
    c.dz = dy;
  }
  // dz is dL/du and, through the residual, part of dL/dquery.
  STREETSIM_NN_RETURN_IF_ERROR(LinearGrad<T>(s.o, params, c.O, c.dz, &c.dO, false, d_params));
  c.dQ.setZero(rows, m);
  c.dK.setZero(rows * nt, m);
  c.dV.setZero(rows * nt, m);
  const T scale = T(1) / std::sqrt(static_cast<T>(dh));
  T da[kMaxTokens];
  for (Eigen::Index r = 0; r < rows; ++r) {
    for (int h = 0; h < nh; ++h) {
      const T* qh = c.Q.row(r).data() + h * dh;
      const T* a = c.A.row(r).data() + h * nt;
      const T* doh = c.dO.row(r).data() + h * dh;
      T* dqh = c.dQ.row(r).data() + h * dh;
      T mean = 0;  // sum_j a_j da_j
      for (int j = 0; j < nt; ++j) {
        const T* vj = c.V.row(r * nt + j).data() + h * dh;
        T* dvj = c.dV.row(r * nt + j).data() + h * dh;
        T dot = 0;
        for (int d = 0; d < dh; ++d) {
          dot += doh[d] * vj[d];
          dvj[d] += a[j] * doh[d];
        }
        da[j] = dot;
        mean += a[j] * dot;
      }
      for (int j = 0; j < nt; ++j) {
        const T ds = a[j] * (da[j] - mean) * scale;  // through the softmax and the 1/sqrt(dh)
        const T* kj = c.K.row(r * nt + j).data() + h * dh;
        T* dkj = c.dK.row(r * nt + j).data() + h * dh;
        for (int d = 0; d < dh; ++d) {
          dqh[d] += ds * kj[d];
          dkj[d] += ds * qh[d];
        }
      }
    }
  }
  // Query path (and the residual), then the token paths.
  STREETSIM_NN_RETURN_IF_ERROR(LinearGrad<T>(s.q, params, c.query, c.dQ, d_query, false, d_params));
  if (d_query != nullptr && s.residual_norm) *d_query += c.dz;
  Mat<T>* dx = d_tokens != nullptr ? &c.dx : nullptr;
  STREETSIM_NN_RETURN_IF_ERROR(LinearGrad<T>(s.k, params, c.x, c.dK, dx, false, d_params));
  STREETSIM_NN_RETURN_IF_ERROR(LinearGrad<T>(s.v, params, c.x, c.dV, dx, true, d_params));
  if (d_tokens != nullptr) {
    d_tokens->resize(rows, int64_t{nt} * s.token_dim);
    for (Eigen::Index r = 0; r < rows; ++r)
      MatMap<T>(d_tokens->row(r).data(), nt, s.token_dim) = ConstMatMap<T>(c.dx.row(r * nt).data(), nt, s.token_dim);
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                            \
  template void InitAttention<T>(const AttentionSpec&, std::mt19937_64&, T*);                                 \
  template absl::Status AttentionForward<T>(const AttentionSpec&, const T*, const ConstRef<T>&,               \
                                            const ConstRef<T>&, Mat<T>*, AttentionCache<T>*);                 \
  template absl::Status AttentionBackward<T>(const AttentionSpec&, const T*, AttentionCache<T>&,              \
                                             const ConstRef<T>&, Mat<T>*, Mat<T>*, T*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
