#include "scene/init/moving_objects.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <unordered_map>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "scene/log/kdtree.h"
#include "scene/log/point_scatter.h"
#include "scene/log/voxel_hash.h"

namespace streetsim {

Eigen::Vector3d MovingObjectTrack::ReferencePoint(size_t observation) const {
  return observations[observation].T_world_motion * observations.front().centroid_world;
}

double MovingObjectTrack::NetDisplacementM() const {
  if (observations.empty()) return 0;
  return (ReferencePoint(observations.size() - 1) - ReferencePoint(0)).norm();
}

double MovingObjectTrack::PathLengthM() const {
  double sum = 0;
  for (size_t i = 1; i < observations.size(); ++i) sum += (ReferencePoint(i) - ReferencePoint(i - 1)).norm();
  return sum;
}

namespace {

constexpr double kIcpVoxelM = 0.15;  // thinning of a registration's source: same surfaces, fewer points
constexpr int kIcpIterations = 30;

// A connected group of one scan's points. Most of a scan's groups (walls, parked cars, poles)
// never meet a track, so what only tracking needs (the thinned view, the tree, the normals) is
// built on first use: the same values as built up front, for a fraction of the scans' cost.
class Object {
 public:
  std::vector<Eigen::Vector3f> points;  // level frame
  int num_dynamic = 0;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();

  // The registration source when this is a track's last view.
  const std::vector<Eigen::Vector3f>& Thinned();
  // Over `points`: the registration target. `points` must not change once it is built.
  const KdTree3& Tree();
  // Of points[i]; zero where no plane fits. A registration meets only the points nearest its
  // source, so each is fitted when first asked for.
  const Eigen::Vector3f& Normal(int i);

 private:
  bool has_thinned_ = false, has_tree_ = false;
  std::vector<Eigen::Vector3f> thinned_;
  KdTree3 tree_;
  std::vector<Eigen::Vector3f> normals_;
  std::vector<uint8_t> has_normal_;
};

// One measured point per voxel (not the centroid: a centroid across an edge lies inside the
// object, and registering it would pull the motion).
std::vector<Eigen::Vector3f> FirstPointPerVoxel(const std::vector<Eigen::Vector3f>& points, double voxel_m) {
  VoxelIndex seen;
  std::vector<Eigen::Vector3f> out;
  const double inv = 1.0 / voxel_m;
  for (const Eigen::Vector3f& p : points) {
    bool inserted = false;
    seen.FindOrInsert(VoxelOf(p.cast<double>(), inv), &inserted);
    if (inserted) out.push_back(p);
  }
  return out;
}

// Connected groups of occupied 2-D cells, in the order of their first point (deterministic).
std::vector<std::unique_ptr<Object>> GroupObjects(const LevelScan& scan, const MovingObjectOptions& o) {
  const double inv = 1.0 / o.cell_m;
  const auto key_of = [&](const Eigen::Vector3f& p) {
    return VoxelKey{static_cast<int32_t>(std::floor(p.x() * inv)), static_cast<int32_t>(std::floor(p.y() * inv)), 0};
  };
  // Dense cell ids (2-D cells: z = 0), and each cell's points in scan order (one flat array, not a
  // vector per cell).
  VoxelIndex cell_id;
  cell_id.Clear(scan.points.size() / 4);
  std::vector<int> cell_of(scan.points.size());
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const VoxelKey k = key_of(scan.points[i]);
    bool inserted = false;
    cell_of[i] = cell_id.FindOrInsert(k, &inserted);
  }
  std::vector<int> first(cell_id.size() + 1, 0);
  for (int c : cell_of) ++first[c + 1];
  for (size_t c = 0; c < cell_id.size(); ++c) first[c + 1] += first[c];
  std::vector<int> members(scan.points.size());
  std::vector<int> fill(first.begin(), first.end() - 1);
  for (size_t i = 0; i < scan.points.size(); ++i) members[fill[cell_of[i]]++] = static_cast<int>(i);

