#include "scene/field/extended/extended_deform.h"

#include <algorithm>
#include <cmath>
#include <mutex>
#include <unordered_map>

#include "absl/strings/str_cat.h"
#include "scene/field/huge_pages.h"
#include "scene/optim/adam_kernel.h"

namespace streetsim::field {

double ExtNetworkLr(const ExtHyper& h, int64_t fine_iteration) {
  return FieldExpLr(h.network_lr_init * h.lr_scale, h.network_lr_final * h.lr_scale, fine_iteration, h.lr_decay_steps);
}

double ExtKlBeta(const ExtendedFieldConfig& c, int64_t fine_iteration) {
  if (c.kl_warmup_iterations <= 0) return c.kl_weight;
  return c.kl_weight * std::min(1.0, static_cast<double>(fine_iteration) / c.kl_warmup_iterations);
}

void ExtAdamStep(float* params, const float* grads, size_t n, ExtAdamState* s, double lr) {
  if (s->m.size() != n) s->m.assign(n, 0.0f), s->v.assign(n, 0.0f), s->step = 0;
  s->step += 1;
  const double bc1 = 1 - std::pow(double(optim::kAdamBeta1), double(s->step));
  const double bc2 = 1 - std::pow(double(optim::kAdamBeta2), double(s->step));
  optim::AdamRange(params, grads, s->m.data(), s->v.data(), n, static_cast<float>(lr / bc1),
                   static_cast<float>(1 / std::sqrt(bc2)));
}

absl::Status DeformSceneExt(const ExtendedField& field, const ExtPass& pass, const ExtCanonicalView& c,
                            ThreadPool& pool, ExtWorkspace& ws, ExtDeformedScene* out, const ExtEvaluator& eval) {
  if (c.n > 0 && (!c.means || !c.sh || !c.log_scales || !c.rotations || !c.opacity_logits)) {
    return absl::InvalidArgumentError("DeformSceneExt: null canonical arrays");
  }
  const size_t n = c.n;
  const bool dec = field.config().decoder;
  out->pass = pass;
  out->dx.resize(n * 3);
  out->dsh.resize(n * kShOutputs);
  out->means.resize(n * 3);
  out->sh.resize(n * kShOutputs);
  for (std::vector<float>* v : {&out->dscale, &out->log_scales}) v->resize(dec ? n * 3 : 0);
  for (std::vector<float>* v : {&out->drot, &out->rotations}) v->resize(dec ? n * 4 : 0);
  for (std::vector<float>* v : {&out->dopacity, &out->opacity_logits}) v->resize(dec ? n : 0);
  ExtInputs<float> in{n, c.means, c.opacity_logits, c.log_scales, c.rotations};
  ExtOutputs<float> o{out->dx.data(), out->dsh.data(), dec ? out->dscale.data() : nullptr,
                      dec ? out->drot.data() : nullptr, dec ? out->dopacity.data() : nullptr};
  absl::StatusOr<double> kl =
      eval.forward ? eval.forward(pass, in, o) : ExtendedForward<float>(ModelOf(field), pass, in, o, pool, ws);
  if (!kl.ok()) return kl.status();
  out->kl_sum = *kl;
  const float bound = field.config().decoder_max_dlog_scale;
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b * 3; i < e * 3; ++i) out->means[i] = c.means[i] + out->dx[i];
    for (int64_t i = b * kShOutputs; i < e * kShOutputs; ++i) out->sh[i] = c.sh[i] + out->dsh[i];
    if (!dec) return;
    BoundDecoderLogScales(bound, out->dscale.data() + b * 3, static_cast<size_t>(e - b) * 3);
    for (int64_t i = b * 3; i < e * 3; ++i) out->log_scales[i] = c.log_scales[i] + out->dscale[i];
    for (int64_t i = b * 4; i < e * 4; ++i) out->rotations[i] = c.rotations[i] + out->drot[i];
    for (int64_t i = b; i < e; ++i) out->opacity_logits[i] = c.opacity_logits[i] + out->dopacity[i];
  });
  return absl::OkStatus();
}

GaussianParamsView ExtDeformedParamsView(const GaussianParamsView& canonical, const ExtDeformedScene& d) {
  GaussianParamsView v = canonical;
  v.means = d.means.data();
  v.sh = d.sh.data();
  v.sh_stride = kShCoeffs;
  if (!d.log_scales.empty()) {
    v.log_scales = d.log_scales.data();
    v.rotations = d.rotations.data();
    v.opacity_logits = d.opacity_logits.data();
  }
  return v;
}

