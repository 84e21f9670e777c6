#include "scene/field/field_io.h"

#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"

namespace streetsim::field {

namespace {

constexpr char kMagic[8] = {'S', 'S', 'F', 'I', 'E', 'L', 'D', '\0'};
constexpr uint32_t kVersion = 1;
constexpr uint32_t kFlagAdam = 1;

using checked_file::Checksum;
using checked_file::Reader;
using checked_file::Writer;

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

  return checked_file::WriteAtomically(path, w.buf);
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
