#include "scene/log/text_util.h"

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <algorithm>

#include <Eigen/SVD>

#include "absl/strings/str_cat.h"

namespace streetsim {
namespace {

std::string LinePrefix(const std::string& path, int line_number) {
  return line_number > 0 ? absl::StrCat(path, ": line ", line_number, ": ") : absl::StrCat(path, ": ");
}

}  // namespace

absl::StatusOr<std::string> ReadTextFile(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  if (std::filesystem::is_directory(path, ec)) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": is a directory, expected a file"));
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot open"));
  std::ostringstream buffer;
  buffer << in.rdbuf();
  if (in.bad()) return absl::DataLossError(absl::StrCat(path, ": read error"));
  return buffer.str();
}

absl::StatusOr<std::vector<std::string>> ReadLines(const std::string& path) {
  absl::StatusOr<std::string> text = ReadTextFile(path);
  if (!text.ok()) return text.status();
  std::vector<std::string> lines;
  size_t start = 0;
  while (start < text->size()) {
    size_t end = text->find('\n', start);
    if (end == std::string::npos) end = text->size();
    std::string line = text->substr(start, end - start);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    lines.push_back(std::move(line));
    start = end + 1;
  }
  return lines;
}

absl::StatusOr<std::vector<double>> ParseNumbers(const std::string& text, const std::string& path,
                                                 int line_number, int expected) {
  std::vector<double> values;
  const char* p = text.c_str();
  while (true) {
    while (*p == ' ' || *p == '\t' || *p == '\r') ++p;
    if (*p == '\0') break;
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(p, &end);
    // strtod stops at the first non-number character; a token must end at whitespace.
    if (end == p || (*end != '\0' && *end != ' ' && *end != '\t' && *end != '\r')) {
      const char* tok_end = p;
      while (*tok_end && *tok_end != ' ' && *tok_end != '\t') ++tok_end;
      return absl::InvalidArgumentError(absl::StrCat(LinePrefix(path, line_number), "'",
                                                     std::string(p, tok_end), "' is not a number"));
    }
    values.push_back(v);
    p = end;
  }
  if (expected >= 0 && static_cast<int>(values.size()) != expected) {
    return absl::InvalidArgumentError(absl::StrCat(LinePrefix(path, line_number), "expected ",
                                                   expected, " values, got ", values.size()));
  }
  return values;
}

bool IsBlankOrComment(const std::string& line) {
  for (char c : line) {
    if (c == '#') return true;
    if (c != ' ' && c != '\t' && c != '\r') return false;
  }
  return true;
}

absl::StatusOr<Eigen::Isometry3d> RigidFromRowMajor(const double* rotation9,
                                                    const Eigen::Vector3d& translation,
                                                    const std::string& where, double tolerance) {
  Eigen::Matrix3d r;
  for (int i = 0; i < 9; ++i) {
    if (!std::isfinite(rotation9[i])) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite rotation"));
    }
    r(i / 3, i % 3) = rotation9[i];
  }
  if (!translation.allFinite()) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite translation"));
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(r, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d nearest = svd.matrixU() * svd.matrixV().transpose();
  if (nearest.determinant() < 0) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": rotation is a reflection (det < 0)"));
  }
  const double off = (nearest - r).norm();
  if (off > tolerance) {
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": not a rotation matrix (", off, " from the nearest rotation)"));
  }
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = nearest;
  t.translation() = translation;
  return t;
}

absl::StatusOr<Eigen::Isometry3d> RigidFrom3x4(const std::vector<double>& v, const std::string& where,
                                               double tolerance) {
  if (v.size() != 12) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": expected 12 values, got ", v.size()));
  }
  const double r[9] = {v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]};
  return RigidFromRowMajor(r, Eigen::Vector3d(v[3], v[7], v[11]), where, tolerance);
}

absl::StatusOr<std::vector<double>> CalibFile::Get(const std::string& key, int count) const {
  auto it = entries.find(key);
  if (it == entries.end()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": missing calibration entry '", key, "'"));
  }
  const CalibEntry& e = it->second;
  if (static_cast<int>(e.numbers.size()) != count) {
    return absl::InvalidArgumentError(absl::StrCat(LinePrefix(path, e.line), key, ": expected ",
                                                   count, " values, got ", e.numbers.size()));
  }
  for (double v : e.numbers) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(LinePrefix(path, e.line), key, ": non-finite value"));
    }
  }
  return e.numbers;
}