  std::vector<uint8_t> grouped(cell_id.size(), 0);
  std::vector<std::unique_ptr<Object>> objects;
  std::vector<int> stack;
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const int seed = cell_of[i];
    if (grouped[seed]) continue;
    auto object = std::make_unique<Object>();
    grouped[seed] = 1;
    stack.assign(1, seed);
    Eigen::Vector2f lo(1e30f, 1e30f), hi(-1e30f, -1e30f);
    while (!stack.empty()) {
      const int c = stack.back();
      stack.pop_back();
      for (int m = first[c]; m < first[c + 1]; ++m) {
        const int p = members[m];
        object->points.push_back(scan.points[p]);
        object->num_dynamic += scan.dynamic[p] ? 1 : 0;
        lo = lo.cwiseMin(scan.points[p].head<2>());
        hi = hi.cwiseMax(scan.points[p].head<2>());
      }
      for (int dx = -1; dx <= 1; ++dx) {
        for (int dy = -1; dy <= 1; ++dy) {
          const int32_t n = cell_id.Find(VoxelKey{cell_id.key(c).x + dx, cell_id.key(c).y + dy, 0});
          if (n < 0 || grouped[n]) continue;
          grouped[n] = 1;
          stack.push_back(n);
        }
      }
    }
    const float length = (hi - lo).maxCoeff();
    if (static_cast<int>(object->points.size()) < o.min_points || length > o.max_length_m) {
      object->points.clear();  // kept as a placeholder so that ids stay dense; never matched
    }
    objects.push_back(std::move(object));
  }
  for (auto& object : objects) {
    for (const Eigen::Vector3f& p : object->points) object->centroid += p.cast<double>();
    if (!object->points.empty()) object->centroid /= static_cast<double>(object->points.size());
  }
  return objects;
}

Eigen::Vector3d Centroid(const std::vector<Eigen::Vector3f>& points) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3f& p : points) c += p.cast<double>();
  return points.empty() ? c : Eigen::Vector3d(c / static_cast<double>(points.size()));
}

const std::vector<Eigen::Vector3f>& Object::Thinned() {
  if (!has_thinned_) thinned_ = FirstPointPerVoxel(points, kIcpVoxelM);
  has_thinned_ = true;
  return thinned_;
}

const KdTree3& Object::Tree() {
  if (!has_tree_) tree_.Build(&points);
  has_tree_ = true;
  return tree_;
}

// The smallest principal axis of the point's 8 nearest neighbours.
const Eigen::Vector3f& Object::Normal(int i) {
  if (has_normal_.empty()) {
    normals_.assign(points.size(), Eigen::Vector3f::Zero());
    has_normal_.assign(points.size(), 0);
  }
  if (has_normal_[i]) return normals_[i];
  has_normal_[i] = 1;
  constexpr int kNeighbours = 8;
  int idx[kNeighbours];
  float d2[kNeighbours];
  const int n = Tree().KNearest(points[i], kNeighbours, 1.0f, idx, d2);
  if (n < 3) return normals_[i];  // isolated: no plane, no constraint
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(NeighbourScatter(points, idx, n));
  normals_[i] = eig.eigenvectors().col(0).cast<float>();
  return normals_[i];
}

