#include "scene/field/field_io.h"

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"

namespace streetsim::field {

namespace {

constexpr char kMagic[8] = {'S', 'S', 'F', 'I', 'E', 'L', 'D', '\0'};
constexpr uint32_t kVersion = 1;
constexpr uint32_t kFlagAdam = 1;

// 64-bit FNV-1a over 8-byte words (bytes for the tail): catches truncation and bit rot, fast
// enough for 140 MiB of planes.
uint64_t Checksum(const char* data, size_t n) {
  uint64_t h = 1469598103934665603ull;
  constexpr uint64_t kPrime = 1099511628211ull;
  size_t i = 0;
  for (; i + 8 <= n; i += 8) {
    uint64_t w;
    std::memcpy(&w, data + i, 8);
    h = (h ^ w) * kPrime;
  }
  for (; i < n; ++i) h = (h ^ static_cast<unsigned char>(data[i])) * kPrime;
  return h;
}

class Writer {
 public:
  template <typename T>
  void Pod(const T& v) { Raw(&v, sizeof(T)); }
  void Raw(const void* p, size_t n) { buf.append(static_cast<const char*>(p), n); }
  std::string buf;
};

class Reader {
 public:
  Reader(const char* data, size_t n) : data_(data), n_(n) {}
  template <typename T>
  bool Pod(T* v) { return Raw(v, sizeof(T)); }
  bool Raw(void* p, size_t n) {
    if (n > n_ - pos_) return false;
    std::memcpy(p, data_ + pos_, n);
    pos_ += n;
    return true;
  }
  bool Floats(std::vector<float>* v, size_t count) {
    if (count > (n_ - pos_) / sizeof(float)) return false;
    v->resize(count);
    return Raw(v->data(), count * sizeof(float));
  }
  size_t pos() const { return pos_; }

