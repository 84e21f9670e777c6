#include "scene/gaussians/ply_io.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string_view>
#include <system_error>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/escaping.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"

namespace streetsim {
namespace {

// Floats are copied byte-for-byte between the file and memory; that is only the PLY's
// little-endian encoding on a little-endian host.
static_assert(std::endian::native == std::endian::little, "PLY I/O assumes a little-endian host");
static_assert(sizeof(float) == 4 && std::numeric_limits<float>::is_iec559);

// A real 3DGS header is ~1.5 KiB; anything far larger is not a Gaussian PLY, and bounding the
// search keeps a garbage file from being scanned (or held) in full before we give up.
constexpr size_t kMaxHeaderBytes = 64 * 1024;
// Some tools end the file with "\n" or "\r\n" after the binary body; more than that is garbage.
constexpr size_t kMaxTrailingNewlineBytes = 2;
constexpr int kMaxRest = 3 * (ShCoeffsForDegree(kMaxShDegree) - 1);  // 45

// Every known property has a fixed slot, independent of where it appears in a file. Slot order is
// also the canonical INRIA write order.
enum Slot : int {
  kSlotX = 0,
  kSlotNx = 3,
  kSlotDc = 6,
  kSlotRest = 9,
  kSlotOpacity = kSlotRest + kMaxRest,  // 54
  kSlotScale = kSlotOpacity + 1,        // 55
  kSlotRot = kSlotScale + 3,            // 58
  kNumSlots = kSlotRot + 4,             // 62
};
// Not a 3DGS property: the per-Gaussian LiDAR reflectance a trained scene carries (docs/lidar.md).
// Accepted and skipped by the reader (the store has no such array; lidar_eval.h reads it).
constexpr int kSlotReflectance = -2;
constexpr char kReflectanceName[] = "reflectance";

std::string SlotName(int slot) {
  if (slot == kSlotReflectance) return kReflectanceName;
  static constexpr const char* kXyz[] = {"x", "y", "z"};
  static constexpr const char* kNormal[] = {"nx", "ny", "nz"};
  if (slot < kSlotNx) return kXyz[slot - kSlotX];
  if (slot < kSlotDc) return kNormal[slot - kSlotNx];
  if (slot < kSlotRest) return absl::StrCat("f_dc_", slot - kSlotDc);
  if (slot < kSlotOpacity) return absl::StrCat("f_rest_", slot - kSlotRest);
  if (slot == kSlotOpacity) return "opacity";
  if (slot < kSlotRot) return absl::StrCat("scale_", slot - kSlotScale);
  return absl::StrCat("rot_", slot - kSlotRot);
}

// Returns the slot for a property name, or -1 if it is not part of the 3DGS layout. Only the
// canonical spellings match, so e.g. "f_rest_01" is not an alias of f_rest_1.
int SlotForName(absl::string_view name) {
  static const std::array<std::string, kNumSlots>* const kNames = [] {
    auto* names = new std::array<std::string, kNumSlots>;
    for (int s = 0; s < kNumSlots; ++s) (*names)[s] = SlotName(s);
    return names;
  }();
  for (int s = 0; s < kNumSlots; ++s) {
    if ((*kNames)[s] == name) return s;
  }
  return -1;
}

enum ArrayId { kMeans, kNormals, kSh, kOpacity, kScales, kRotations };

// Where a slot's value lives in the store: array[i * per + offset] for Gaussian i.
struct SlotLayout {
  ArrayId array;
  size_t per;
  size_t offset;
};

SlotLayout LayoutOf(int slot, int k_coeffs) {
  const size_t sh_per = static_cast<size_t>(k_coeffs) * 3;
  if (slot < kSlotNx) return {kMeans, 3, static_cast<size_t>(slot - kSlotX)};
  if (slot < kSlotDc) return {kNormals, 3, static_cast<size_t>(slot - kSlotNx)};
  if (slot < kSlotRest) return {kSh, sh_per, static_cast<size_t>(slot - kSlotDc)};  // k = 0
  if (slot < kSlotOpacity) {
    // f_rest is channel-major in the file; the store is coefficient-major.
    const int rest = slot - kSlotRest;
    const int channel = rest / (k_coeffs - 1);
    const int coeff = rest % (k_coeffs - 1) + 1;
    return {kSh, sh_per, static_cast<size_t>(coeff * 3 + channel)};
  }
  if (slot == kSlotOpacity) return {kOpacity, 1, 0};
  if (slot < kSlotRot) return {kScales, 3, static_cast<size_t>(slot - kSlotScale)};
  return {kRotations, 4, static_cast<size_t>(slot - kSlotRot)};
}

// Indexed by ArrayId.
constexpr std::vector<float> GaussianStore::*kArrays[] = {
    &GaussianStore::means,          &GaussianStore::normals,    &GaussianStore::sh,
    &GaussianStore::opacity_logits, &GaussianStore::log_scales, &GaussianStore::rotations};

std::vector<int> CanonicalSlots(int sh_degree, bool normals) {
  const int rest = 3 * (ShCoeffsForDegree(sh_degree) - 1);
  std::vector<int> slots;
  for (int s = 0; s < kNumSlots; ++s) {
    if (!normals && s >= kSlotNx && s < kSlotDc) continue;
    if (s >= kSlotRest + rest && s < kSlotOpacity) continue;
    slots.push_back(s);
  }
  return slots;
}

// File bytes are echoed into messages; escape and clip them so errors stay printable and short.
std::string Quote(absl::string_view s) {
  constexpr size_t kMax = 48;
  return absl::StrCat("'", absl::CHexEscape(s.substr(0, kMax)), s.size() > kMax ? "..." : "", "'");
}

absl::Status HeaderError(int line_no, absl::string_view msg) {
  return absl::InvalidArgumentError(absl::StrCat("PLY header line ", line_no, ": ", msg));
}

struct Header {
  uint64_t count = 0;
  std::vector<int> slots;  // in file column order
  int sh_degree = 0;
  bool normals = false;
  size_t data_offset = 0;
};

// Checks that the vertex properties are exactly one valid 3DGS layout and derives its shape.
absl::Status CheckPropertySet(const std::array<bool, kNumSlots>& seen, Header* header) {
  std::string missing;
  for (int s = 0; s < kNumSlots; ++s) {
    const bool optional = (s >= kSlotNx && s < kSlotDc) || (s >= kSlotRest && s < kSlotOpacity);
    if (!optional && !seen[s]) absl::StrAppend(&missing, missing.empty() ? "" : " ", SlotName(s));
  }
  if (!missing.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("PLY: missing required properties: ", missing));
  }
  const int normals = seen[kSlotNx] + seen[kSlotNx + 1] + seen[kSlotNx + 2];
  if (normals != 0 && normals != 3) {
    return absl::InvalidArgumentError("PLY: normals must be all of nx ny nz or none");
  }
  header->normals = normals == 3;
  const int rest =
      static_cast<int>(std::count(seen.begin() + kSlotRest, seen.begin() + kSlotOpacity, true));
  int degree = -1;
  for (int d = 0; d <= kMaxShDegree; ++d) {
    if (rest == 3 * (ShCoeffsForDegree(d) - 1)) degree = d;
  }
  if (degree < 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "PLY: ", rest, " f_rest properties; expected 0, 9, 24 or 45 (SH degree 0..3)"));
  }
  for (int r = 0; r < rest; ++r) {
    if (!seen[kSlotRest + r]) {
      return absl::InvalidArgumentError(absl::StrCat("PLY: f_rest numbering has a gap: f_rest_", r,
                                                     " missing among ", rest,
                                                     " f_rest properties"));
    }
  }
  header->sh_degree = degree;
  return absl::OkStatus();
}