// Rotation about z plus translation taking `source` onto `target`, point-to-plane: LiDAR samples
// a surface at the sensor's angles, not at fixed places on the object, so a vehicle sliding along
// itself shows the same side in both scans; point-to-point pairs would hold it still, while
// point-to-plane leaves the slide to the ends and edges. A small damping keeps a direction no
// surface constrains at the prediction. Returns the motion and the final RMS point-to-plane
// distance of the matched pairs.
Eigen::Isometry3d RegisterYawTranslation(const std::vector<Eigen::Vector3f>& source, Object& target,
                                         double first_radius_m, double last_radius_m, double* rms_m) {
  const KdTree3& tree = target.Tree();
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  *rms_m = 0;
  for (int it = 0; it < kIcpIterations; ++it) {
    const double a = kIcpIterations > 1 ? double(it) / (kIcpIterations - 1) : 1.0;
    const double radius = first_radius_m + (last_radius_m - first_radius_m) * std::min(1.0, 2 * a);
    Eigen::Matrix4d H = Eigen::Matrix4d::Identity() * 1e-3;
    Eigen::Vector4d g = Eigen::Vector4d::Zero();
    double sq = 0;
    int pairs = 0;
    for (const Eigen::Vector3f& s : source) {
      const Eigen::Vector3d p = T * s.cast<double>();
      const int j = tree.Nearest(p.cast<float>(), static_cast<float>(radius * radius));
      if (j < 0) continue;
      const Eigen::Vector3f& normal = target.Normal(j);
      if (normal.isZero()) continue;
      const Eigen::Vector3d n = normal.cast<double>();
      const double r = n.dot(p - target.points[j].cast<double>());
      Eigen::Vector4d J;
      J << n, n.x() * -p.y() + n.y() * p.x();
      H += J * J.transpose();
      g += J * r;
      sq += r * r;
      ++pairs;
    }
    if (pairs < 6) break;
    *rms_m = std::sqrt(sq / pairs);
    const Eigen::Vector4d x = -H.ldlt().solve(g);
    Eigen::Isometry3d step = Eigen::Isometry3d::Identity();
    step.linear() = Eigen::AngleAxisd(x(3), Eigen::Vector3d::UnitZ()).toRotationMatrix();
    step.translation() = x.head<3>();
    T = step * T;
    if (x.head<3>().norm() < 1e-5 && std::abs(x(3)) < 1e-6 && radius == last_radius_m) break;
  }
  return T;
}

struct Track {
  MovingObjectTrack out;
  Eigen::Isometry3d motion = Eigen::Isometry3d::Identity();  // level frame, since the first observation
  std::vector<Eigen::Vector3f> last_points;                  // thinned, level frame
  Eigen::Vector3d velocity_mps = Eigen::Vector3d::Zero();
  bool has_velocity = false;
  int64_t last_time_us = 0;
  int missed = 0;
};

}  // namespace