absl::StatusOr<ExtDeformLosses> DeformBackwardExt(const ExtendedField& field, const ExtCanonicalView& c,
                                                  const ExtDeformedScene& d, int active_degree, const FieldHyper& h,
                                                  double kl_beta, ThreadPool& pool, ExtWorkspace& ws,
                                                  GaussianGrads* grads, std::vector<float>* d_base,
                                                  std::vector<float>* d_ext, const ExtEvaluator& eval) {
  const size_t n = c.n;
  if (active_degree < 0 || active_degree > 3) {
    return absl::InvalidArgumentError(absl::StrCat("DeformBackwardExt: SH degree ", active_degree));
  }
  const int ka3 = ShCoeffsForDegree(active_degree) * 3;
  const bool dec = field.config().decoder, enc = field.config().encoder;
  if (grads->means.size() != n * 3 || grads->sh.size() != n * ka3 || d.dx.size() != n * 3 ||
      d.dsh.size() != n * kShOutputs || ((dec || enc) && (grads->log_scales.size() != n * 3 ||
                                                          grads->rotations.size() != n * 4 ||
                                                          grads->opacity_logits.size() != n))) {
    return absl::InvalidArgumentError(absl::StrCat("DeformBackwardExt: sizes disagree (", n, " Gaussians, grads ",
                                                   grads->means.size() / 3, ", deformed ", d.dx.size() / 3, ")"));
  }
  const size_t base_total = field.base().layout().total;
  if (d_base->size() != base_total) AssignOnHugePages(d_base, base_total, 0.0f);
  if (d_ext->size() != field.layout().total()) d_ext->assign(field.layout().total(), 0.0f);
  ExtDeformLosses losses;
  if (n == 0) return losses;
  std::vector<float> g_dx(n * 3), g_dsh(n * kShOutputs), g_dscale, g_drot, g_dop;
  const DeformLosses sparsity = SparsityGradients(d.dx, d.dsh, ka3, h, *grads, pool, g_dx.data(), g_dsh.data());
  if (dec) {  // Δ added to the parameter: its gradient is the rendered parameter's (copied first:
              // the encoder path adds into grads below)
    g_dscale = grads->log_scales;
    BoundDecoderLogScalesBackward(field.config().decoder_max_dlog_scale, d.dscale.data(), g_dscale.data(),
                                  g_dscale.size());
    g_drot = grads->rotations;
    g_dop = grads->opacity_logits;
  }
  losses.dx_l1 = sparsity.dx_l1;
  losses.dsh_l1 = sparsity.dsh_l1;
  ExtInputs<float> in{n, c.means, c.opacity_logits, c.log_scales, c.rotations};
  ExtOutputGrads<float> go{g_dx.data(), g_dsh.data(), dec ? g_dscale.data() : nullptr, dec ? g_drot.data() : nullptr,
                           dec ? g_dop.data() : nullptr};
  ExtInputGrads<float> gi{d_base->data(), d_ext->data(), grads->means.data(),
                          enc ? grads->opacity_logits.data() : nullptr, enc ? grads->log_scales.data() : nullptr,
                          enc ? grads->rotations.data() : nullptr};
  absl::StatusOr<double> kl =
      eval.backward ? eval.backward(d.pass, in, go, kl_beta / n, gi)
                    : ExtendedBackward<float>(ModelOf(field), d.pass, in, go, kl_beta / n, gi, pool, ws);
  if (!kl.ok()) return kl.status();
  losses.kl_mean = *kl / n;
  losses.weighted = h.lambda_dx * losses.dx_l1 + h.lambda_dsh * losses.dsh_l1 + kl_beta * losses.kl_mean;
  return losses;
}

absl::StatusOr<GaussianStore> ExtDeformedStore(const ExtendedField& f, const GaussianStore& canonical,
                                               int64_t time_us, ThreadPool& pool) {
  if (canonical.sh_degree != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
  }
  ExtWorkspace ws;
  ExtDeformedScene d;
  ExtPass pass;
  pass.time_coord = f.base().TimeCoordinate(time_us);
  const ExtCanonicalView c{canonical.size(), canonical.means.data(), canonical.sh.data(), canonical.log_scales.data(),
                           canonical.rotations.data(), canonical.opacity_logits.data()};
  if (absl::Status s = DeformSceneExt(f, pass, c, pool, ws, &d); !s.ok()) return s;
  GaussianStore out = canonical;
  out.means = std::move(d.means);
  out.sh = std::move(d.sh);
  if (f.config().decoder) {
    out.log_scales = std::move(d.log_scales);
    out.rotations = std::move(d.rotations);
    out.opacity_logits = std::move(d.opacity_logits);
  }
  return out;
}

namespace {
std::mutex& RegistryMutex() {
  static std::mutex mu;
  return mu;
}
std::unordered_map<const DeformationField*, std::weak_ptr<const ExtendedField>>& Registry() {
  static auto* table = new std::unordered_map<const DeformationField*, std::weak_ptr<const ExtendedField>>();
  return *table;
}
}  // namespace

std::shared_ptr<const DeformationField> ShareWithExtension(ExtendedField field) {
  auto* raw = new ExtendedField(std::move(field));
  const DeformationField* key = &raw->base();
  std::shared_ptr<const ExtendedField> owner(raw, [key](const ExtendedField* p) {
    {
      std::lock_guard<std::mutex> lock(RegistryMutex());
      auto it = Registry().find(key);
      if (it != Registry().end() && it->second.expired()) Registry().erase(it);
    }
    delete p;
  });
  {
    std::lock_guard<std::mutex> lock(RegistryMutex());
    Registry()[key] = owner;
  }
  return std::shared_ptr<const DeformationField>(owner, key);
}

std::shared_ptr<const ExtendedField> ExtensionOf(const DeformationField& base) {
  std::lock_guard<std::mutex> lock(RegistryMutex());
  auto it = Registry().find(&base);
  return it == Registry().end() ? nullptr : it->second.lock();
}

}  // namespace streetsim::field
