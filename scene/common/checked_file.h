// The pieces of streetsim's versioned binary files (field.bin, field_ext.bin, checkpoint.bin):
// a byte writer, a bounds-checked reader, the FNV-1a checksum the field files end with, and the
// write-to-temp-then-rename that keeps a killed run from leaving half a file behind. Each file
// format keeps its own magic, version and layout; only these mechanics are shared.
// Header-only so that every scene library can use it without a link dependency.
#pragma once

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace streetsim::checked_file {

// 64-bit FNV-1a over 8-byte words (bytes for the tail): catches truncation and bit rot, fast
// enough for 140 MiB of planes.
inline uint64_t Checksum(const char* data, size_t n) {
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

// Appends values in host byte order (files are read back on the machines that write them).
class Writer {
 public:
  template <typename T>
  void Pod(const T& v) { Raw(&v, sizeof(T)); }
  void Raw(const void* p, size_t n) { buf.append(static_cast<const char*>(p), n); }
  std::string buf;
};

// Reads from [data, data + n); every read fails (false, nothing consumed) rather than run past n.
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

// Writes `bytes` to path + ".tmp", then renames it over `path`: readers see the old file or the
// whole new one, never a torn one.
inline absl::Status WriteAtomically(const std::string& path, const std::string& bytes) {
  const std::string tmp = path + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
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

// A small text file's whole content (a config, a record): NotFound when it is not a regular file,
// OutOfRange when it is larger than `max_bytes` (read before its content, so that a huge or
// hostile file costs nothing), DataLoss when it cannot be read. Messages name the path; callers
// map the codes onto their own (a flag's file is InvalidArgument, a run's record DataLoss).
inline absl::StatusOr<std::string> ReadBounded(const std::string& path, std::uintmax_t max_bytes) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  const std::uintmax_t size = std::filesystem::file_size(path, ec);
  if (ec) return absl::DataLossError(absl::StrCat(path, ": ", ec.message()));
  if (size > max_bytes) return absl::OutOfRangeError(absl::StrCat(path, ": larger than ", max_bytes, " bytes"));
  std::ifstream in(path, std::ios::binary);
  std::string text(static_cast<size_t>(size), '\0');
  in.read(text.data(), static_cast<std::streamsize>(size));
  if (!in && !in.eof()) return absl::DataLossError(absl::StrCat(path, ": cannot be read"));
  text.resize(static_cast<size_t>(in.gcount()));
  return text;
}

}  // namespace streetsim::checked_file
