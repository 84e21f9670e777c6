#include "scene/field/extended/extended_config.h"

#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace streetsim::field {

absl::Status ExtendedFieldConfig::Validate(const FieldConfig& base) const {
  auto bad = [](const std::string& why) { return absl::InvalidArgumentError(absl::StrCat("extended field: ", why)); };
  if (heads < 1 || base.width % heads != 0) {
    return bad(absl::StrCat("the model dim (the field width, ", base.width, ") must be a multiple of heads (", heads,
                            ")"));
  }
  if (vae_latent < 1 || vae_latent > 1024) return bad(absl::StrCat("VAE latent ", vae_latent, " not in 1..1024"));
  if (gru_hidden < 1 || gru_hidden > 1024) return bad(absl::StrCat("GRU hidden ", gru_hidden, " not in 1..1024"));
  if (window_k < 0 || window_k > 16) return bad(absl::StrCat("window k ", window_k, " not in 0..16"));
  if (fourier_frequencies < 0 || fourier_frequencies > 16) {
    return bad(absl::StrCat("Fourier frequencies ", fourier_frequencies, " not in 0..16"));
  }
  if (encoder_layers < 0 || encoder_layers > 8) {
    return bad(absl::StrCat("encoder layers ", encoder_layers, " not in 0..8"));
  }
  if (vae_dilation < 0 || vae_dilation > 16) return bad(absl::StrCat("VAE dilation ", vae_dilation, " not in 0..16"));
  if (!(decoder_max_dlog_scale >= 0 && decoder_max_dlog_scale <= 50)) {
    return bad(absl::StrCat("decoder Δlog-scale bound ", decoder_max_dlog_scale, " not in [0, 50]"));
  }
  if (!(window_dt >= 0 && window_dt <= 2)) return bad(absl::StrCat("window dt ", window_dt, " not in [0, 2]"));
  if (!(kl_weight >= 0 && kl_weight < 1e6) || kl_warmup_iterations < 0) return bad("KL weight / warm-up out of range");
  return absl::OkStatus();
}

absl::StatusOr<ExtendedFieldConfig> ExtendedFieldConfig::WithModules(const std::string& list) {
  ExtendedFieldConfig c;
  if (list == "none") return c;
  for (absl::string_view part : absl::StrSplit(list, ',')) {
    if (part == "encoder") {
      c.encoder = true;
    } else if (part == "vae") {
      c.vae = true;
    } else if (part == "vae_dilated") {
      c.vae = true;
      c.vae_dilation = 1;
    } else if (part == "temporal") {
      c.temporal = true;
    } else if (part == "attention") {
      c.attention = true;
    } else if (part == "gru") {
      c.gru = true;
    } else if (part == "decoder") {
      c.decoder = true;
    } else if (part == "all") {
      c.encoder = c.vae = c.temporal = c.attention = c.gru = c.decoder = true;
    } else {
      return absl::InvalidArgumentError(absl::StrCat(
          "--field-modules: unknown module '", std::string(part),
          "' (want a comma-separated subset of encoder,vae,vae_dilated,temporal,attention,gru,decoder, or all, or "
          "none)"));
    }
  }
  return c;
}

std::string ExtendedFieldConfig::ModulesString() const {
  std::vector<std::string> parts;
  if (encoder) parts.push_back("encoder");
  if (vae) parts.push_back(vae_dilation > 0 ? "vae_dilated" : "vae");
  if (temporal) parts.push_back("temporal");
  if (attention) parts.push_back("attention");
  if (gru) parts.push_back("gru");
  if (decoder) parts.push_back("decoder");
  return parts.empty() ? "none" : absl::StrJoin(parts, ",");
}

ExtendedFieldConfig ExtendedFieldConfig::AllOn() {
  ExtendedFieldConfig c;
  c.encoder = c.vae = c.temporal = c.attention = c.gru = c.decoder = true;
  c.heads = 2;
  c.vae_latent = 3;
  c.gru_hidden = 3;
  c.window_k = 1;
  c.fourier_frequencies = 2;
  c.encoder_layers = 1;
  c.window_dt = 0.3;
  return c;
}

namespace {
template <typename Spec>
absl::Status Assign(absl::StatusOr<Spec> r, Spec* out) {
  if (!r.ok()) return r.status();
  *out = *r;
  return absl::OkStatus();
}
}  // namespace

