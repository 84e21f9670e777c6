#include "render/cpu/scene_soa.h"

namespace streetsim::cpu {

SceneSoa SceneSoa::FromStore(const GaussianStore& s) {
  SceneSoa o;
  o.n = s.size();
  o.sh_degree = s.sh_degree;
  const size_t n = o.n;
  for (auto* v : {&o.mx, &o.my, &o.mz, &o.ls0, &o.ls1, &o.ls2, &o.qw, &o.qx, &o.qy, &o.qz,
                  &o.opacity_logit}) {
    v->resize(n);
  }
  const int K = s.sh_coeffs();
  o.sh.resize(static_cast<size_t>(K) * 3 * n);
  for (size_t i = 0; i < n; ++i) {
    o.mx[i] = s.means[i * 3];
    o.my[i] = s.means[i * 3 + 1];
    o.mz[i] = s.means[i * 3 + 2];
    o.ls0[i] = s.log_scales[i * 3];
    o.ls1[i] = s.log_scales[i * 3 + 1];
    o.ls2[i] = s.log_scales[i * 3 + 2];
    o.qw[i] = s.rotations[i * 4];
    o.qx[i] = s.rotations[i * 4 + 1];
    o.qy[i] = s.rotations[i * 4 + 2];
    o.qz[i] = s.rotations[i * 4 + 3];
    o.opacity_logit[i] = s.opacity_logits[i];
    for (int kc = 0; kc < K * 3; ++kc) o.sh[kc * n + i] = s.sh[i * K * 3 + kc];
  }
  return o;
}

}  // namespace streetsim::cpu