 private:
  const char* data_;
  size_t n_;
  size_t pos_ = 0;
};

absl::Status Save(const DeformationField& f, const FieldAdamState* adam, const std::string& path) {
  const FieldConfig& c = f.config();
  const size_t total = f.layout().total;
  if (adam && (adam->m.size() != total || adam->v.size() != total)) {
    return absl::InvalidArgumentError(absl::StrCat("field checkpoint: Adam moments have ", adam->m.size(), " / ",
                                                   adam->v.size(), " values, the field ", total));
  }
  Writer w;
  w.buf.reserve(64 + total * sizeof(float) * (adam ? 3 : 1));
  w.Raw(kMagic, 8);
  w.Pod<uint32_t>(kVersion);
  w.Pod<uint32_t>(adam ? kFlagAdam : 0);
  w.Pod<int32_t>(c.channels);
  w.Pod<int32_t>(c.base_resolution);
  w.Pod<int32_t>(c.num_levels());
  for (int m : c.multires) w.Pod<int32_t>(m);
  w.Pod<int32_t>(c.time_resolution);
  w.Pod<int32_t>(c.width);
  w.Pod<float>(c.plane_init_lo);
  w.Pod<float>(c.plane_init_hi);
  w.Pod<uint8_t>(c.full_time_range ? 1 : 0);
  w.Raw(f.aabb().min, sizeof(double) * 3);
  w.Raw(f.aabb().max, sizeof(double) * 3);
  w.Pod<int64_t>(f.time_range().start_us);
  w.Pod<int64_t>(f.time_range().end_us);
  w.Pod<uint64_t>(total);
  w.Raw(f.params().data(), total * sizeof(float));
  if (adam) {
    w.Pod<int64_t>(adam->step);
    w.Raw(adam->m.data(), total * sizeof(float));
    w.Raw(adam->v.data(), total * sizeof(float));
  }
  w.Pod<uint64_t>(Checksum(w.buf.data(), w.buf.size()));

  const std::string tmp = path + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out.write(w.buf.data(), static_cast<std::streamsize>(w.buf.size()));
    out.flush();
    if (!out) {
      std::error_code ec;
      std::filesystem::remove(tmp, ec);
      return absl::InternalError(absl::StrCat("cannot write ", tmp));
    }
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot rename ", tmp, " to ", path, ": ", ec.message()));
  return absl::OkStatus();
}

absl::StatusOr<FieldCheckpoint> Load(const std::string& path, bool want_adam) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open field file ", path));
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) return absl::DataLossError(absl::StrCat(path, ": read error"));
  auto corrupt = [&](const std::string& why) { return absl::DataLossError(absl::StrCat(path, ": ", why)); };
  if (bytes.size() < 8 + 8 || std::memcmp(bytes.data(), kMagic, 8) != 0) {
    return corrupt("not a streetsim field file");
  }
  const size_t body = bytes.size() - 8;
  uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + body, 8);
  Reader r(bytes.data(), body);
  char magic[8];
  uint32_t version = 0, flags = 0;
  r.Raw(magic, 8);
  if (!r.Pod(&version) || !r.Pod(&flags)) return corrupt("truncated header");
  if (version != kVersion) return corrupt(absl::StrCat("unsupported field file version ", version, " (want ", kVersion, ")"));
  if (stored != Checksum(bytes.data(), body)) return corrupt("checksum mismatch (truncated or corrupt field file)");
  if (flags & ~kFlagAdam) return corrupt(absl::StrCat("unknown flags ", flags));
  FieldConfig c;
  int32_t levels = 0;
  uint8_t full = 0;
  bool ok = r.Pod(&c.channels) && r.Pod(&c.base_resolution) && r.Pod(&levels);
  if (!ok || levels < 1 || levels > 8) return corrupt("bad level count");
  c.multires.assign(levels, 0);
  for (int l = 0; l < levels && ok; ++l) ok = r.Pod(&c.multires[l]);
  ok = ok && r.Pod(&c.time_resolution) && r.Pod(&c.width) && r.Pod(&c.plane_init_lo) && r.Pod(&c.plane_init_hi) &&
       r.Pod(&full);
  if (!ok) return corrupt("truncated configuration");
  c.full_time_range = full != 0;
  if (absl::Status s = c.Validate(); !s.ok()) return corrupt(std::string(s.message()));
  FieldAabb aabb;
  FieldTimeRange tr;
  uint64_t count = 0;
  if (!r.Raw(aabb.min, 24) || !r.Raw(aabb.max, 24) || !r.Pod(&tr.start_us) || !r.Pod(&tr.end_us) || !r.Pod(&count)) {
    return corrupt("truncated header");
  }
  const FieldLayout layout = FieldLayout::Make(c);
  if (count != layout.total) {
    return corrupt(absl::StrCat(count, " parameters, the configuration needs ", layout.total));
  }
  std::vector<float> params;
  if (!r.Floats(&params, count)) return corrupt("truncated parameters");
  FieldAdamState adam;
  if (flags & kFlagAdam) {
    if (!r.Pod(&adam.step) || !r.Floats(&adam.m, count) || !r.Floats(&adam.v, count)) {
      return corrupt("truncated Adam moments");
    }
  } else if (want_adam) {
    return absl::FailedPreconditionError(absl::StrCat(path, ": a field without Adam moments, not a checkpoint"));
  }
  if (r.pos() != body) return corrupt("trailing bytes");
  absl::StatusOr<DeformationField> f = DeformationField::FromParams(c, aabb, tr, std::move(params));
  if (!f.ok()) return corrupt(std::string(f.status().message()));
  return FieldCheckpoint{std::move(*f), std::move(adam)};
}

}  // namespace

absl::Status SaveField(const DeformationField& field, const std::string& path) { return Save(field, nullptr, path); }

absl::StatusOr<DeformationField> LoadField(const std::string& path) {
  absl::StatusOr<FieldCheckpoint> c = Load(path, false);
  if (!c.ok()) return c.status();
  return std::move(c->field);
}

absl::Status SaveFieldCheckpoint(const DeformationField& field, const FieldAdamState& adam, const std::string& path) {
  return Save(field, &adam, path);
}

absl::StatusOr<FieldCheckpoint> LoadFieldCheckpoint(const std::string& path) { return Load(path, true); }

}  // namespace streetsim::field
