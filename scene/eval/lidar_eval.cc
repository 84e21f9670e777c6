#include "scene/eval/lidar_eval.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_renderer.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/log/kdtree.h"

namespace streetsim::train {
namespace {

// Mean distance from (a strided subset of) `queries` to their nearest point in `tree`. Distances
// land in one slot per query and are summed in order, so the result does not depend on threads.
double MeanNearestM(const std::vector<Eigen::Vector3f>& queries, const KdTree3& tree, size_t max_queries,
                    ThreadPool* pool) {
  const size_t stride = std::max<size_t>(1, (queries.size() + max_queries - 1) / std::max<size_t>(1, max_queries));
  const size_t n = (queries.size() + stride - 1) / stride;
  std::vector<double> dist(n, -1);
  auto run = [&](int64_t begin, int64_t end, int) {
    for (int64_t k = begin; k < end; ++k) {
      float d2 = 0;
      if (tree.Nearest(queries[k * stride], std::numeric_limits<float>::infinity(), &d2) >= 0) {
        dist[k] = std::sqrt(static_cast<double>(d2));
      }
    }
  };
  if (pool) {
    pool->ParallelFor(static_cast<int64_t>(n), 256, run);
  } else {
    run(0, static_cast<int64_t>(n), 0);
  }
  double sum = 0;
  size_t found = 0;
  for (double d : dist) {
    if (d >= 0) sum += d, ++found;
  }
  return found ? sum / found : -1;
}

std::vector<Eigen::Vector3f> RangeImagePoints(const LidarModel& model, const std::vector<float>& range) {
  std::vector<Eigen::Vector3f> pts;
  const int W = model.columns;
  for (int b = 0; b < model.beams(); ++b) {
    for (int c = 0; c < W; ++c) {
      const float r = range[static_cast<size_t>(b) * W + c];
      if (r > 0) pts.push_back((model.RayDirection(b, c) * r).cast<float>());
    }
  }
  return pts;
}

size_t PlyTypeSize(const std::string& t) {
  if (t == "char" || t == "uchar" || t == "int8" || t == "uint8") return 1;
  if (t == "short" || t == "ushort" || t == "int16" || t == "uint16") return 2;
  if (t == "int" || t == "uint" || t == "float" || t == "int32" || t == "uint32" || t == "float32") return 4;
  if (t == "double" || t == "float64") return 8;
  return 0;
}

}  // namespace

double ChamferDistanceM(const std::vector<Eigen::Vector3f>& a, const std::vector<Eigen::Vector3f>& b,
                        size_t max_queries, ThreadPool* pool) {
  if (a.empty() || b.empty()) return -1;
  const KdTree3 tree_a(&a), tree_b(&b);
  return 0.5 * (MeanNearestM(a, tree_b, max_queries, pool) + MeanNearestM(b, tree_a, max_queries, pool));
}

LidarFrameMetrics CompareRangeImages(const LidarModel& model, const std::vector<float>& rendered_range,
                                     const std::vector<float>& rendered_intensity,
                                     const std::vector<float>& real_range,
                                     const std::vector<float>& real_intensity, size_t chamfer_max_queries,
                                     ThreadPool* pool) {
  LidarFrameMetrics m;
  const size_t P = rendered_range.size();
  size_t same_drop = 0;
  double intensity_sq = 0;
  std::vector<float> abs_err;
  for (size_t p = 0; p < P; ++p) {
    const bool ret_r = rendered_range[p] > 0, ret_t = real_range[p] > 0;
    same_drop += ret_r == ret_t;
    if (ret_r && ret_t) {
      abs_err.push_back(std::fabs(rendered_range[p] - real_range[p]));
      const double di = static_cast<double>(rendered_intensity[p]) - real_intensity[p];
      intensity_sq += di * di;
    }
  }
  m.rays = abs_err.size();
  if (P > 0) m.drop_accuracy = static_cast<double>(same_drop) / P;
  if (!abs_err.empty()) {
    auto mid = abs_err.begin() + abs_err.size() / 2;
    std::nth_element(abs_err.begin(), mid, abs_err.end());
    m.range_median_abs_m = *mid;
    m.intensity_rmse = std::sqrt(intensity_sq / abs_err.size());
  }
  m.chamfer_m = ChamferDistanceM(RangeImagePoints(model, rendered_range), RangeImagePoints(model, real_range),
                                 chamfer_max_queries, pool);
  return m;
}

Eigen::Isometry3d LogEgoPoseAt(const DriveLog& log, int64_t time_us) {
  const std::vector<Frame>& f = log.frames;
  if (time_us <= f.front().time_us) return f.front().T_world_from_ego;
  if (time_us >= f.back().time_us) return f.back().T_world_from_ego;
  const auto it = std::upper_bound(f.begin(), f.end(), time_us,
                                   [](int64_t t, const Frame& frame) { return t < frame.time_us; });
  const Frame& b = *it;
  const Frame& a = *(it - 1);
  const double s = static_cast<double>(time_us - a.time_us) / static_cast<double>(b.time_us - a.time_us);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Quaterniond(a.T_world_from_ego.linear())
                   .slerp(s, Eigen::Quaterniond(b.T_world_from_ego.linear()))
                   .normalized()
                   .toRotationMatrix();
  T.translation() = (1 - s) * a.T_world_from_ego.translation() + s * b.T_world_from_ego.translation();
  return T;
}

absl::StatusOr<LidarEvalResult> EvaluateLidar(const DriveLog& log, const std::vector<int>& frames,
                                              const GaussianStore& scene, const std::vector<float>* reflectance,
                                              const LidarEvalOptions& options) {
  return EvaluateLidar(log, frames, scene, reflectance, options, StoreAtTime());
}

absl::StatusOr<LidarEvalResult> EvaluateLidar(const DriveLog& log, const std::vector<int>& frames,
                                              const GaussianStore& scene, const std::vector<float>* reflectance,
                                              const LidarEvalOptions& options, const StoreAtTime& store_at) {
  if (reflectance != nullptr && reflectance->size() != scene.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat(reflectance->size(), " reflectance values for ", scene.size(), " Gaussians"));
  }
  LidarRenderer renderer;
  if (!store_at) {
    if (absl::Status s = renderer.Upload(scene); !s.ok()) return s;
  }
  ThreadPool pool;
  LidarRenderOptions ropt;
  ropt.reflectance = reflectance;
  ropt.return_alpha_threshold = options.return_alpha_threshold;
  LidarEvalResult result;
  for (int f : frames) {
    if (f < 0 || f >= static_cast<int>(log.frames.size())) {
      return absl::InvalidArgumentError(absl::StrCat("frame ", f, " is not in the log"));
    }
    const Frame& frame = log.frames[f];
    if (frame.lidars.empty()) continue;
    const LidarObservation& obs = frame.lidars[0];
    if (store_at) {
      absl::StatusOr<GaussianStore> at = store_at(frame.time_us);
      if (!at.ok()) return at.status();
      if (at->size() != scene.size()) return absl::InternalError("the deformed scene changed the Gaussian count");
      if (absl::Status s = renderer.Upload(*at); !s.ok()) return s;
    }
    LidarModel model = KittiHdl64e(options.columns);
    model.T_ego_from_lidar = log.lidars[obs.lidar].T_ego_from_lidar;
    absl::StatusOr<LidarScan> scan = LoadLidarScan(obs.path);
    if (!scan.ok()) return scan.status();
    LidarSweepPose sweep = LidarSweepPose::Static(frame.T_world_from_ego * model.T_ego_from_lidar);
    ropt.sweep_start_us = obs.time_us;
    if (options.rolling_sweep) {
      const int64_t half_us = model.sweep_duration_us / 2;
      ropt.sweep_start_us = obs.time_us - half_us;
      sweep.T_world_from_lidar_start = LogEgoPoseAt(log, obs.time_us - half_us) * model.T_ego_from_lidar;
      sweep.T_world_from_lidar_end =
          LogEgoPoseAt(log, obs.time_us - half_us + model.sweep_duration_us) * model.T_ego_from_lidar;
    }
    LidarRenderOutput out;
    if (absl::Status s = renderer.Render(model, sweep, ropt, &out); !s.ok()) return s;
    std::vector<float> real_range, real_intensity;
    BinPointsToRangeImage(model, scan->points, &scan->reflectance, &real_range, &real_intensity);
    LidarFrameMetrics m = CompareRangeImages(model, out.range, out.intensity, real_range, real_intensity,
                                             options.chamfer_max_queries, &pool);
    m.frame = f;
    result.frames.push_back(m);
  }
  // Mean of each metric over the frames where it is defined.
  auto mean_of = [&](double LidarFrameMetrics::*field) {
    double sum = 0;
    int n = 0;
    for (const LidarFrameMetrics& m : result.frames) {
      if (m.*field >= 0) sum += m.*field, ++n;
    }
    return n ? sum / n : -1.0;
  };
  result.mean.range_median_abs_m = mean_of(&LidarFrameMetrics::range_median_abs_m);
  result.mean.chamfer_m = mean_of(&LidarFrameMetrics::chamfer_m);
  result.mean.drop_accuracy = mean_of(&LidarFrameMetrics::drop_accuracy);
  result.mean.intensity_rmse = mean_of(&LidarFrameMetrics::intensity_rmse);
  for (const LidarFrameMetrics& m : result.frames) result.mean.rays += m.rays;
  return result;
}

