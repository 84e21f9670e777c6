// Deterministic LiDAR backward, step 2: the inverse of the range order, rank_of[entry] = j for
// every drawn entry (the rest keep the 0xffffffff the host filled in), so that step 3 finds a
// Gaussian's two entries' slots.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Ids { uint sorted_ids[]; };  // entry by range rank
layout(std430, binding = 1) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 2) writeonly buffer RankOf { uint rank_of[]; };

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  rank_of[sorted_ids[j]] = j;
}
