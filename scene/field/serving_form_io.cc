#include "scene/field/serving_form_io.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/common/checked_file.h"

namespace streetsim::field {

namespace {

using checked_file::Checksum;
using checked_file::Reader;
using checked_file::Writer;

constexpr char kServingFormMagic[8] = {'S', 'T', 'S', 'F', 'O', 'R', 'M', '\n'};
constexpr uint32_t kServingFormVersion = 4;  // 4: compact tables (serving_form_tables.h)
constexpr uint64_t kPrime = 1099511628211ull;

uint64_t Mix(uint64_t h, uint64_t v) { return (h ^ v) * kPrime; }

uint64_t MixDouble(uint64_t h, double v) {
  uint64_t bits;
  std::memcpy(&bits, &v, 8);
  return Mix(h, bits);
}

}  // namespace

class ServingFormCodec {
 public:
  static std::string Encode(const ServingForm& f, uint64_t key);
  static absl::StatusOr<std::unique_ptr<ServingForm>> Decode(const std::string& bytes, uint64_t key,
                                                             const std::string& path);
};

std::string ServingFormCodec::Encode(const ServingForm& f, uint64_t key) {
  Writer w;
  w.Raw(kServingFormMagic, 8);
  w.Pod(kServingFormVersion);
  w.Pod(key);
  w.Pod(f.time_range_.start_us);
  w.Pod(f.time_range_.end_us);
  w.Pod<int32_t>(f.control_points_);
  w.Pod<int32_t>(f.degree_);
  w.Pod<uint32_t>(f.groups_);
  const GaussianStore& g = f.current_;
  w.Pod<uint64_t>(g.size());
  w.Pod<int32_t>(g.sh_degree);
  for (const std::vector<float>* a : {&g.means, &g.log_scales, &g.rotations, &g.opacity_logits, &g.sh}) {
    w.Raw(a->data(), a->size() * sizeof(float));
  }
  w.Pod<uint64_t>(f.rows_.size());
  const FormTables& t = f.tables_;
  w.Pod<int32_t>(t.appearance_rank());
  auto raw = [&w](const auto& v) { w.Raw(v.data(), v.size() * sizeof(v[0])); };
  raw(f.rows_);
  raw(t.position_ends_);
  raw(t.position_step_);
  raw(t.q_position_);
  for (const FormTables::Block& b : t.blocks_) {
    raw(b.base_offset);
    raw(b.base_step);
    raw(b.q_base);
    raw(b.scale);
    raw(b.q_u);
    raw(b.q_v);
  }
  w.Raw(f.error_.max.data(), sizeof(float) * kFormGroups);
  w.Pod(f.error_.position_p99_m);
  w.Pod<int32_t>(f.error_.check_samples);
  w.Pod<uint64_t>(Checksum(w.buf.data(), w.buf.size()));
  return std::move(w.buf);
}

absl::StatusOr<std::unique_ptr<ServingForm>> ServingFormCodec::Decode(const std::string& bytes, uint64_t key,
                                                                      const std::string& path) {
  auto corrupt = [&](const std::string& why) { return absl::DataLossError(absl::StrCat(path, ": ", why)); };
  if (bytes.size() < 8 + 4 + 8 + 8 || std::memcmp(bytes.data(), kServingFormMagic, 8) != 0) {
    return corrupt("not a streetsim serving form");
  }
  const size_t body = bytes.size() - 8;
  uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + body, 8);
  Reader r(bytes.data(), body);
  char magic[8];
  uint32_t version = 0;
  uint64_t file_key = 0;
  r.Raw(magic, 8);
  if (!r.Pod(&version)) return corrupt("truncated header");
  if (version != kServingFormVersion) return corrupt(absl::StrCat("serving form version ", version, ", this streetsim reads ", kServingFormVersion));
  if (stored != Checksum(bytes.data(), body)) return corrupt("checksum mismatch (truncated or damaged)");
  if (!r.Pod(&file_key)) return corrupt("truncated header");
  if (file_key != key) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, ": built from other files or options (the scene changed since): stale"));
  }
  std::unique_ptr<ServingForm> f(new ServingForm());
  int32_t m = 0, degree = 0, sh_degree = 0;
  uint32_t groups = 0;
  uint64_t n = 0, nd = 0;
  if (!r.Pod(&f->time_range_.start_us) || !r.Pod(&f->time_range_.end_us) || !r.Pod(&m) || !r.Pod(&degree) || !r.Pod(&groups) ||
      !r.Pod(&n) || !r.Pod(&sh_degree)) {
    return corrupt("truncated header");
  }
  if ((degree != 1 && degree != 3) || m < degree + 1 || m > 1024 + degree || !(groups & 1u) || groups >= (1u << kFormGroups) || sh_degree != 3 ||
      n > (1ull << 32) || f->time_range_.end_us < f->time_range_.start_us) {
    return corrupt("header out of range");
  }
  f->control_points_ = m;
  f->degree_ = degree;
  f->groups_ = groups;
  GaussianStore& g = f->current_;
  g.sh_degree = sh_degree;
  const size_t K3 = static_cast<size_t>(g.sh_coeffs()) * 3;
  if (!r.Floats(&g.means, n * 3) || !r.Floats(&g.log_scales, n * 3) || !r.Floats(&g.rotations, n * 4) ||
      !r.Floats(&g.opacity_logits, n) || !r.Floats(&g.sh, n * K3) || !r.Pod(&nd) || nd > n) {
    return corrupt("truncated Gaussians");
  }
  int32_t rank = 0;
  if (!r.Pod(&rank) || rank < 0 || rank > kMaxAppearanceRank) return corrupt("bad appearance rank");
  FormTables& t = f->tables_;
  t.rows_ = nd;
  t.control_points_ = m;
  t.groups_ = groups;
  t.blocks_ = FormTables::BlocksOf(groups, rank, m);
  if (t.appearance_rank() != rank) return corrupt("bad appearance rank");
  // Every table's size follows from the header: checked against the file before allocating.
  size_t per_row = sizeof(uint32_t) + 6 * sizeof(float) + 3 * sizeof(uint16_t) + size_t(m) * 3;
  for (const FormTables::Block& b : t.blocks_) {
    per_row += b.group_count() * (sizeof(float) + sizeof(uint16_t)) + b.channels + b.rank * sizeof(uint16_t) +
               size_t(b.rank) * (m + b.channels);
  }
  if (nd * per_row > body - r.pos()) return corrupt("truncated tables");
  f->rows_.resize(nd);
  t.position_ends_.resize(nd * 6);
  t.position_step_.resize(nd * 3);
  t.q_position_.resize(nd * m * 3);
  for (FormTables::Block& b : t.blocks_) b.Resize(nd, m);
  auto raw = [&r](auto& v) { return r.Raw(v.data(), v.size() * sizeof(v[0])); };
  bool ok = raw(f->rows_) && raw(t.position_ends_) && raw(t.position_step_) && raw(t.q_position_);
  for (FormTables::Block& b : t.blocks_) {
    ok = ok && raw(b.base_offset) && raw(b.base_step) && raw(b.q_base) && raw(b.scale) && raw(b.q_u) && raw(b.q_v);
  }
  if (!ok || !r.Raw(f->error_.max.data(), sizeof(float) * kFormGroups) || !r.Pod(&f->error_.position_p99_m) ||
      !r.Pod(&f->error_.check_samples)) {
    return corrupt("truncated tables");
  }
  if (r.pos() != body) return corrupt("trailing bytes");
  for (size_t r2 = 0; r2 < nd; ++r2) {
    if (f->rows_[r2] >= n || (r2 > 0 && f->rows_[r2] <= f->rows_[r2 - 1])) return corrupt("bad row index");
  }
  auto finite = [](const std::vector<float>& v) { return std::all_of(v.begin(), v.end(), [](float x) { return std::isfinite(x); }); };
  auto finite16 = [](const std::vector<uint16_t>& v) {
    return std::all_of(v.begin(), v.end(), [](uint16_t x) { return std::isfinite(FromBf16(x)); });
  };
  ok = finite(t.position_ends_) && finite16(t.position_step_);
  for (const FormTables::Block& b : t.blocks_) ok = ok && finite(b.base_offset) && finite16(b.base_step) && finite16(b.scale);
  if (!ok) return corrupt("non-finite table value");
  if (absl::Status s = g.Validate(); !s.ok()) return corrupt(std::string(s.message()));
  return f;
}

