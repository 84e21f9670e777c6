#include "server/lidar_request.h"

#include <cmath>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "server/digest.h"
#include "server/proto_convert.h"

namespace streetsim::server {
namespace {

constexpr int kMaxColumns = 65536;

template <typename T>
std::string Bytes(const std::vector<T>& v) {
  std::string s(v.size() * sizeof(T), '\0');
  if (!v.empty()) std::memcpy(s.data(), v.data(), s.size());
  return s;
}

absl::StatusOr<double> Range(double v, double dflt, const char* field) {
  if (!std::isfinite(v) || v < 0) {
    return absl::InvalidArgumentError(absl::StrCat("lidar.", field, " must be a finite number >= 0"));
  }
  return v == 0 ? dflt : v;
}

}  // namespace

absl::StatusOr<LidarJob> ResolveLidar(const v1::LidarRequest& req, const SceneManifest& manifest) {
  if (req.columns() < 0 || req.columns() > kMaxColumns) {
    return absl::InvalidArgumentError(
        absl::StrCat("lidar.columns ", req.columns(), " is outside 1..", kMaxColumns, " (0 = 2048)"));
  }
  LidarJob job;
  job.model = KittiHdl64e(req.columns() == 0 ? 2048 : req.columns());
  const RigLidar rig = manifest.lidars.empty() ? RigLidar{} : manifest.lidars.front();
  job.sensor_id = rig.sensor_id;
  job.model.T_ego_from_lidar = rig.T_ego_from_lidar;
  job.model.sweep_duration_us = rig.sweep_duration_us;
  absl::StatusOr<double> min_m = Range(req.min_range_m(), job.model.min_range_m, "min_range_m");
  if (!min_m.ok()) return min_m.status();
  absl::StatusOr<double> max_m = Range(req.max_range_m(), job.model.max_range_m, "max_range_m");
  if (!max_m.ok()) return max_m.status();
  if (*max_m > 1e6) return absl::InvalidArgumentError("lidar.max_range_m must be at most 1e6");
  if (*min_m >= *max_m) {
    return absl::InvalidArgumentError(
        absl::StrCat("lidar.min_range_m (", *min_m, ") must be below max_range_m (", *max_m, ")"));
  }
  job.model.min_range_m = *min_m;
  job.model.max_range_m = *max_m;
  const double threshold = req.return_alpha_threshold();
  if (!std::isfinite(threshold) || threshold < 0 || threshold > 1) {
    return absl::InvalidArgumentError("lidar.return_alpha_threshold must be in (0, 1] (0 = 0.5)");
  }
  job.options.return_alpha_threshold = threshold == 0 ? 0.5f : static_cast<float>(threshold);
  job.options.sample_drop = req.sample_drop();
  job.options.seed = req.drop_seed();
  job.options.want_points = req.want_points();
  if (!v1::LidarPointFrame_IsValid(req.points_frame())) {
    return absl::InvalidArgumentError("lidar.points_frame: unknown value");
  }
  job.points_frame = req.points_frame() == v1::LIDAR_POINT_FRAME_EGO ? v1::LIDAR_POINT_FRAME_EGO
                                                                      : v1::LIDAR_POINT_FRAME_SENSOR;
  job.options.point_frame = job.points_frame == v1::LIDAR_POINT_FRAME_EGO ? LidarRenderOptions::PointFrame::kEgo
                                                                          : LidarRenderOptions::PointFrame::kSensor;
  if (req.has_t_ego_from_lidar()) {
    absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(req.t_ego_from_lidar(), "lidar.T_ego_from_lidar");
    if (!T.ok()) return T.status();
    job.model.T_ego_from_lidar = *T;
  }
  if (absl::Status s = job.model.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("lidar: ", s.message()));
  }
  return job;
}

void PlaceLidar(const Eigen::Isometry3d& T_world_from_ego_start, const Eigen::Isometry3d& T_world_from_ego_end,
                int64_t time_us, LidarJob* job) {
  job->sweep.T_world_from_lidar_start = T_world_from_ego_start * job->model.T_ego_from_lidar;
  job->sweep.T_world_from_lidar_end = T_world_from_ego_end * job->model.T_ego_from_lidar;
  job->options.sweep_start_us = time_us;
}

void PlaceLidarAt(const Eigen::Isometry3d& T_world_from_lidar, int64_t time_us, LidarJob* job) {
  job->sweep = LidarSweepPose::Static(T_world_from_lidar);
  job->options.sweep_start_us = time_us;
}

void LidarResultToProto(const LidarJob& job, const LidarRenderOutput& out, v1::LidarResult* r) {
  r->set_sensor_id(job.sensor_id);
  r->set_beams(out.beams);
  r->set_columns(out.columns);
  for (double e : job.model.beam_elevation_deg) r->add_beam_elevation_deg(e);
  r->set_min_range_m(job.model.min_range_m);
  r->set_max_range_m(job.model.max_range_m);
  PoseToProto(job.sweep.T_world_from_lidar_start, r->mutable_t_world_from_lidar());
  PoseToProto(job.sweep.T_world_from_lidar_end, r->mutable_t_world_from_lidar_end());
  PoseToProto(job.model.T_ego_from_lidar, r->mutable_t_ego_from_lidar());
  r->set_rolling_sweep(!job.sweep.is_static());
  r->set_sweep_start_us(job.options.sweep_start_us);
  r->set_sweep_duration_us(job.model.sweep_duration_us);
  r->set_range(Bytes(out.range));
  r->set_intensity(Bytes(out.intensity));
  r->set_alpha(Bytes(out.alpha));
  r->set_num_visible_splats(out.num_visible);
  ContentDigest digest;
  digest.Update(r->range());
  digest.Update(r->intensity());
  digest.Update(r->alpha());
  if (job.options.want_points) {
    const LidarPoints& p = out.points;
    v1::LidarPointCloud* pc = r->mutable_points();
    pc->set_count(static_cast<uint32_t>(p.size()));
    pc->set_frame(job.points_frame);
    std::string xyz(p.size() * 12, '\0');
    for (size_t i = 0; i < p.size(); ++i) std::memcpy(xyz.data() + 12 * i, p.xyz[i].data(), 12);
    pc->set_xyz(std::move(xyz));
    pc->set_intensity(Bytes(p.intensity));
    pc->set_time_us(Bytes(p.time_us));
    pc->set_beam(Bytes(p.beam));
    pc->set_column(Bytes(p.column));
    for (const std::string* b : {&pc->xyz(), &pc->intensity(), &pc->time_us(), &pc->beam(), &pc->column()}) {
      digest.Update(*b);
    }
  }
  r->set_digest(digest.Hex());
  v1::LidarTimings* t = r->mutable_timings();
  t->set_projection_ms(out.projection_ms);
  t->set_sort_ms(out.sort_ms);
  t->set_blend_ms(out.blend_ms);
  t->set_total_ms(out.total_ms);
}

}  // namespace streetsim::server