std::vector<MovingObjectTrack> TrackObjectsInLevelScans(const std::vector<LevelScan>& scans,
                                                        const MovingObjectOptions& o) {
  std::vector<Track> tracks;
  std::vector<size_t> active;
  for (const LevelScan& scan : scans) {
    std::vector<std::unique_ptr<Object>> objects = GroupObjects(scan, o);
    // Votes: each track's predicted points on the objects they land on.
    struct Candidate {
      int votes;  // a track's predicted points on the object: a long-followed object outranks a
                  // fragment's short track that lies wholly on it
      double overlap;
      size_t track;
      int object;
      Eigen::Isometry3d predicted;
    };
    std::vector<Candidate> candidates;
    for (size_t t : active) {
      Track& tr = tracks[t];
      const double dt_s = (scan.time_us - tr.last_time_us) * 1e-6;
      Eigen::Isometry3d predicted = Eigen::Isometry3d::Identity();
      if (tr.has_velocity) predicted.translation() = tr.velocity_mps * dt_s;
      const double radius = tr.has_velocity ? o.match_distance_m : o.match_distance_m + o.max_speed_mps * dt_s;
      std::unordered_map<int, int> votes;
      for (const Eigen::Vector3f& p : tr.last_points) {
        const Eigen::Vector3f q = (predicted * p.cast<double>()).cast<float>();
        int best = -1;
        float best_d2 = static_cast<float>(radius * radius);
        for (size_t k = 0; k < objects.size(); ++k) {
          if (objects[k]->points.empty()) continue;
          if ((objects[k]->centroid - q.cast<double>()).head<2>().norm() > radius + o.max_length_m) continue;
          float d2;
          if (objects[k]->Tree().Nearest(q, best_d2, &d2) >= 0 && d2 < best_d2) {
            best_d2 = d2;
            best = static_cast<int>(k);
          }
        }
        if (best >= 0) ++votes[best];
      }
      for (const auto& [k, n] : votes) {
        const double overlap = double(n) / tr.last_points.size();
        if (overlap >= o.min_overlap) candidates.push_back({n, overlap, t, k, predicted});
      }
    }
    std::sort(candidates.begin(), candidates.end(), [](const Candidate& a, const Candidate& b) {
      if (a.votes != b.votes) return a.votes > b.votes;
      return a.track != b.track ? a.track < b.track : a.object < b.object;
    });
    std::vector<uint8_t> object_taken(objects.size(), 0), track_matched(tracks.size(), 0);
    for (const Candidate& c : candidates) {
      if (object_taken[c.object] || track_matched[c.track]) continue;
      object_taken[c.object] = track_matched[c.track] = 1;
      Track& tr = tracks[c.track];
      Object& obj = *objects[c.object];
      const double dt_s = (scan.time_us - tr.last_time_us) * 1e-6;
      std::vector<Eigen::Vector3f> source;
      source.reserve(tr.last_points.size());
      for (const Eigen::Vector3f& p : tr.last_points) source.push_back((c.predicted * p.cast<double>()).cast<float>());
      const double first_radius =
          tr.has_velocity ? 2 * o.match_distance_m + 0.5 : o.match_distance_m + o.max_speed_mps * dt_s;
      double rms = 0;
      const Eigen::Isometry3d step =
          RegisterYawTranslation(source, obj, first_radius, o.match_distance_m, &rms) * c.predicted;
      const Eigen::Vector3d c_last = Centroid(tr.last_points);
      if (dt_s > 0) {
        tr.velocity_mps = (step * c_last - c_last) / dt_s;
        tr.has_velocity = true;
      }
      tr.motion = step * tr.motion;
      tr.last_points = obj.Thinned();
      tr.last_time_us = scan.time_us;
      tr.missed = 0;
      ObjectObservation ob;
      ob.frame = scan.frame;
      ob.time_us = scan.time_us;
      ob.T_world_motion = tr.motion;
      ob.centroid_world = obj.centroid;
      ob.num_points = static_cast<int>(obj.points.size());
      ob.num_dynamic = obj.num_dynamic;
      ob.icp_rms_m = rms;
      if (o.keep_points) ob.points_world = obj.Thinned();
      tr.out.observations.push_back(ob);
    }
    std::vector<size_t> still_active;
    for (size_t t : active) {
      if (!track_matched[t] && ++tracks[t].missed > o.max_missed_frames) continue;
      still_active.push_back(t);
    }
    for (size_t k = 0; k < objects.size(); ++k) {
      Object& obj = *objects[k];
      if (object_taken[k] || obj.points.empty()) continue;
      if (obj.num_dynamic < o.min_dynamic_points ||
          obj.num_dynamic < o.min_dynamic_fraction * static_cast<double>(obj.points.size())) {
        continue;
      }
      Track tr;
      tr.out.id = static_cast<int>(tracks.size());
      tr.last_points = obj.Thinned();
      tr.last_time_us = scan.time_us;
      ObjectObservation ob;
      ob.frame = scan.frame;
      ob.time_us = scan.time_us;
      ob.centroid_world = obj.centroid;
      ob.num_points = static_cast<int>(obj.points.size());
      ob.num_dynamic = obj.num_dynamic;
      if (o.keep_points) ob.points_world = obj.Thinned();
      tr.out.observations.push_back(ob);
      still_active.push_back(tracks.size());
      tracks.push_back(std::move(tr));
    }
    active = std::move(still_active);
  }
  std::vector<MovingObjectTrack> out;
  out.reserve(tracks.size());
  for (Track& t : tracks) out.push_back(std::move(t.out));
  return out;
}

namespace {

// Ground height under the scanner, sensor frame: a low percentile of the returns 3-20 m away,
// which the road dominates even beside a truck.
double GroundZ(const std::vector<Eigen::Vector3f>& points) {
  std::vector<float> z;
  for (const Eigen::Vector3f& p : points) {
    const float r = p.head<2>().norm();
    if (r > 3 && r < 20) z.push_back(p.z());
  }
  if (z.empty()) return 0;
  const size_t k = z.size() / 10;
  std::nth_element(z.begin(), z.begin() + k, z.end());
  return z[k];
}

}  // namespace

