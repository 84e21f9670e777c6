// Moving objects of a log, found and followed in its LiDAR alone: no boxes, no labels.
//
// Per scan: the points above the ground, grouped into objects by 2-D connectivity in the level
// frame (cells of cell_m, 8-connected); an object whose points the dynamic mask flags (free space
// seen through them from a neighbouring scan) starts a track. The mask flags little of a vehicle
// that slides along itself (the side of a truck overtaking the ego car occupies the same place in
// both scans); grouping lends the flagged ends' motion to the whole object. From scan to scan a
// track takes the object that overlaps its constant-velocity prediction most and registers its
// last points onto it (ICP: rotation about the level frame's up axis plus translation), so an
// object keeps its track when it stops and the mask no longer flags it.
//
// The level frame is the ego frame of the first selected frame (up = its z axis); motions are
// returned in the world frame.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "scene/init/dynamic_mask.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct MovingObjectOptions {
  FrameRange frames;
  DynamicMaskOptions dynamic;
  double min_range_m = 3.0;            // the ego car's own returns
  double max_range_m = 40.0;           // the mask judges nothing farther
  double min_height_m = 0.3;           // above the ground under the scanner: kerbs and road markings out
  double max_height_m = 4.0;           // branches and bridges out
  double cell_m = 0.3;                 // 2-D grouping cell; objects closer than ~1.4 cells merge
  int min_points = 30;                 // smaller groups are noise, not objects
  int min_dynamic_points = 15;         // a new track needs this many flagged points...
  double min_dynamic_fraction = 0.05;  // ...and this share of the object's points
  double max_length_m = 25.0;          // longer groups (walls, hedges, parked queues) are not one object
  double max_speed_mps = 30.0;         // a track's first association is searched this far
  double match_distance_m = 0.5;       // a predicted point is on an object within this
  double min_overlap = 0.3;            // share of a track's predicted points an object must cover
  int max_missed_frames = 3;           // a track ends after this many scans without its object
  bool keep_points = false;            // ObjectObservation::points_world (thinned to 15 cm)
};

struct ObjectObservation {
  int frame = 0;
  int64_t time_us = 0;
  // The object's rigid motion since the track's first observation: a point on it at the first
  // observation (world frame) is at T_world_motion * p now.
  Eigen::Isometry3d T_world_motion = Eigen::Isometry3d::Identity();
  Eigen::Vector3d centroid_world = Eigen::Vector3d::Zero();  // of the points seen in this scan
  int num_points = 0;
  int num_dynamic = 0;
  double icp_rms_m = 0;  // of the registration that placed it; 0 for the first observation
  std::vector<Eigen::Vector3f> points_world;  // with MovingObjectOptions::keep_points
};

struct MovingObjectTrack {
  int id = 0;
  std::vector<ObjectObservation> observations;
  // Where the first observation's centroid is carried to by each observation's motion.
  Eigen::Vector3d ReferencePoint(size_t observation) const;
  double NetDisplacementM() const;  // first to last observation
  double PathLengthM() const;       // summed over consecutive observations
};

struct MovingObjects {
  std::vector<MovingObjectTrack> tracks;  // every track, by id; callers filter by length or motion
  int frames_used = 0;
};

absl::StatusOr<MovingObjects> TrackMovingObjects(const DriveLog& log, const MovingObjectOptions& options);

// The core on in-memory scans (exposed for tests). Points in the level frame, above-ground
// filtering already done; `dynamic` has one flag per point.
struct LevelScan {
  int frame = 0;
  int64_t time_us = 0;
  std::vector<Eigen::Vector3f> points;
  std::vector<uint8_t> dynamic;
};
std::vector<MovingObjectTrack> TrackObjectsInLevelScans(const std::vector<LevelScan>& scans,
                                                        const MovingObjectOptions& options);

}  // namespace streetsim