std::string EncodeServingForm(const ServingForm& form, uint64_t key) { return ServingFormCodec::Encode(form, key); }

absl::StatusOr<std::unique_ptr<ServingForm>> DecodeServingForm(const std::string& bytes, uint64_t key,
                                                               const std::string& path) {
  return ServingFormCodec::Decode(bytes, key, path);
}

absl::StatusOr<uint64_t> ServingFormSourceKey(const std::vector<std::string>& files, const ServingFormOptions& form,
                                              const StaticSkipOptions& skip) {
  uint64_t h = Mix(1469598103934665603ull, kServingFormVersion);
  for (int v : {form.degree, form.segments_per_cell, form.max_segments_per_cell, form.samples_per_segment,
                form.appearance_rank}) {
    h = Mix(h, static_cast<uint64_t>(v));
  }
  h = MixDouble(h, form.max_position_error_m);
  for (double v : {skip.motion_threshold_m, skip.sh_threshold, skip.log_scale_threshold, skip.rotation_threshold,
                   skip.opacity_threshold, double(skip.num_samples), double(skip.enabled)}) {
    h = MixDouble(h, v);
  }
  std::vector<char> chunk(8 << 20);
  for (const std::string& path : files) {
    const std::string name = std::filesystem::path(path).filename().string();
    h = Mix(h, Checksum(name.data(), name.size()));
    std::error_code ec;
    if (!std::filesystem::exists(path, ec)) {
      h = Mix(h, 0xab5e47ull);
      continue;
    }
    std::ifstream in(path, std::ios::binary);
    if (!in) return absl::NotFoundError(absl::StrCat("cannot open ", path));
    uint64_t total = 0;
    while (in) {
      in.read(chunk.data(), static_cast<std::streamsize>(chunk.size()));
      const std::streamsize got = in.gcount();
      if (got <= 0) break;
      h = Mix(h, Checksum(chunk.data(), static_cast<size_t>(got)));
      total += static_cast<uint64_t>(got);
    }
    if (in.bad()) return absl::DataLossError(absl::StrCat(path, ": read error"));
    h = Mix(h, total);
  }
  return h;
}