absl::StatusOr<ExtendedLayout> ExtendedLayout::Make(const FieldConfig& base, const ExtendedFieldConfig& c) {
  if (absl::Status s = base.Validate(); !s.ok()) return s;
  if (absl::Status s = c.Validate(base); !s.ok()) return s;
  ExtendedLayout L;
  L.feature_dim = base.feature_dim();
  L.model_dim = base.width;
  L.tokens = c.tokens();
  L.token_dim = (c.temporal ? 2 * c.fourier_frequencies : 0) + L.feature_dim;
  const int M = L.model_dim;
  nn::NnLayout* p = &L.params;
  if (c.encoder) {
    STREETSIM_NN_RETURN_IF_ERROR(
        Assign(nn::MakeLinear(p, "enc.in", kEncoderGeometryInputs + L.feature_dim, M), &L.enc_in));
    for (int i = 0; i < c.encoder_layers; ++i) {
      L.enc_linear.emplace_back();
      L.enc_norm.emplace_back();
      STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, absl::StrCat("enc.", i, ".linear"), M, M), &L.enc_linear.back()));
      STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLayerNorm(p, absl::StrCat("enc.", i, ".norm"), M), &L.enc_norm.back()));
    }
  }
  if (c.vae) {
    if (c.vae_dilation > 0) {
      STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "vae.mu", M, c.vae_latent), &L.vae_mu));
      STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "vae.var", L.feature_dim, c.vae_latent), &L.vae_var));
    } else {
      STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "vae.in", M, 2 * c.vae_latent), &L.vae_in));
    }
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeVae(c.vae_latent), &L.vae));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "vae.out", c.vae_latent, M), &L.vae_out));
  }
  if (c.temporal) {
    STREETSIM_NN_RETURN_IF_ERROR(
        Assign(nn::MakeFourierTime(c.fourier_frequencies, L.tokens, L.feature_dim), &L.fourier));
  }
  if (c.attention) {
    STREETSIM_NN_RETURN_IF_ERROR(
        Assign(nn::MakeAttention(p, "attn", M, L.token_dim, L.tokens, c.heads, M, /*residual_norm=*/true), &L.attention));
  }
  if (c.gru) {
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeBiGru(p, "gru", L.tokens, L.token_dim, c.gru_hidden, M), &L.gru));
  }
  if (c.temporal && !c.attention && !c.gru) {
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "readout", L.tokens * L.token_dim, M), &L.readout));
  }
  if (c.encoder || c.vae || c.uses_tokens()) {
    L.has_gate = true;
    L.gate_offset = p->Add("gate", M);
  }
  if (c.decoder) {
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.scale.1", M, M), &L.scale1));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.scale.2", M, kDecoderScaleOutputs), &L.scale2));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.rotation.1", M, M), &L.rot1));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.rotation.2", M, kDecoderRotationOutputs), &L.rot2));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.opacity.1", M, M), &L.op1));
    STREETSIM_NN_RETURN_IF_ERROR(Assign(nn::MakeLinear(p, "dec.opacity.2", M, kDecoderOpacityOutputs), &L.op2));
  }
  return L;
}

int64_t ExtendedLayout::Macs(const ExtendedFieldConfig& c) const {
  int64_t m = 0;
  if (c.encoder) {
    m += enc_in.Macs();
    for (const nn::LinearSpec& l : enc_linear) m += l.Macs();
  }
  if (c.vae) m += vae_in.Macs() + vae_mu.Macs() + vae_var.Macs() + vae_out.Macs();
  if (c.attention) m += attention.Macs();
  if (c.gru) m += gru.Macs();
  if (c.temporal && !c.attention && !c.gru) m += readout.Macs();
  if (has_gate) m += model_dim;
  if (c.decoder) m += scale1.Macs() + scale2.Macs() + rot1.Macs() + rot2.Macs() + op1.Macs() + op2.Macs();
  return m;
}

int64_t BaseMlpMacs(const FieldLayout& L) {
  int64_t m = 0;
  for (const DenseInfo* d : {&L.trunk, &L.pos1, &L.pos2, &L.sh1, &L.sh2}) m += int64_t{d->in} * d->out;
  return m;
}

template <typename T>
void InitExtendedParams(const ExtendedFieldConfig& c, const ExtendedLayout& L, uint64_t seed, std::vector<T>* params) {
  params->assign(L.total(), T(0));
  std::mt19937_64 rng(seed ^ 0x5eedE7E7Dull);
  T* p = params->data();
  if (c.encoder) {
    nn::InitLinear(L.enc_in, rng, p);
    for (size_t i = 0; i < L.enc_linear.size(); ++i) {
      nn::InitLinear(L.enc_linear[i], rng, p);
      nn::InitLayerNorm(L.enc_norm[i], p);
    }
  }
  if (c.vae) {
    if (c.vae_dilation > 0) {
      nn::InitLinear(L.vae_mu, rng, p);
      nn::InitLinear(L.vae_var, rng, p);
    } else {
      nn::InitLinear(L.vae_in, rng, p);
    }
    nn::InitLinear(L.vae_out, rng, p);
  }
  if (c.attention) nn::InitAttention(L.attention, rng, p);
  if (c.gru) nn::InitBiGru(L.gru, rng, p);
  if (c.temporal && !c.attention && !c.gru) nn::InitLinear(L.readout, rng, p);
  if (c.decoder) {
    for (const nn::LinearSpec* s : {&L.scale1, &L.rot1, &L.op1}) nn::InitLinear(*s, rng, p);
    // Last layers stay zero (see the header).
  }
}

template void InitExtendedParams<float>(const ExtendedFieldConfig&, const ExtendedLayout&, uint64_t,
                                        std::vector<float>*);
template void InitExtendedParams<double>(const ExtendedFieldConfig&, const ExtendedLayout&, uint64_t,
                                         std::vector<double>*);

}  // namespace streetsim::field