absl::StatusOr<Header> ParseHeader(absl::string_view bytes) {
  const absl::string_view window = bytes.substr(0, kMaxHeaderBytes);
  Header header;
  std::array<bool, kNumSlots> seen{};
  bool have_format = false;
  bool have_vertex = false;
  bool in_vertex = false;
  bool in_other = false;  // properties of an empty non-vertex element: parsed leniently, ignored
  size_t pos = 0;
  for (int line_no = 1;; ++line_no) {
    const size_t nl = window.find('\n', pos);
    if (nl == absl::string_view::npos) {
      return absl::InvalidArgumentError(
          bytes.size() <= kMaxHeaderBytes
              ? std::string("PLY: header ends without an end_header line (file truncated?)")
              : absl::StrCat("PLY: no end_header within the first ", kMaxHeaderBytes, " bytes"));
    }
    absl::string_view line = window.substr(pos, nl - pos);
    pos = nl + 1;
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    const std::vector<absl::string_view> tok =
        absl::StrSplit(line, absl::ByAnyChar(" \t"), absl::SkipEmpty());
    if (line_no == 1) {
      if (tok.size() != 1 || tok[0] != "ply") {
        return absl::InvalidArgumentError("PLY: not a PLY file (first line is not 'ply')");
      }
      continue;
    }
    if (tok.empty() || tok[0] == "comment" || tok[0] == "obj_info") continue;
    const absl::string_view kw = tok[0];
    if (kw == "end_header") {
      if (tok.size() != 1) return HeaderError(line_no, "malformed end_header line");
      break;
    }
    if (kw == "format") {
      if (have_format) return HeaderError(line_no, "duplicate format line");
      if (tok.size() != 3) return HeaderError(line_no, "malformed format line");
      if (tok[1] != "binary_little_endian") {
        return HeaderError(line_no, absl::StrCat("unsupported format ", Quote(tok[1]),
                                                 "; only binary_little_endian is supported"));
      }
      if (tok[2] != "1.0") {
        return HeaderError(line_no, absl::StrCat("unsupported PLY version ", Quote(tok[2])));
      }
      have_format = true;
      continue;
    }
    if (kw == "element") {
      if (!have_format) return HeaderError(line_no, "element before the format line");
      uint64_t count = 0;
      const auto is_digit = [](char ch) { return ch >= '0' && ch <= '9'; };
      // SimpleAtoi alone would accept "+5" and "-0"; a count is plain digits.
      if (tok.size() != 3 || !std::all_of(tok[2].begin(), tok[2].end(), is_digit) ||
          !absl::SimpleAtoi(tok[2], &count)) {
        return HeaderError(line_no, absl::StrCat("malformed element line ", Quote(line)));
      }
      in_vertex = tok[1] == "vertex";
      in_other = !in_vertex;
      if (in_vertex) {
        if (have_vertex) return HeaderError(line_no, "duplicate vertex element");
        have_vertex = true;
        header.count = count;
      } else if (count > 0) {
        return HeaderError(line_no, absl::StrCat("element ", Quote(tok[1]), " has ", count,
                                                 " entries; only a vertex element may hold data"));
      }
      continue;
    }
    if (kw == "property") {
      if (in_other) continue;
      if (!in_vertex) return HeaderError(line_no, "property before any element");
      if (tok.size() >= 2 && tok[1] == "list") {
        return HeaderError(line_no, "list properties are not supported in the vertex element");
      }
      if (tok.size() != 3) {
        return HeaderError(line_no, absl::StrCat("malformed property line ", Quote(line)));
      }
      if (tok[1] != "float" && tok[1] != "float32") {
        return HeaderError(line_no, absl::StrCat("property ", Quote(tok[2]), " has type ",
                                                 Quote(tok[1]), "; only float is supported"));
      }
      if (tok[2] == kReflectanceName) {
        if (std::count(header.slots.begin(), header.slots.end(), kSlotReflectance) > 0) {
          return HeaderError(line_no, absl::StrCat("duplicate property ", Quote(tok[2])));
        }
        header.slots.push_back(kSlotReflectance);
        continue;
      }
      const int slot = SlotForName(tok[2]);
      if (slot < 0) {
        return HeaderError(line_no, absl::StrCat("unexpected property ", Quote(tok[2])));
      }
      if (seen[slot]) {
        return HeaderError(line_no, absl::StrCat("duplicate property ", Quote(tok[2])));
      }
      seen[slot] = true;
      header.slots.push_back(slot);
      continue;
    }
    return HeaderError(line_no, absl::StrCat("unknown header keyword ", Quote(kw)));
  }
  if (!have_vertex) return absl::InvalidArgumentError("PLY: no vertex element");
  if (absl::Status s = CheckPropertySet(seen, &header); !s.ok()) return s;
  header.data_offset = pos;
  return header;
}

