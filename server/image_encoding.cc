#include "server/image_encoding.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "server/digest.h"

namespace streetsim::server {
namespace {

absl::Status Imencode(const char* ext, const cv::Mat& mat, const std::vector<int>& params,
                      std::string* out) {
  std::vector<uchar> buf;
  try {
    if (!cv::imencode(ext, mat, buf, params)) {
      return absl::InternalError(absl::StrCat("encoding ", ext, " failed"));
    }
  } catch (const cv::Exception& e) {
    return absl::InternalError(absl::StrCat("encoding ", ext, " failed: ", e.what()));
  }
  out->assign(reinterpret_cast<const char*>(buf.data()), buf.size());
  return absl::OkStatus();
}

void Finish(int width, int height, v1::Image* out) {
  out->set_width(width);
  out->set_height(height);
  out->set_digest(DigestOf(out->data()));
}

}  // namespace

absl::Status EncodeRgb(int width, int height, const std::vector<float>& rgb,
                       v1::ImageEncoding encoding, int jpeg_quality, v1::Image* out) {
  const size_t n = size_t(width) * height;
  std::string bytes(n * 3, '\0');
  // lround(v * 255) for v in [0, 1], written so that it vectorises: x - trunc(x) is exact in
  // float, so the comparison rounds half away from zero exactly as lround does.
  const float* src = rgb.data();
  uint8_t* dst = reinterpret_cast<uint8_t*>(bytes.data());
  for (size_t i = 0; i < n * 3; ++i) {
    const float v = src[i];
    float c = v > 1.0f ? 1.0f : v;
    c = c >= 0.0f ? c : 0.0f;                                      // NaN, -inf -> 0
    c = v == std::numeric_limits<float>::infinity() ? 0.0f : c;  // +inf -> 0, as every non-finite
    const float x = c * 255.0f;
    const int r = static_cast<int>(x);
    dst[i] = static_cast<uint8_t>(r + (x - static_cast<float>(r) >= 0.5f ? 1 : 0));
  }
  out->set_format(v1::IMAGE_FORMAT_RGB8);
  if (encoding == v1::IMAGE_ENCODING_UNSPECIFIED || encoding == v1::IMAGE_ENCODING_RAW) {
    out->set_encoding(v1::IMAGE_ENCODING_RAW);
    out->set_data(std::move(bytes));
  } else {
    cv::Mat rgb8(height, width, CV_8UC3, bytes.data());
    cv::Mat bgr;
    cv::cvtColor(rgb8, bgr, cv::COLOR_RGB2BGR);
    std::string* data = out->mutable_data();
    if (encoding == v1::IMAGE_ENCODING_PNG) {
      out->set_encoding(v1::IMAGE_ENCODING_PNG);
      if (absl::Status s = Imencode(".png", bgr, {cv::IMWRITE_PNG_COMPRESSION, 1}, data); !s.ok()) return s;
    } else if (encoding == v1::IMAGE_ENCODING_JPEG) {
      out->set_encoding(v1::IMAGE_ENCODING_JPEG);
      const int q = jpeg_quality == 0 ? 90 : jpeg_quality;
      if (absl::Status s = Imencode(".jpg", bgr, {cv::IMWRITE_JPEG_QUALITY, q}, data); !s.ok()) return s;
    } else {
      return absl::InvalidArgumentError("unknown rgb encoding");
    }
  }
  Finish(width, height, out);
  return absl::OkStatus();
}

absl::Status EncodeDepth(int width, int height, const std::vector<float>& depth,
                         v1::DepthEncoding encoding, v1::Image* out) {
  const size_t n = size_t(width) * height;
  if (encoding == v1::DEPTH_ENCODING_UNSPECIFIED || encoding == v1::DEPTH_ENCODING_F32) {
    out->set_format(v1::IMAGE_FORMAT_F32);
    out->set_encoding(v1::IMAGE_ENCODING_RAW);
    out->mutable_data()->assign(reinterpret_cast<const char*>(depth.data()), n * sizeof(float));
  } else if (encoding == v1::DEPTH_ENCODING_PNG16) {
    cv::Mat u16(height, width, CV_16UC1);
    for (size_t i = 0; i < n; ++i) {
      const double v = std::isfinite(depth[i]) ? depth[i] / kDepthPng16Scale : 0.0;
      u16.at<uint16_t>(static_cast<int>(i)) = static_cast<uint16_t>(std::clamp(std::lround(v), 0L, 65535L));
    }
    out->set_format(v1::IMAGE_FORMAT_U16);
    out->set_encoding(v1::IMAGE_ENCODING_PNG);
    out->set_scale(kDepthPng16Scale);
    if (absl::Status s = Imencode(".png", u16, {cv::IMWRITE_PNG_COMPRESSION, 1}, out->mutable_data()); !s.ok()) return s;
  } else {
    return absl::InvalidArgumentError("unknown depth encoding");
  }
  Finish(width, height, out);
  return absl::OkStatus();
}

absl::Status EncodeAlpha(int width, int height, const std::vector<float>& alpha,
                         v1::ImageEncoding encoding, v1::Image* out) {
  const size_t n = size_t(width) * height;
  if (encoding == v1::IMAGE_ENCODING_UNSPECIFIED || encoding == v1::IMAGE_ENCODING_RAW) {
    out->set_format(v1::IMAGE_FORMAT_F32);
    out->set_encoding(v1::IMAGE_ENCODING_RAW);
    out->mutable_data()->assign(reinterpret_cast<const char*>(alpha.data()), n * sizeof(float));
  } else if (encoding == v1::IMAGE_ENCODING_PNG) {
    cv::Mat u8(height, width, CV_8UC1);
    for (size_t i = 0; i < n; ++i) {
      const float v = std::isfinite(alpha[i]) ? std::clamp(alpha[i], 0.0f, 1.0f) : 0.0f;
      u8.at<uint8_t>(static_cast<int>(i)) = static_cast<uint8_t>(std::lround(v * 255.0f));
    }
    out->set_format(v1::IMAGE_FORMAT_U8);
    out->set_encoding(v1::IMAGE_ENCODING_PNG);
    if (absl::Status s = Imencode(".png", u8, {cv::IMWRITE_PNG_COMPRESSION, 1}, out->mutable_data()); !s.ok()) return s;
  } else {
    return absl::InvalidArgumentError("alpha encoding must be RAW or PNG");
  }
  Finish(width, height, out);
  return absl::OkStatus();
}

}  // namespace streetsim::server