absl::StatusOr<MovingObjects> TrackMovingObjects(const DriveLog& log, const MovingObjectOptions& options) {
  if (!(options.cell_m > 0.01 && options.cell_m <= 5) || !(options.max_range_m > options.min_range_m) ||
      !(options.max_height_m > options.min_height_m) || !(options.max_speed_mps > 0) ||
      !(options.match_distance_m > 0) || !(options.min_overlap > 0 && options.min_overlap <= 1)) {
    return absl::InvalidArgumentError("moving objects: an option is out of range");
  }
  if (log.lidars.empty()) return absl::FailedPreconditionError("moving objects: the log has no LiDAR");
  const std::vector<int> frames = options.frames.Select(log);
  if (frames.size() < 2) return absl::InvalidArgumentError("moving objects: fewer than 2 frames selected");
  const Eigen::Isometry3d T_world_from_level = log.frames[frames.front()].T_world_from_ego;
  const Eigen::Isometry3d T_level_from_world = T_world_from_level.inverse();
  const Eigen::Isometry3d T_ego_from_lidar = log.lidars[0].T_ego_from_lidar;

  std::vector<LevelScan> scans(frames.size());
  std::vector<absl::Status> status(frames.size());
  const auto prepare = [&](size_t i) -> absl::Status {
    const int f = frames[i];
    const LidarObservation* obs = nullptr;
    for (const LidarObservation& l : log.frames[f].lidars) {
      if (l.lidar == 0) obs = &l;
    }
    if (obs == nullptr) return absl::FailedPreconditionError(absl::StrCat("frame ", f, " has no LiDAR scan"));
    absl::StatusOr<LidarScan> scan = LoadLidarScan(obs->path);
    if (!scan.ok()) return scan.status();
    absl::StatusOr<DynamicMask> mask = ComputeDynamicMask(log, f, scan->points, options.dynamic);
    if (!mask.ok()) return mask.status();
    const double ground_z = GroundZ(scan->points);
    const Eigen::Isometry3f T_level_from_lidar =
        (T_level_from_world * log.frames[f].T_world_from_ego * T_ego_from_lidar).cast<float>();
    LevelScan& out = scans[i];
    out.frame = f;
    out.time_us = obs->time_us;
    for (size_t k = 0; k < scan->points.size(); ++k) {
      const Eigen::Vector3f& p = scan->points[k];
      const float r = p.norm(), h = p.z() - static_cast<float>(ground_z);
      if (r < options.min_range_m || r > options.max_range_m) continue;
      if (h < options.min_height_m || h > options.max_height_m) continue;
      out.points.push_back(T_level_from_lidar * p);
      out.dynamic.push_back(mask->dynamic[k]);
    }
    return absl::OkStatus();
  };
  ThreadPool pool;
  pool.ParallelFor(static_cast<int64_t>(frames.size()), 1, [&](int64_t begin, int64_t end, int) {
    for (int64_t i = begin; i < end; ++i) status[i] = prepare(static_cast<size_t>(i));
  });
  for (const absl::Status& s : status) {
    if (!s.ok()) return s;
  }
  for (size_t i = 1; i < scans.size(); ++i) {
    if (scans[i].time_us <= scans[i - 1].time_us) {
      return absl::FailedPreconditionError(
          absl::StrCat("moving objects: LiDAR times do not increase at frame ", scans[i].frame));
    }
  }
  MovingObjects result;
  result.frames_used = static_cast<int>(scans.size());
  result.tracks = TrackObjectsInLevelScans(scans, options);
  for (MovingObjectTrack& t : result.tracks) {
    for (ObjectObservation& ob : t.observations) {
      ob.T_world_motion = T_world_from_level * ob.T_world_motion * T_level_from_world;
      ob.centroid_world = T_world_from_level * ob.centroid_world;
      const Eigen::Isometry3f T = T_world_from_level.cast<float>();
      for (Eigen::Vector3f& p : ob.points_world) p = T * p;
    }
  }
  return result;
}

}  // namespace streetsim