absl::Status WithPath(const std::string& path, const absl::Status& s) {
  return absl::Status(s.code(), absl::StrCat(path, ": ", s.message()));
}

// Owns a file descriptor so every early return closes it.
class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  ~Fd() { Close(); }
  int get() const { return fd_; }
  int Close() {
    const int rc = fd_ >= 0 ? ::close(fd_) : 0;
    fd_ = -1;
    return rc;
  }

 private:
  int fd_;
};

absl::Status WriteAll(int fd, absl::string_view data) {
  while (!data.empty()) {
    const ssize_t n = ::write(fd, data.data(), data.size());
    if (n < 0) {
      if (errno == EINTR) continue;
      return absl::ErrnoToStatus(errno, "write");
    }
    if (n == 0) return absl::DataLossError("write made no progress");  // would spin forever
    data.remove_prefix(static_cast<size_t>(n));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<GaussianStore> ParseGaussianPly(std::string_view file,
                                               const PlyReadOptions& options) {
  // Debian's Abseil is built with its own string_view type, distinct from std::string_view.
  const absl::string_view bytes(file.data(), file.size());
  absl::StatusOr<Header> parsed = ParseHeader(bytes);
  if (!parsed.ok()) return parsed.status();
  const Header& h = *parsed;
  if (h.count > options.max_gaussians) {
    return absl::InvalidArgumentError(absl::StrCat("PLY: header declares ", h.count,
                                                   " Gaussians, more than the limit of ",
                                                   options.max_gaussians));
  }
  // Checked against the actual byte count before anything is allocated, so a lying header cannot
  // trigger a huge allocation; the division form cannot overflow.
  const size_t stride = h.slots.size() * sizeof(float);
  const size_t available = bytes.size() - h.data_offset;
  if (h.count > available / stride) {
    return absl::InvalidArgumentError(
        absl::StrCat("PLY: file truncated: header declares ", h.count, " Gaussians of ", stride,
                     " bytes each but only ", available, " data bytes follow the header"));
  }
  const size_t n = static_cast<size_t>(h.count);
  const absl::string_view trailing = bytes.substr(h.data_offset + n * stride);
  if (trailing.size() > kMaxTrailingNewlineBytes ||
      trailing.find_first_not_of("\r\n") != absl::string_view::npos) {
    return absl::InvalidArgumentError(absl::StrCat(
        "PLY: ", trailing.size(), " unexpected bytes after the last of ", n, " Gaussians"));
  }

  GaussianStore store;
  store.sh_degree = h.sh_degree;
  store.Resize(n);
  if (h.normals) store.normals.resize(n * 3);
  struct Column {
    float* base;
    size_t per;
    size_t offset;
  };
  std::vector<Column> cols;
  cols.reserve(h.slots.size());
  // A skipped column (reflectance) lands in a scratch slot.
  float skipped = 0;
  for (int slot : h.slots) {
    if (slot == kSlotReflectance) {
      cols.push_back({&skipped, 0, 0});
      continue;
    }
    const SlotLayout l = LayoutOf(slot, store.sh_coeffs());
    cols.push_back({(store.*kArrays[l.array]).data(), l.per, l.offset});
  }
  const char* rec = bytes.data() + h.data_offset;
  for (size_t i = 0; i < n; ++i) {
    for (size_t j = 0; j < cols.size(); ++j, rec += sizeof(float)) {
      float v;
      std::memcpy(&v, rec, sizeof(float));
      if (!std::isfinite(v)) {
        return absl::InvalidArgumentError(absl::StrCat(
            "PLY: Gaussian ", i, " property '", SlotName(h.slots[j]), "' is not finite (", v, ")"));
      }
      cols[j].base[i * cols[j].per + cols[j].offset] = v;
    }
  }
  // Values are finite by now; this catches all-zero rotations, which would normalise to NaN later.
  if (absl::Status s = store.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("PLY: ", s.message()));
  }
  return store;
}

absl::StatusOr<GaussianStore> ReadGaussianPly(const std::string& path,
                                              const PlyReadOptions& options) {
  // O_NONBLOCK: opening a FIFO must not wait for a writer; it is then refused as irregular.
  Fd fd(::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC));
  if (fd.get() < 0) {
    const int err = errno;
    const std::string why = std::generic_category().message(err);
    if (err == ENOENT || err == ENOTDIR) return absl::NotFoundError(absl::StrCat(path, ": ", why));
    return absl::InvalidArgumentError(absl::StrCat(path, ": cannot open: ", why));
  }
  struct stat st;
  if (::fstat(fd.get(), &st) != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": cannot stat: ", std::generic_category().message(errno)));
  }
  if (!S_ISREG(st.st_mode)) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a regular file"));
  }
  // Bound the read by what options allow, so a huge unrelated file is refused before it is loaded.
  const uint64_t size = static_cast<uint64_t>(st.st_size);
  const uint64_t max_stride = kNumSlots * sizeof(float);
  const uint64_t max_size =
      options.max_gaussians >
              (std::numeric_limits<uint64_t>::max() - 2 * kMaxHeaderBytes) / max_stride
          ? std::numeric_limits<uint64_t>::max()
          : options.max_gaussians * max_stride + kMaxHeaderBytes + kMaxTrailingNewlineBytes;
  if (size > max_size) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": file of ", size,
                                                   " bytes is larger than any PLY of at most ",
                                                   options.max_gaussians, " Gaussians"));
  }
  std::string bytes(static_cast<size_t>(size), '\0');
  size_t got = 0;
  while (got < bytes.size()) {
    const ssize_t r = ::read(fd.get(), bytes.data() + got, bytes.size() - got);
    if (r < 0) {
      if (errno == EINTR) continue;
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": read failed: ", std::generic_category().message(errno)));
    }
    if (r == 0) break;  // shrank while reading; the parser reports what is missing
    got += static_cast<size_t>(r);
  }
  bytes.resize(got);
  absl::StatusOr<GaussianStore> store = ParseGaussianPly(bytes, options);
  if (!store.ok()) return WithPath(path, store.status());
  return store;
}