absl::StatusOr<CalibFile> ReadCalibFile(const std::string& path) {
  absl::StatusOr<std::vector<std::string>> lines = ReadLines(path);
  if (!lines.ok()) return lines.status();
  CalibFile calib;
  calib.path = path;
  for (size_t i = 0; i < lines->size(); ++i) {
    const std::string& line = (*lines)[i];
    if (IsBlankOrComment(line)) continue;
    const size_t colon = line.find(':');
    if (colon == std::string::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat(LinePrefix(path, i + 1), "expected 'key: values'"));
    }
    const std::string key = line.substr(0, colon);
    if (key == "calib_time") continue;  // a date, not numbers
    absl::StatusOr<std::vector<double>> numbers =
        ParseNumbers(line.substr(colon + 1), path, static_cast<int>(i + 1));
    if (!numbers.ok()) return numbers.status();
    calib.entries[key] = CalibEntry{*std::move(numbers), static_cast<int>(i + 1)};
  }
  return calib;
}

absl::StatusOr<int64_t> ParseKittiTimestamp(const std::string& text, const std::string& path,
                                            int line_number) {
  int year, month, day, hour, minute;
  int second;
  int consumed = 0;
  const auto bad = [&]() {
    return absl::InvalidArgumentError(absl::StrCat(
        LinePrefix(path, line_number), "'", text, "' is not a timestamp YYYY-MM-DD HH:MM:SS.fffffffff"));
  };
  if (std::sscanf(text.c_str(), "%4d-%2d-%2d %2d:%2d:%2d%n", &year, &month, &day, &hour, &minute,
                  &second, &consumed) != 6) {
    return bad();
  }
  int64_t micros = 0;
  const char* rest = text.c_str() + consumed;
  if (*rest == '.') {
    ++rest;
    int digits = 0;
    while (*rest >= '0' && *rest <= '9') {
      if (digits < 6) micros = micros * 10 + (*rest - '0');
      ++digits;
      ++rest;
    }
    if (digits == 0) return bad();
    for (int d = digits; d < 6; ++d) micros *= 10;
  }
  while (*rest == ' ' || *rest == '\r' || *rest == '\t') ++rest;
  if (*rest != '\0') return bad();
  if (month < 1 || month > 12 || day < 1 || day > 31 || hour > 23 || minute > 59 || second > 60) {
    return bad();
  }
  const std::chrono::year_month_day ymd{std::chrono::year{year}, std::chrono::month(month),
                                        std::chrono::day(day)};
  if (!ymd.ok()) return bad();
  const int64_t days = std::chrono::sys_days(ymd).time_since_epoch().count();
  return ((days * 24 + hour) * 60 + minute) * 60'000'000LL + second * 1'000'000LL + micros;
}

}  // namespace streetsim

namespace streetsim {

absl::StatusOr<std::vector<std::string>> ListNumberedFiles(const std::string& dir,
                                                           const std::string& extension,
                                                           std::vector<int>* indices) {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat(dir, ": no such directory"));
  }
  std::vector<std::pair<int, std::string>> found;
  for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
    if (!entry.is_regular_file()) continue;
    const std::filesystem::path& p = entry.path();
    if (p.extension() != extension) continue;
    const std::string stem = p.stem().string();
    if (stem.empty() || stem.size() > 10) continue;
    bool digits = true;
    for (char c : stem) digits = digits && c >= '0' && c <= '9';
    if (!digits) continue;
    const long long index = std::stoll(stem);
    if (index > 1'000'000'000) continue;
    found.emplace_back(static_cast<int>(index), p.string());
  }
  if (ec) return absl::PermissionDeniedError(absl::StrCat(dir, ": cannot list: ", ec.message()));
  std::sort(found.begin(), found.end());
  std::vector<std::string> paths;
  if (indices) indices->clear();
  for (auto& [index, path] : found) {
    if (indices) indices->push_back(index);
    paths.push_back(std::move(path));
  }
  return paths;
}

}  // namespace streetsim
