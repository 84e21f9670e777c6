#include "scene/field/extended/extended_io.h"

#include <cmath>
#include <cstring>
#include <fstream>
#include <iterator>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"

namespace streetsim::field {

namespace {

constexpr char kMagic[8] = {'S', 'S', 'F', 'L', 'D', 'E', 'X', 'T'};
// Version 2 adds i32 vae_dilation after the activation; version 3 also f32
// decoder_max_dlog_scale after it. Each file is written at the lowest version that holds it (a
// field without the dilated branch or the bound is byte for byte what it was), so older readers
// keep reading what they can; a version 1 or 2 file loads with the bound 0 it was trained with.
constexpr uint32_t kVersion1 = 1, kVersion2 = 2, kVersion3 = 3;
constexpr uint32_t kFlagAdam = 1;

using checked_file::Reader;
using checked_file::Writer;
using checked_file::Checksum;

absl::Status Save(const ExtendedField& f, const ExtAdamState* adam, const std::string& path) {
  const ExtendedFieldConfig& c = f.config();
  const size_t total = f.layout().total();
  if (adam && (adam->m.size() != total || adam->v.size() != total)) {
    return absl::InvalidArgumentError(absl::StrCat("extended field checkpoint: Adam moments have ", adam->m.size(),
                                                   " values, the extension ", total));
  }
  Writer w;
  w.Raw(kMagic, 8);
  const bool bounded = c.decoder && c.decoder_max_dlog_scale != 0;  // the bound means nothing without the decoder
  const uint32_t version = bounded ? kVersion3 : c.vae_dilation != 0 ? kVersion2 : kVersion1;
  w.Pod<uint32_t>(version);
  w.Pod<uint32_t>(adam ? kFlagAdam : 0);
  for (bool b : {c.encoder, c.vae, c.temporal, c.attention, c.gru, c.decoder}) w.Pod<uint8_t>(b ? 1 : 0);
  for (int v : {c.heads, c.vae_latent, c.gru_hidden, c.window_k, c.fourier_frequencies, c.encoder_layers,
                static_cast<int>(c.activation)}) {
    w.Pod<int32_t>(v);
  }
  if (version >= kVersion2) w.Pod<int32_t>(c.vae_dilation);
  if (version >= kVersion3) w.Pod<float>(c.decoder_max_dlog_scale);
  w.Pod<double>(c.window_dt);
  w.Pod<double>(c.kl_weight);
  w.Pod<int32_t>(c.kl_warmup_iterations);
  w.Pod<int32_t>(f.layout().feature_dim);
  w.Pod<int32_t>(f.layout().model_dim);
  w.Pod<uint64_t>(BaseParamsChecksum(f.base().params()));
  w.Pod<uint64_t>(total);
  w.Raw(f.params().data(), total * sizeof(float));
  if (adam) {
    w.Pod<int64_t>(adam->step);
    w.Raw(adam->m.data(), total * sizeof(float));
    w.Raw(adam->v.data(), total * sizeof(float));
  }
  w.Pod<uint64_t>(Checksum(w.buf.data(), w.buf.size()));
  return checked_file::WriteAtomically(path, w.buf);
}

absl::StatusOr<ExtendedField> Load(const std::string& path, DeformationField base, ExtAdamState* adam) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open extended field file ", path));
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  auto corrupt = [&](const std::string& why) { return absl::DataLossError(absl::StrCat(path, ": ", why)); };
  if (bytes.size() < 16 || std::memcmp(bytes.data(), kMagic, 8) != 0) return corrupt("not a streetsim extended field file");
  const size_t body = bytes.size() - 8;
  uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + body, 8);
  Reader r(bytes.data(), body);
  char magic[8];
  r.Raw(magic, 8);
  uint32_t version = 0, flags = 0;
  if (!r.Pod(&version) || !r.Pod(&flags)) return corrupt("truncated header");
  if (version != kVersion1 && version != kVersion2 && version != kVersion3) {
    return corrupt(absl::StrCat("unsupported extended field version ", version, " (want 1, 2 or 3)"));
  }
  if (stored != Checksum(bytes.data(), body)) return corrupt("checksum mismatch (truncated or corrupt file)");
  if (flags & ~kFlagAdam) return corrupt(absl::StrCat("unknown flags ", flags));
  ExtendedFieldConfig c;
  uint8_t sw[6];
  int32_t iv[7], warm = 0, feature_dim = 0, model_dim = 0;
  bool ok = r.Raw(sw, 6);
  for (int i = 0; i < 7 && ok; ++i) ok = r.Pod(&iv[i]);
  int32_t dilation = 0;
  float dlog_scale_bound = 0;  // versions 1 and 2: trained unbounded
  if (version >= kVersion2) ok = ok && r.Pod(&dilation);
  if (version >= kVersion3) ok = ok && r.Pod(&dlog_scale_bound);
  ok = ok && r.Pod(&c.window_dt) && r.Pod(&c.kl_weight) && r.Pod(&warm) && r.Pod(&feature_dim) && r.Pod(&model_dim);
  uint64_t base_sum = 0, count = 0;
  ok = ok && r.Pod(&base_sum) && r.Pod(&count);
  if (!ok) return corrupt("truncated configuration");
  c.encoder = sw[0], c.vae = sw[1], c.temporal = sw[2], c.attention = sw[3], c.gru = sw[4], c.decoder = sw[5];
  c.heads = iv[0], c.vae_latent = iv[1], c.gru_hidden = iv[2], c.window_k = iv[3], c.fourier_frequencies = iv[4];
  c.encoder_layers = iv[5];
  c.vae_dilation = dilation;
  c.decoder_max_dlog_scale = dlog_scale_bound;
  if (iv[6] < 0 || iv[6] > static_cast<int>(nn::Activation::kSilu)) return corrupt("unknown activation");
  c.activation = static_cast<nn::Activation>(iv[6]);
  c.kl_warmup_iterations = warm;
  if (feature_dim != base.config().feature_dim() || model_dim != base.config().width) {
    return corrupt(absl::StrCat("written for a base field of feature dim ", feature_dim, " and width ", model_dim,
                                ", field.bin has ", base.config().feature_dim(), " and ", base.config().width));
  }
  if (base_sum != BaseParamsChecksum(base.params())) {
    return corrupt("does not belong to this field.bin (written with other base parameters: an interrupted or "
                   "different run)");
  }
  absl::StatusOr<ExtendedLayout> L = ExtendedLayout::Make(base.config(), c);
  if (!L.ok()) return corrupt(std::string(L.status().message()));
  if (count != L->total()) return corrupt(absl::StrCat(count, " parameters, the modules need ", L->total()));
  std::vector<float> params;
  if (!r.Floats(&params, count)) return corrupt("truncated parameters");
  for (float v : params)
    if (!std::isfinite(v)) return corrupt("non-finite parameter");
  ExtAdamState moments;
  if (flags & kFlagAdam) {
    if (!r.Pod(&moments.step) || !r.Floats(&moments.m, count) || !r.Floats(&moments.v, count)) {
      return corrupt("truncated Adam moments");
    }
  } else if (adam) {
    return absl::FailedPreconditionError(absl::StrCat(path, ": an extension without Adam moments, not a checkpoint"));
  }
  if (r.pos() != body) return corrupt("trailing bytes");
  if (adam) *adam = std::move(moments);
  return ExtendedField::FromParams(std::move(base), c, std::move(params));
}

}  // namespace

uint64_t BaseParamsChecksum(const std::vector<float>& params) {
  return Checksum(reinterpret_cast<const char*>(params.data()), params.size() * sizeof(float));
}

absl::Status SaveExtendedField(const ExtendedField& field, const std::string& path) {
  return Save(field, nullptr, path);
}
absl::StatusOr<ExtendedField> LoadExtendedField(const std::string& path, DeformationField base) {
  return Load(path, std::move(base), nullptr);
}
absl::Status SaveExtendedCheckpoint(const ExtendedField& field, const ExtAdamState& adam, const std::string& path) {
  return Save(field, &adam, path);
}
absl::StatusOr<ExtendedField> LoadExtendedCheckpoint(const std::string& path, DeformationField base,
                                                     ExtAdamState* adam) {
  return Load(path, std::move(base), adam);
}

}  // namespace streetsim::field