std::string SerializeGaussianPly(const GaussianStore& store) { return SerializeGaussianPly(store, nullptr); }

std::string SerializeGaussianPly(const GaussianStore& store, const std::vector<float>* reflectance) {
  std::vector<int> slots = CanonicalSlots(store.sh_degree, !store.normals.empty());
  if (reflectance != nullptr) slots.push_back(kSlotReflectance);
  const size_t n = store.size();
  std::string header =
      absl::StrCat("ply\nformat binary_little_endian 1.0\nelement vertex ", n, "\n");
  for (int s : slots) absl::StrAppend(&header, "property float ", SlotName(s), "\n");
  header += "end_header\n";

  struct Column {
    const float* base;
    size_t per;
    size_t offset;
  };
  std::vector<Column> cols;
  cols.reserve(slots.size());
  for (int slot : slots) {
    if (slot == kSlotReflectance) {
      cols.push_back({reflectance->data(), 1, 0});
      continue;
    }
    const SlotLayout l = LayoutOf(slot, store.sh_coeffs());
    cols.push_back({(store.*kArrays[l.array]).data(), l.per, l.offset});
  }
  std::string out(header.size() + n * slots.size() * sizeof(float), '\0');
  std::memcpy(out.data(), header.data(), header.size());
  char* p = out.data() + header.size();
  for (size_t i = 0; i < n; ++i) {
    for (const Column& c : cols) {
      std::memcpy(p, &c.base[i * c.per + c.offset], sizeof(float));
      p += sizeof(float);
    }
  }
  return out;
}