absl::StatusOr<std::optional<std::vector<float>>> ReadPlyReflectance(const std::string& path,
                                                                     size_t expected_count) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return absl::NotFoundError(absl::StrCat(path, ": cannot open"));
  std::string line;
  bool in_vertex = false, binary_le = false;
  size_t count = 0, row_bytes = 0, offset = 0, value_size = 0;
  bool found = false;
  for (int lines = 0; std::getline(f, line); ++lines) {
    if (lines > 10000) return absl::InvalidArgumentError(absl::StrCat(path, ": PLY header too long"));
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ls(line);
    std::string word;
    ls >> word;
    if (word == "end_header") break;
    if (word == "format") {
      std::string fmt;
      ls >> fmt;
      binary_le = fmt == "binary_little_endian";
    } else if (word == "element") {
      std::string name;
      ls >> name;
      in_vertex = name == "vertex";
      if (in_vertex) ls >> count;
    } else if (word == "property" && in_vertex) {
      std::string type, name;
      ls >> type >> name;
      const size_t size = PlyTypeSize(type);
      if (size == 0) return std::optional<std::vector<float>>();  // lists etc.: not ours to read
      if (name == "reflectance") {
        if (type != "float" && type != "float32" && type != "double" && type != "float64") {
          return absl::InvalidArgumentError(absl::StrCat(path, ": reflectance must be float or double"));
        }
        found = true;
        offset = row_bytes;
        value_size = size;
      }
      row_bytes += size;
    }
  }
  if (!found) return std::optional<std::vector<float>>();
  if (!binary_le) return absl::InvalidArgumentError(absl::StrCat(path, ": reflectance needs binary_little_endian"));
  if (count != expected_count) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": ", count, " vertices with reflectance, expected ", expected_count));
  }
  std::vector<float> out(count);
  std::vector<char> row(row_bytes);
  for (size_t i = 0; i < count; ++i) {
    if (!f.read(row.data(), static_cast<std::streamsize>(row_bytes))) {
      return absl::DataLossError(absl::StrCat(path, ": truncated at vertex ", i));
    }
    if (value_size == 4) {
      std::memcpy(&out[i], row.data() + offset, 4);
    } else {
      double d;
      std::memcpy(&d, row.data() + offset, 8);
      out[i] = static_cast<float>(d);
    }
    if (!std::isfinite(out[i])) return absl::InvalidArgumentError(absl::StrCat(path, ": reflectance ", i, " not finite"));
  }
  return std::optional<std::vector<float>>(std::move(out));
}

}  // namespace streetsim::train
