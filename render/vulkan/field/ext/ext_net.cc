#include "render/vulkan/field/ext/ext_net.h"

#include <algorithm>
#include <vector>

#include "absl/strings/str_cat.h"

namespace streetsim::field::vkext {

namespace vk = vulkan;
using vknn::View;

namespace {

nn::LinearSpec FromDense(const DenseInfo& d, size_t grid_size) {
  nn::LinearSpec s;
  s.in = d.in;
  s.out = d.out;
  s.w_offset = d.w_offset - grid_size;
  s.b_offset = d.b_offset - grid_size;
  return s;
}
nn::LinearSpec GruLinear(const nn::GruCellSpec& g, bool input) {
  nn::LinearSpec s;
  s.in = input ? g.input_dim : g.hidden;
  s.out = 3 * g.hidden;
  s.w_offset = input ? g.w_ih : g.w_hh;
  s.b_offset = input ? g.b_ih : g.b_hh;
  return s;
}
std::string Idx(const char* name, int i) { return absl::StrCat(name, i); }

}  // namespace

uint32_t ExtNet::WidestRow() const {
  const int M = L_.model_dim, D = L_.feature_dim, K = L_.tokens, TD = L_.token_dim, H3 = 3 * c_.gru_hidden;
  return static_cast<uint32_t>(std::max({K * TD, K * D, kEncoderGeometryInputs + D, K * std::max(M, H3),
                                         2 * c_.vae_latent, c_.heads * K, static_cast<int>(kOutTotal), kShOutputs}));
}

uint32_t ExtNet::MaxParamFloats() const {
  std::vector<nn::LinearSpec> specs = {FromDense(BL_.trunk, 0), FromDense(BL_.pos1, 0), FromDense(BL_.pos2, 0),
                                       FromDense(BL_.sh1, 0), FromDense(BL_.sh2, 0)};
  if (c_.encoder) {
    specs.push_back(L_.enc_in);
    specs.insert(specs.end(), L_.enc_linear.begin(), L_.enc_linear.end());
  }
  if (c_.vae) specs.insert(specs.end(), {L_.vae_in, L_.vae_out, L_.vae_mu, L_.vae_var});
  if (c_.attention) specs.insert(specs.end(), {L_.attention.q, L_.attention.k, L_.attention.v, L_.attention.o});
  if (c_.gru) {
    specs.insert(specs.end(), {GruLinear(L_.gru.fwd, true), GruLinear(L_.gru.fwd, false), L_.gru.proj});
  }
  if (c_.temporal && !c_.attention && !c_.gru) specs.push_back(L_.readout);
  if (c_.decoder) specs.insert(specs.end(), {L_.scale1, L_.scale2, L_.rot1, L_.rot2, L_.op1, L_.op2});
  uint64_t m = 2 * static_cast<uint64_t>(L_.model_dim);  // LayerNorm gain + bias, the gate
  for (const nn::LinearSpec& s : specs) m = std::max<uint64_t>(m, uint64_t(s.in + 1) * s.out);
  return static_cast<uint32_t>(m);
}

absl::Status ExtNet::Allocate(uint32_t batch) {
  batch_ = batch;
  const size_t grid = BL_.grid_size;
  trunk_ = FromDense(BL_.trunk, grid), pos1_ = FromDense(BL_.pos1, grid), pos2_ = FromDense(BL_.pos2, grid);
  sh1_ = FromDense(BL_.sh1, grid), sh2_ = FromDense(BL_.sh2, grid);
  if (c_.gru) {
    gru_ih_[0] = GruLinear(L_.gru.fwd, true), gru_hh_[0] = GruLinear(L_.gru.fwd, false);
    gru_ih_[1] = GruLinear(L_.gru.rev, true), gru_hh_[1] = GruLinear(L_.gru.rev, false);
  }
  const size_t B = batch, M = L_.model_dim, D = L_.feature_dim, K = L_.tokens, TD = L_.token_dim;
  const size_t E = kEncoderGeometryInputs + D, Lat = c_.vae ? L_.vae.latent : 0, H = c_.gru_hidden;
  std::vector<std::pair<std::string, size_t>> want = {
      {"means", B * 3}, {"ftok", B * K * D}, {"h0", B * M}, {"arelu", B * M}, {"pos_h", B * M}, {"sh_h", B * M},
      {"out", B * kOutTotal}, {"gout", B * kOutTotal}, {"kl", B}, {"d_means", B * 3}, {"dA", B * M},
      {"dH", B * M}, {"dhid", B * M}, {"dftok", B * K * D}, {"dq", B * M}, {"dtok", B * K * TD}};
  auto add = [&](std::initializer_list<std::pair<std::string, size_t>> l) { want.insert(want.end(), l); };
  if (L_.has_gate) add({{"r", B * M}, {"h", B * M}, {"dr", B * M}});
  if (c_.encoder) {
    add({{"geom", B * kEncoderGeometryInputs}, {"xenc", B * E}, {"e0", B * M}, {"dxenc", B * E}, {"dEa", B * M},
         {"dEb", B * M}, {"dN", B * M}, {"dZ", B * M}});
    for (size_t i = 0; i < L_.enc_linear.size(); ++i) {
      const int ii = static_cast<int>(i);
      add({{Idx("z", ii), B * M}, {Idx("n", ii), B * M}, {Idx("a", ii), B * M}, {Idx("xhat", ii), B * M},
           {Idx("rstd", ii), B}});
    }
  }
  if (c_.vae) {
    add({{"eps", B * Lat}, {"ml", B * 2 * Lat}, {"z", B * Lat}, {"q", B * M}, {"dz", B * Lat},
         {"dml", B * 2 * Lat}, {"dq0", B * M}});
    if (c_.vae_dilation > 0) add({{"sdil", B * D}, {"dsdil", B * D}});
  }
  if (c_.temporal) add({{"times", B * K}, {"tok", B * K * TD}});
  if (c_.attention) {
    add({{"aq", B * M}, {"ak", B * K * M}, {"av", B * K * M}, {"aa", B * c_.heads * K}, {"ao", B * M},
         {"au", B * M}, {"aout", B * M}, {"axhat", B * M}, {"arstd", B}, {"adz", B * M}, {"ado", B * M},
         {"adq", B * M}, {"adk", B * K * M}, {"adv", B * K * M}});
  }
  if (c_.gru) {
    for (int d = 0; d < 2; ++d) {
      add({{Idx("gi", d), B * K * 3 * H}, {Idx("gh", d), K * B * 3 * H}, {Idx("rzn", d), K * B * 3 * H},
           {Idx("hs", d), std::max<size_t>(K - 1, 1) * B * H}, {Idx("dgi", d), B * K * 3 * H}});
    }
    add({{"last", B * 2 * H}, {"gzero", B * H}, {"dlast", B * 2 * H}, {"dha", B * H}, {"dhb", B * H},
         {"dgh", B * 3 * H}});
  }
  if (c_.decoder) add({{"x1", B * M}, {"r1", B * M}, {"o1", B * M}});
  for (const auto& [name, floats] : want) {
    auto b = vk::Buffer::Create(ctx_, std::max<size_t>(floats, 1) * sizeof(float), vk::Buffer::Kind::kDevice,
                                "ext " + name);
    if (!b.ok()) return b.status();
    bufs_[name] = *std::move(b);
  }
  return absl::OkStatus();
}

View ExtNet::V(const std::string& name, uint32_t rows, uint32_t cols, uint32_t offset, uint32_t stride) const {
  return View{&bufs_.at(name), offset, rows, cols, stride > 0 ? stride : cols};
}
View ExtNet::Q0(uint32_t rows) const {
  if (!c_.encoder) return V("h0", rows, L_.model_dim);
  return V(Idx("a", static_cast<int>(L_.enc_linear.size()) - 1), rows, L_.model_dim);
}
View ExtNet::Q(uint32_t rows) const { return c_.vae ? V("q", rows, L_.model_dim) : Q0(rows); }
View ExtNet::Tok(uint32_t rows) const {
  return V(c_.temporal ? "tok" : "ftok", rows, static_cast<uint32_t>(L_.tokens * L_.token_dim));
}
View ExtNet::TokRows(const std::string& name, uint32_t rows) const { return V(name, rows * L_.tokens, L_.token_dim); }
View ExtNet::H(uint32_t rows) const { return V(L_.has_gate ? "h" : "h0", rows, L_.model_dim); }
View ExtNet::Hidden(bool rev, int step, uint32_t rows) const {
  const uint32_t H = c_.gru_hidden;
  if (step < 0) return V("gzero", rows, H);
  if (step == L_.tokens - 1) return V("last", rows, H, rev ? H : 0, 2 * H);
  return V(Idx("hs", rev), rows, H, static_cast<uint32_t>(step) * batch_ * H);
}
const vk::Buffer& ExtNet::dftok() const { return bufs_.at(!c_.temporal && c_.uses_tokens() ? "dtok" : "dftok"); }

void ExtNet::Grad(vk::Recorder& rec, const nn::LinearSpec& s, const vk::Buffer& p, const vk::Buffer& dp, View x,
                  View dy, View dx, bool acc) const {
  nn_.LinearParamGrad(rec, s, x, dy, dp);  // ends with a barrier
  nn_.LinearInputGrad(rec, s, p, dy, dx, acc);
}

void ExtNet::RecordForward(vk::Recorder& rec, uint32_t rows, bool training, const bool wanted[kOutputs]) const {
  const vk::Buffer& mlp = *mlp_;
  const vk::Buffer& ext = *ext_;
  const uint32_t M = L_.model_dim, D = L_.feature_dim, K = L_.tokens, kc = c_.center_token();
  const uint32_t Hh = c_.gru_hidden, H3 = 3 * Hh;
  // The ordering barrier after the sampling is the caller's; r's zero fill is ordered by the
  // barrier after the trunk.
  if (L_.has_gate) rec.Fill(buf("r"), 0, uint64_t{rows} * M * 4, 0);
  if (c_.gru) rec.Fill(buf("gzero"), 0, uint64_t{rows} * Hh * 4, 0);  // both directions start at h = 0
  Lin(rec, trunk_, mlp, V("ftok", rows, D, kc * D, K * D), V("h0", rows, M), false);
  if (c_.temporal) nn_.FourierTokens(rec, L_.fourier, V("times", rows, K), V("ftok", rows, K * D), Tok(rows));
  rec.Barrier();
  if (c_.encoder) {
    Lin(rec, L_.enc_in, ext, V("xenc", rows, kEncoderGeometryInputs + D), V("e0", rows, M), false);
    rec.Barrier();
    for (size_t i = 0; i < L_.enc_linear.size(); ++i) {
      const int ii = static_cast<int>(i);
      Lin(rec, L_.enc_linear[i], ext, i == 0 ? V("e0", rows, M) : V(Idx("a", ii - 1), rows, M),
          V(Idx("z", ii), rows, M), false);
      rec.Barrier();
      nn_.LayerNorm(rec, L_.enc_norm[i], ext, V(Idx("z", ii), rows, M), V(Idx("n", ii), rows, M),
                    V(Idx("xhat", ii), rows, M), V(Idx("rstd", ii), rows, 1));
      rec.Barrier();
      nn_.Activation(rec, c_.activation, V(Idx("n", ii), rows, M), V(Idx("a", ii), rows, M));
      rec.Barrier();
    }
  }
  if (c_.vae) {
    const uint32_t Lat = L_.vae.latent;
    if (c_.vae_dilation > 0) {
      // μ from the latent, log σ² from the dilated samples (extended_config.h).
      Lin(rec, L_.vae_mu, ext, Q0(rows), V("ml", rows, Lat, 0, 2 * Lat), false);
      Lin(rec, L_.vae_var, ext, V("sdil", rows, D), V("ml", rows, Lat, Lat, 2 * Lat), false);
    } else {
      Lin(rec, L_.vae_in, ext, Q0(rows), V("ml", rows, 2 * Lat), false);
    }
    rec.Barrier();
    nn_.VaeSample(rec, Lat, V("ml", rows, 2 * Lat), training ? V("eps", rows, Lat) : View{}, V("z", rows, Lat),
                  V("kl", rows, 1));
    rec.Barrier();
    Lin(rec, L_.vae_out, ext, V("z", rows, Lat), V("q", rows, M), false);
    rec.Barrier();
  }
  if (L_.has_gate) {
    const View r = V("r", rows, M);
    if (c_.attention) {
      const nn::AttentionSpec& a = L_.attention;
      Lin(rec, a.q, ext, Q(rows), V("aq", rows, M), false);
      Lin(rec, a.k, ext, TokRows(c_.temporal ? "tok" : "ftok", rows), V("ak", rows * K, M), false);
      Lin(rec, a.v, ext, TokRows(c_.temporal ? "tok" : "ftok", rows), V("av", rows * K, M), false);
      rec.Barrier();
      nn_.AttentionCore(rec, K, a.heads, a.head_dim(), V("aq", rows, M), V("ak", rows * K, M), V("av", rows * K, M),
                        V("aa", rows, a.heads * K), V("ao", rows, M));
      rec.Barrier();
      Lin(rec, a.o, ext, V("ao", rows, M), V("au", rows, M), false);
      rec.Barrier();
      if (a.residual_norm) {
        nn_.Add(rec, Q(rows), V("au", rows, M));
        rec.Barrier();
        nn_.LayerNorm(rec, a.norm, ext, V("au", rows, M), V("aout", rows, M), V("axhat", rows, M),
                      V("arstd", rows, 1));
        rec.Barrier();
        nn_.Add(rec, V("aout", rows, M), r);
      } else {
        nn_.Add(rec, V("au", rows, M), r);
      }
      rec.Barrier();
    } else if (c_.encoder || c_.vae) {
      nn_.Add(rec, Q(rows), r);
      rec.Barrier();
    }
    if (c_.gru) {
      for (int d = 0; d < 2; ++d) {
        Lin(rec, gru_ih_[d], ext, TokRows(c_.temporal ? "tok" : "ftok", rows), V(Idx("gi", d), rows * K, H3), false);
      }
      rec.Barrier();
      for (int j = 0; j < static_cast<int>(K); ++j) {
        for (int d = 0; d < 2; ++d) {
          Lin(rec, gru_hh_[d], ext, Hidden(d, j - 1, rows), V(Idx("gh", d), rows, H3, j * batch_ * H3), false);
        }
        rec.Barrier();
        for (int d = 0; d < 2; ++d) {
          const uint32_t token = d ? K - 1 - j : j;
          nn_.GruStep(rec, Hh, V(Idx("gi", d), rows, H3, token * H3, K * H3),
                      V(Idx("gh", d), rows, H3, j * batch_ * H3), Hidden(d, j - 1, rows), Hidden(d, j, rows),
                      V(Idx("rzn", d), rows, H3, j * batch_ * H3));
        }
        rec.Barrier();
      }
      Lin(rec, L_.gru.proj, ext, V("last", rows, 2 * Hh), r, true);
      rec.Barrier();
    }
    if (c_.temporal && !c_.attention && !c_.gru) {
      Lin(rec, L_.readout, ext, Tok(rows), r, true);
      rec.Barrier();
    }
    nn_.Gate(rec, ext, static_cast<uint32_t>(L_.gate_offset), V("h0", rows, M), r, V("h", rows, M));
    rec.Barrier();
  }
  nn_.Activation(rec, nn::Activation::kRelu, H(rows), V("arelu", rows, M));
  rec.Barrier();
  auto head = [&](const nn::LinearSpec& l1, const nn::LinearSpec& l2, const vk::Buffer& p, const char* hidden,
                  int o) {
    if (!wanted[o]) return;
    Lin(rec, l1, p, V("arelu", rows, M), V(hidden, rows, M), false);
    rec.Barrier();
    nn_.Activation(rec, nn::Activation::kRelu, V(hidden, rows, M), V(hidden, rows, M));
    rec.Barrier();
    Lin(rec, l2, p, V(hidden, rows, M), V("out", rows, kOutCols[o], batch_ * kOutCol0[o]), false);
  };
  head(pos1_, pos2_, mlp, "pos_h", 0);
  head(sh1_, sh2_, mlp, "sh_h", 1);
  if (c_.decoder) {
    head(L_.scale1, L_.scale2, ext, "x1", 2);
    head(L_.rot1, L_.rot2, ext, "r1", 3);
    head(L_.op1, L_.op2, ext, "o1", 4);
  }
  rec.Barrier();
}

void ExtNet::RecordAttentionBackward(vk::Recorder& rec, uint32_t rows, View dr, const vk::Buffer& ext,
                                     const vk::Buffer& d_ext) const {
  const nn::AttentionSpec& a = L_.attention;
  const uint32_t M = L_.model_dim, K = L_.tokens;
  const std::string tok = c_.temporal ? "tok" : "ftok";
  View dz = dr;
  if (a.residual_norm) {
    nn_.LayerNormGrad(rec, a.norm, ext, V("axhat", rows, M), V("arstd", rows, 1), dr, V("adz", rows, M), d_ext);
    rec.Barrier();
    dz = V("adz", rows, M);
  }
  Grad(rec, a.o, ext, d_ext, V("ao", rows, M), dz, V("ado", rows, M), false);
  rec.Barrier();
  nn_.AttentionCoreGrad(rec, K, a.heads, a.head_dim(), V("aq", rows, M), V("ak", rows * K, M), V("av", rows * K, M),
                        V("aa", rows, a.heads * K), V("ado", rows, M), V("adq", rows, M), V("adk", rows * K, M),
                        V("adv", rows * K, M));
  rec.Barrier();
  Grad(rec, a.q, ext, d_ext, Q(rows), V("adq", rows, M), V("dq", rows, M), true);
  rec.Barrier();
  if (a.residual_norm) {
    nn_.Add(rec, dz, V("dq", rows, M));
    rec.Barrier();
  }
  Grad(rec, a.k, ext, d_ext, TokRows(tok, rows), V("adk", rows * K, M), TokRows("dtok", rows), true);
  rec.Barrier();
  Grad(rec, a.v, ext, d_ext, TokRows(tok, rows), V("adv", rows * K, M), TokRows("dtok", rows), true);
  rec.Barrier();
}

void ExtNet::RecordGruBackward(vk::Recorder& rec, uint32_t rows, View dr, const vk::Buffer& ext,
                               const vk::Buffer& d_ext) const {
  const uint32_t K = L_.tokens, Hh = c_.gru_hidden, H3 = 3 * Hh;
  const std::string tok = c_.temporal ? "tok" : "ftok";
  Grad(rec, L_.gru.proj, ext, d_ext, V("last", rows, 2 * Hh), dr, V("dlast", rows, 2 * Hh), false);
  rec.Barrier();
  // Back through time, one direction after the other (bi_gru.cc's order).
  for (int d = 0; d < 2; ++d) {
    View dh = V("dlast", rows, Hh, d ? Hh : 0, 2 * Hh);
    bool ping = false;
    for (int j = static_cast<int>(K) - 1; j >= 0; --j) {
      const uint32_t token = d ? K - 1 - j : j;
      const View hp = Hidden(d, j - 1, rows);
      const View dhp = V(ping ? "dhb" : "dha", rows, Hh);
      nn_.GruStepGrad(rec, Hh, V(Idx("gh", d), rows, H3, j * batch_ * H3), V(Idx("rzn", d), rows, H3, j * batch_ * H3),
                      hp, dh, V(Idx("dgi", d), rows, H3, token * H3, K * H3), V("dgh", rows, H3), dhp);
      rec.Barrier();
      Grad(rec, gru_hh_[d], ext, d_ext, hp, V("dgh", rows, H3), dhp, true);
      rec.Barrier();
      dh = dhp;
      ping = !ping;
    }
  }
  for (int d = 0; d < 2; ++d) {
    Grad(rec, gru_ih_[d], ext, d_ext, TokRows(tok, rows), V(Idx("dgi", d), rows * K, H3), TokRows("dtok", rows), true);
    rec.Barrier();
  }
}

void ExtNet::RecordBackward(vk::Recorder& rec, uint32_t rows, bool training, float kl_weight,
                            const bool present[kOutputs], const vk::Buffer& mlp, const vk::Buffer& ext,
                            const vk::Buffer& d_mlp, const vk::Buffer& d_ext) const {
  const uint32_t M = L_.model_dim, D = L_.feature_dim, K = L_.tokens, TD = L_.token_dim, kc = c_.center_token();
  rec.Fill(buf("dA"), 0, uint64_t{rows} * M * 4, 0);
  if (c_.uses_tokens()) rec.Fill(buf("dtok"), 0, uint64_t{rows} * K * TD * 4, 0);
  rec.Fill(buf("dq"), 0, uint64_t{rows} * M * 4, 0);
  if (!c_.uses_tokens()) rec.Fill(buf("dftok"), 0, uint64_t{rows} * K * D * 4, 0);
  rec.Barrier();
  auto head = [&](const nn::LinearSpec& l1, const nn::LinearSpec& l2, const vk::Buffer& p, const vk::Buffer& dp,
                  const char* hidden, int o) {
    if (!present[o]) return;
    const View dy = V("gout", rows, kOutCols[o], batch_ * kOutCol0[o]);
    Grad(rec, l2, p, dp, V(hidden, rows, M), dy, V("dhid", rows, M), false);
    rec.Barrier();
    nn_.ActivationGrad(rec, nn::Activation::kRelu, V(hidden, rows, M), V("dhid", rows, M), V("dhid", rows, M));
    rec.Barrier();
    Grad(rec, l1, p, dp, V("arelu", rows, M), V("dhid", rows, M), V("dA", rows, M), true);
    rec.Barrier();
  };
  head(pos1_, pos2_, mlp, d_mlp, "pos_h", 0);
  head(sh1_, sh2_, mlp, d_mlp, "sh_h", 1);
  if (c_.decoder) {
    head(L_.scale1, L_.scale2, ext, d_ext, "x1", 2);
    head(L_.rot1, L_.rot2, ext, d_ext, "r1", 3);
    head(L_.op1, L_.op2, ext, d_ext, "o1", 4);
  }
  // dL/dh = dL/dh0 (the ReLU before the heads).
  const View dH = V("dH", rows, M);
  nn_.ActivationGrad(rec, nn::Activation::kRelu, H(rows), V("dA", rows, M), dH);
  rec.Barrier();
  View dr = dH;
  if (L_.has_gate) {
    nn_.GateGrad(rec, ext, static_cast<uint32_t>(L_.gate_offset), dH, V("r", rows, M), V("dr", rows, M), d_ext);
    rec.Barrier();
    dr = V("dr", rows, M);
  }
  if (c_.temporal && !c_.attention && !c_.gru) {
    Grad(rec, L_.readout, ext, d_ext, Tok(rows), dr, V("dtok", rows, K * TD), true);
    rec.Barrier();
  }
  if (c_.gru) RecordGruBackward(rec, rows, dr, ext, d_ext);
  if (c_.attention) {
    RecordAttentionBackward(rec, rows, dr, ext, d_ext);
  } else if (c_.encoder || c_.vae) {
    nn_.Add(rec, dr, V("dq", rows, M));
    rec.Barrier();
  }
  View dq0 = V("dq", rows, M);
  if (c_.vae) {
    const uint32_t Lat = L_.vae.latent;
    Grad(rec, L_.vae_out, ext, d_ext, V("z", rows, Lat), V("dq", rows, M), V("dz", rows, Lat), false);
    rec.Barrier();
    nn_.VaeSampleGrad(rec, Lat, V("ml", rows, 2 * Lat), training ? V("eps", rows, Lat) : View{}, V("dz", rows, Lat),
                      kl_weight, V("dml", rows, 2 * Lat));
    rec.Barrier();
    if (c_.vae_dilation > 0) {
      Grad(rec, L_.vae_mu, ext, d_ext, Q0(rows), V("dml", rows, Lat, 0, 2 * Lat), V("dq0", rows, M), false);
      rec.Barrier();
      Grad(rec, L_.vae_var, ext, d_ext, V("sdil", rows, D), V("dml", rows, Lat, Lat, 2 * Lat), V("dsdil", rows, D),
           false);
    } else {
      Grad(rec, L_.vae_in, ext, d_ext, Q0(rows), V("dml", rows, 2 * Lat), V("dq0", rows, M), false);
    }
    rec.Barrier();
    dq0 = V("dq0", rows, M);
  }
  if (!c_.encoder) {
    nn_.Add(rec, dq0, dH);  // the latent is the trunk output
    rec.Barrier();
  }
  // dL/d(token features): through the Fourier tokens (written), then the trunk's input (added).
  if (c_.temporal) {
    nn_.FourierTokensGrad(rec, L_.fourier, V("dtok", rows, K * TD), V("dftok", rows, K * D));
    rec.Barrier();
  }
  Grad(rec, trunk_, mlp, d_mlp, V("ftok", rows, D, kc * D, K * D), dH,
       View{&dftok(), kc * D, rows, D, K * D}, true);
  rec.Barrier();
  if (c_.encoder) {
    View dE = dq0;
    bool ping = false;
    for (size_t i = L_.enc_linear.size(); i-- > 0;) {
      const int ii = static_cast<int>(i);
      nn_.ActivationGrad(rec, c_.activation, V(Idx("n", ii), rows, M), dE, V("dN", rows, M));
      rec.Barrier();
      nn_.LayerNormGrad(rec, L_.enc_norm[i], ext, V(Idx("xhat", ii), rows, M), V(Idx("rstd", ii), rows, 1),
                        V("dN", rows, M), V("dZ", rows, M), d_ext);
      rec.Barrier();
      const View next = V(ping ? "dEb" : "dEa", rows, M);
      Grad(rec, L_.enc_linear[i], ext, d_ext, i == 0 ? V("e0", rows, M) : V(Idx("a", ii - 1), rows, M),
           V("dZ", rows, M), next, false);
      rec.Barrier();
      dE = next;
      ping = !ping;
    }
    const uint32_t E = kEncoderGeometryInputs + D;
    Grad(rec, L_.enc_in, ext, d_ext, V("xenc", rows, E), dE, V("dxenc", rows, E), false);
    rec.Barrier();
  }
}

}  // namespace streetsim::field::vkext