absl::StatusOr<CachedServingForm> LoadOrBuildServingForm(
    const std::string& cache_path, uint64_t key,
    const std::function<absl::StatusOr<std::unique_ptr<ServedScene>>()>& make_exact,
    const ServingFormOptions& options, ThreadPool& pool) {
  CachedServingForm out;
  std::error_code ec;
  if (std::filesystem::exists(cache_path, ec)) {
    std::ifstream in(cache_path, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    absl::StatusOr<std::unique_ptr<ServingForm>> cached =
        in.bad() ? absl::DataLossError(absl::StrCat(cache_path, ": read error"))
                 : DecodeServingForm(bytes, key, cache_path);
    if (cached.ok()) {
      out.form = std::move(*cached);
      out.from_cache = true;
      return out;
    }
    out.note = absl::StrCat(cached.status().message(), "; rebuilt");
    LOG(WARNING) << "serving form cache not used: " << out.note;
  }
  const auto t0 = std::chrono::steady_clock::now();
  {
    absl::StatusOr<std::unique_ptr<ServedScene>> exact = make_exact();
    if (!exact.ok()) return exact.status();
    absl::StatusOr<std::unique_ptr<ServingForm>> built = ServingForm::Build(**exact, options, pool);
    if (!built.ok()) return built.status();
    out.form = std::move(*built);
    if (!out.within_bound(options)) out.exact = std::move(*exact);
  }
  const ServingFormError& e = out.form->error();
  LOG(INFO) << "serving form of " << out.form->num_dynamic() << " moving Gaussians built in "
            << std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() << " s: position error max "
            << e.max[0] * 1000 << " mm, p99 " << e.position_p99_m * 1000 << " mm over " << e.check_samples
            << " check samples";
  out.form->ForgetPositionErrors();  // the summary, error(), is what is served and cached
  if (absl::Status s = checked_file::WriteAtomically(cache_path, EncodeServingForm(*out.form, key)); !s.ok()) {
    const std::string why = absl::StrCat("cannot write the serving form cache ", cache_path, " (", s.message(),
                                         "): served from memory, rebuilt at the next load");
    out.note = out.note.empty() ? why : absl::StrCat(out.note, "; ", why);
    LOG(WARNING) << why;
  }
  return out;
}

}  // namespace streetsim::field
