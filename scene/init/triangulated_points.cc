#include "scene/init/triangulated_points.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <map>
#include <unordered_map>
#include <utility>

#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "scene/log/undistort.h"
#include "scene/log/voxel_hash.h"

namespace streetsim {
namespace {

// One image's features, with what triangulation needs of its view.
struct ImageFeatures {
  Eigen::Isometry3d T_world_from_cam, T_cam_from_world;
  const CameraIntrinsics* k = nullptr;
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  cv::Mat rgb;  // undistorted, 8-bit RGB
};

absl::StatusOr<ImageFeatures> DetectFeatures(const DriveLog& log, int frame, const CameraObservation& obs,
                                             cv::ORB& orb) {
  ImageFeatures f;
  f.k = &log.cameras[obs.camera].intrinsics;
  f.T_world_from_cam = WorldFromCamera(log, log.frames[frame], obs);
  f.T_cam_from_world = f.T_world_from_cam.inverse();
  absl::StatusOr<cv::Mat> image = LoadImageRgb(obs.path);
  if (!image.ok()) return image.status();
  if (!f.k->IsPinhole()) {
    absl::StatusOr<cv::Mat> u = UndistortImage(*image, *f.k);
    if (!u.ok()) return u.status();
    *image = *u;
  }
  f.rgb = *image;
  cv::Mat gray;
  cv::cvtColor(f.rgb, gray, cv::COLOR_RGB2GRAY);
  orb.detectAndCompute(gray, cv::noArray(), f.keypoints, f.descriptors);
  return f;
}

Eigen::Vector3d RayInCamera(const CameraIntrinsics& k, const cv::Point2f& px) {
  return Eigen::Vector3d((px.x - k.cx) / k.fx, (px.y - k.cy) / k.fy, 1.0).normalized();
}

// Squared pixel distance between p (world) projected into the view and px; infinite behind it.
double ReprojectionErrorSq(const ImageFeatures& view, const Eigen::Vector3d& p_world, const cv::Point2f& px,
                           double* depth_m) {
  const Eigen::Vector3d c = view.T_cam_from_world * p_world;
  *depth_m = c.z();
  if (c.z() <= 0) return INFINITY;
  const double u = view.k->fx * c.x() / c.z() + view.k->cx, v = view.k->fy * c.y() / c.z() + view.k->cy;
  return (u - px.x) * (u - px.x) + (v - px.y) * (v - px.y);
}

Eigen::Vector3f PixelRgb(const cv::Mat& rgb, const cv::Point2f& px) {
  const int x = std::clamp(static_cast<int>(std::lround(px.x)), 0, rgb.cols - 1);
  const int y = std::clamp(static_cast<int>(std::lround(px.y)), 0, rgb.rows - 1);
  const cv::Vec3b c = rgb.at<cv::Vec3b>(y, x);
  return Eigen::Vector3f(c[0], c[1], c[2]) / 255.0f;
}

// Points of one image pair that pass every check, appended to out (position, colour).
void TriangulatePair(const ImageFeatures& a, const ImageFeatures& b, const TriangulationOptions& o,
                     std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3f>>* out, size_t* matches) {
  if (a.descriptors.empty() || b.descriptors.empty()) return;
  cv::BFMatcher matcher(cv::NORM_HAMMING);
  std::vector<std::vector<cv::DMatch>> knn;
  matcher.knnMatch(a.descriptors, b.descriptors, knn, 2);
  const double max_err_sq = o.max_reprojection_px * o.max_reprojection_px;
  const double min_cos = std::cos(o.min_angle_deg * M_PI / 180.0);
  const Eigen::Vector3d origin_a = a.T_world_from_cam.translation(), origin_b = b.T_world_from_cam.translation();
  for (const std::vector<cv::DMatch>& m : knn) {
    if (m.size() < 2 || m[0].distance >= o.ratio_test * m[1].distance) continue;
    ++*matches;
    const cv::Point2f& pa = a.keypoints[m[0].queryIdx].pt;
    const cv::Point2f& pb = b.keypoints[m[0].trainIdx].pt;
    const Eigen::Vector3d dir_a = a.T_world_from_cam.linear() * RayInCamera(*a.k, pa);
    const Eigen::Vector3d dir_b = b.T_world_from_cam.linear() * RayInCamera(*b.k, pb);
    Eigen::Vector3d p;
    if (!TriangulateMidpoint(origin_a, dir_a, origin_b, dir_b, &p)) continue;
    const double cos_angle = (p - origin_a).normalized().dot((p - origin_b).normalized());
    if (!(cos_angle <= min_cos)) continue;  // too little parallax: depth is a guess
    double depth_a = 0, depth_b = 0;
    if (ReprojectionErrorSq(a, p, pa, &depth_a) > max_err_sq || ReprojectionErrorSq(b, p, pb, &depth_b) > max_err_sq) {
      continue;
    }
    if (std::min(depth_a, depth_b) < o.min_depth_m || std::max(depth_a, depth_b) > o.max_depth_m) continue;
    out->emplace_back(p, 0.5f * (PixelRgb(a.rgb, pa) + PixelRgb(b.rgb, pb)));
  }
}

// fn(0..n-1) on the machine's threads (STREETSIM_THREADS if set); each index once.
void RunAll(size_t n, const std::function<void(size_t)>& fn) {
  ThreadPool pool;
  pool.ParallelFor(static_cast<int64_t>(n), 1, [&](int64_t begin, int64_t end, int) {
    for (int64_t k = begin; k < end; ++k) fn(static_cast<size_t>(k));
  });
}

// One point per voxel, the mean of what fell into it: the same corner seen in many pairs becomes
// one Gaussian, not a cluster, and memory follows the scene, not the log's length.
struct VoxelMeans {
  explicit VoxelMeans(double voxel_m) : inv_voxel(1.0 / voxel_m) {}
  void Add(const Eigen::Vector3d& p, const Eigen::Vector3f& rgb) {
    auto [it, fresh] = slot.emplace(VoxelOf(p, inv_voxel), sum.size());
    if (fresh) {
      sum.push_back(Eigen::Vector3d::Zero());
      rgb_sum.push_back(Eigen::Vector3f::Zero());
      count.push_back(0);
    }
    sum[it->second] += p;
    rgb_sum[it->second] += rgb;
    ++count[it->second];
  }
  double inv_voxel;
  std::unordered_map<VoxelKey, size_t, VoxelKeyHash> slot;
  std::vector<Eigen::Vector3d> sum;
  std::vector<Eigen::Vector3f> rgb_sum;
  std::vector<int> count;
};

}  // namespace

bool TriangulateMidpoint(const Eigen::Vector3d& origin_a, const Eigen::Vector3d& dir_a, const Eigen::Vector3d& origin_b,
                         const Eigen::Vector3d& dir_b, Eigen::Vector3d* point) {
  // Minimise |oa + s da - ob - t db|^2 over s, t.
  const Eigen::Vector3d w = origin_a - origin_b;
  const double aa = dir_a.dot(dir_a), ab = dir_a.dot(dir_b), bb = dir_b.dot(dir_b);
  const double aw = dir_a.dot(w), bw = dir_b.dot(w);
  const double det = aa * bb - ab * ab;
  if (!(det > 1e-12 * aa * bb)) return false;
  const double s = (ab * bw - bb * aw) / det, t = (aa * bw - ab * aw) / det;
  *point = 0.5 * ((origin_a + s * dir_a) + (origin_b + t * dir_b));
  return std::isfinite(point->x()) && std::isfinite(point->y()) && std::isfinite(point->z());
}

absl::StatusOr<TriangulatedPoints> TriangulateWithKnownPoses(const DriveLog& log, const TriangulationOptions& options) {
  const std::vector<int> frames = options.frames.Select(log);
  if (frames.empty()) return absl::InvalidArgumentError("no frames selected");
  const int max_gap = options.frame_gaps.empty() ? 0 : *std::max_element(options.frame_gaps.begin(), options.frame_gaps.end());
  TriangulatedPoints result;
  VoxelMeans merged(options.voxel_m);
  // A window of the last max_gap + 1 frames' images, keyed by (position in the selection, camera):
  // memory follows the rig, not the log's length.
  std::map<std::pair<int, int>, ImageFeatures> window;
  for (int i = 0; i < static_cast<int>(frames.size()); ++i) {
    const std::vector<CameraObservation>& observations = log.frames[frames[i]].cameras;
    std::vector<absl::StatusOr<ImageFeatures>> detected(observations.size(), absl::UnknownError("not run"));
    RunAll(observations.size(), [&](size_t c) {
      cv::Ptr<cv::ORB> orb = cv::ORB::create(options.features_per_image);
      detected[c] = DetectFeatures(log, frames[i], observations[c], *orb);
    });
    for (size_t c = 0; c < observations.size(); ++c) {
      if (!detected[c].ok()) return detected[c].status();
      window.emplace(std::make_pair(i, observations[c].camera), *std::move(detected[c]));
    }
    // This frame's pairs: each camera against itself some frames before (motion parallax) and
    // against the rig's other cameras at this frame (a stereo pair's baseline), each pair once.
    std::vector<std::pair<const ImageFeatures*, const ImageFeatures*>> pairs;
    for (auto b = window.lower_bound({i, -1}); b != window.end(); ++b) {
      for (int gap : options.frame_gaps) {
        auto a = window.find({i - gap, b->first.second});
        if (gap > 0 && a != window.end()) pairs.emplace_back(&a->second, &b->second);
      }
      for (auto a = window.lower_bound({i, -1}); a != b; ++a) pairs.emplace_back(&a->second, &b->second);
    }
    std::vector<std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3f>>> found(pairs.size());
    std::vector<size_t> matches(pairs.size(), 0);
    RunAll(pairs.size(), [&](size_t p) {
      TriangulatePair(*pairs[p].first, *pairs[p].second, options, &found[p], &matches[p]);
    });
    for (size_t p = 0; p < pairs.size(); ++p) {  // in pair order: the result does not depend on threads
      ++result.image_pairs;
      result.matches += matches[p];
      result.triangulated += found[p].size();
      for (const auto& [x, rgb] : found[p]) merged.Add(x, rgb);
    }
    window.erase(window.begin(), window.lower_bound({i - max_gap, -1}));
  }
  for (size_t v = 0; v < merged.sum.size(); ++v) {
    result.points.push_back((merged.sum[v] / merged.count[v]).cast<float>());
    result.rgb.push_back(merged.rgb_sum[v] / static_cast<float>(merged.count[v]));
  }
  return result;
}

}  // namespace streetsim