absl::Status WriteGaussianPly(const GaussianStore& store, const std::string& path) {
  return WriteGaussianPly(store, path, nullptr);
}

absl::Status WriteGaussianPly(const GaussianStore& store, const std::string& path,
                              const std::vector<float>* reflectance) {
  if (absl::Status s = store.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": refusing to write: ", s.message()));
  }
  if (reflectance != nullptr) {
    if (reflectance->size() != store.size()) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": refusing to write: ", reflectance->size(),
                                                     " reflectance values for ", store.size(), " Gaussians"));
    }
    for (float r : *reflectance) {
      if (!(r >= 0.0f && r <= 1.0f)) {
        return absl::InvalidArgumentError(absl::StrCat(path, ": refusing to write: reflectance ", r,
                                                       " outside [0, 1]"));
      }
    }
  }
  const std::string bytes = SerializeGaussianPly(store, reflectance);
  const std::string tmp = absl::StrCat(path, ".tmp.", ::getpid());
  Fd fd(::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644));
  if (fd.get() < 0) return WithPath(path, absl::ErrnoToStatus(errno, "cannot create temp file"));

  absl::Status status = WriteAll(fd.get(), bytes);
  // fsync before rename: otherwise a crash can leave the new name pointing at an empty file.
  if (status.ok() && ::fsync(fd.get()) != 0) status = absl::ErrnoToStatus(errno, "fsync");
  if (fd.Close() != 0 && status.ok()) status = absl::ErrnoToStatus(errno, "close");
  if (status.ok() && ::rename(tmp.c_str(), path.c_str()) != 0) {
    status = absl::ErrnoToStatus(errno, "rename");
  }
  if (!status.ok()) {
    ::unlink(tmp.c_str());
    return WithPath(path, status);
  }
  // Best effort: persist the rename itself. Failure here does not undo a completed write.
  const size_t slash = path.find_last_of('/');
  const std::string dir =
      slash == std::string::npos ? "." : (slash == 0 ? "/" : path.substr(0, slash));
  Fd dir_fd(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (dir_fd.get() >= 0) ::fsync(dir_fd.get());
  return absl::OkStatus();
}

}  // namespace streetsim
