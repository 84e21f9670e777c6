#include "scene/train/parts/appearance.h"

#include <algorithm>

#include <opencv2/core.hpp>

namespace streetsim::train {

void Appearance::InitSky(const std::vector<View>& views, TrainState* st) const {
  if (!sky_) return;
  double acc[3] = {0, 0, 0};
  size_t cnt = 0;
  for (const View& v : views) {
    for (int y = 0; y < std::max(1, v.rgb8.rows / 10); ++y)
      for (int x = 0; x < v.rgb8.cols; ++x, ++cnt)
        for (int c = 0; c < 3; ++c) acc[c] += v.rgb8.at<cv::Vec3b>(y, x)[c] / 255.0;
  }
  for (int c = 0; c < 3; ++c) st->sky[c] = static_cast<float>(acc[c] / std::max<size_t>(cnt, 1));
}

Eigen::Vector3f Appearance::Background(const TrainState& st) const {
  return sky_ ? Eigen::Vector3f(st.sky[0], st.sky[1], st.sky[2]) : Eigen::Vector3f::Zero();
}

const std::vector<float>& Appearance::Apply(const TrainState& st, int view, const RenderOutput& out) {
  if (!exposure_) return out.rgb;
  const float* E = &st.exposure[static_cast<size_t>(view) * 12];
  const size_t pixels = out.rgb.size() / 3;
  exposed_.resize(pixels * 3);
  for (size_t p = 0; p < pixels; ++p)
    for (int r = 0; r < 3; ++r)
      exposed_[p * 3 + r] = E[r * 4] * out.rgb[p * 3] + E[r * 4 + 1] * out.rgb[p * 3 + 1] +
                            E[r * 4 + 2] * out.rgb[p * 3 + 2] + E[r * 4 + 3];
  return exposed_;
}

const std::vector<float>& Appearance::Backward(TrainState* st, int view, const RenderOutput& out,
                                               const std::vector<float>& d_image) {
  const std::vector<float>* d_render = &d_image;
  const size_t pixels = out.rgb.size() / 3;
  if (exposure_) {
    const size_t at = static_cast<size_t>(view) * 12;
    const float* E = &st->exposure[at];
    d_render_.assign(pixels * 3, 0.0f);
    float dE[12] = {0};
    for (size_t p = 0; p < pixels; ++p) {
      for (int r = 0; r < 3; ++r) {
        const float g = d_image[p * 3 + r];
        for (int c = 0; c < 3; ++c) {
          dE[r * 4 + c] += g * out.rgb[p * 3 + c];
          d_render_[p * 3 + c] += E[r * 4 + c] * g;
        }
        dE[r * 4 + 3] += g;
      }
    }
    AdamStepSmall(&st->exposure[at], dE, &st->exposure_m[at], &st->exposure_v[at], 12, h_.exposure_lr,
                  st->aux_step + 1);
    d_render = &d_render_;
  }
  if (sky_) {
    float dsky[3] = {0, 0, 0};
    for (size_t p = 0; p < pixels; ++p) {
      const float T = 1.0f - out.alpha[p];
      for (int c = 0; c < 3; ++c) dsky[c] += (*d_render)[p * 3 + c] * T;
    }
    AdamStepSmall(st->sky, dsky, st->sky_m, st->sky_v, 3, h_.sky_lr, st->aux_step + 1);
  }
  st->aux_step += 1;
  return *d_render;
}

}  // namespace streetsim::train
