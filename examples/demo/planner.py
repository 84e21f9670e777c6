"""A small reactive planner for closed-loop runs: it follows the log's road, keeps its distance to
whatever is ahead in its lane (the Intelligent Driver Model on the gap it measures in the rendered
LiDAR) and changes lane to the left when it is held up and the LiDAR sees the next lane free.

It only ever sees what the simulator renders (LiDAR points in the ego frame, optionally the camera's
depth); the log's own poses give it the road's centre line, as a map would. Frames: ego x forward,
y left, z up; poses are 4x4 T_world_from_ego.
"""
import dataclasses
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np


# --- perception -------------------------------------------------------------------------------

def ground_height_m(points_ego: np.ndarray) -> float:
    """The road's height in the ego frame: a low percentile of the returns 3-20 m away (most of
    them are road in a street; a percentile, not the minimum, ignores the odd low outlier)."""
    if points_ego is None or len(points_ego) == 0:
        return -1.7
    r = np.hypot(points_ego[:, 0], points_ego[:, 1])
    near = points_ego[(r > 3) & (r < 20), 2]
    return float(np.percentile(near, 20)) if len(near) >= 20 else -1.7


def obstacle_points(points_ego: np.ndarray, ground_z: float, min_height_m=0.5, max_height_m=3.0) -> np.ndarray:
    """Returns from things standing on the road (vehicles, people, poles), not the road itself or
    overhanging trees."""
    if points_ego is None or len(points_ego) == 0:
        return np.zeros((0, 3), np.float32)
    h = points_ego[:, 2] - ground_z
    return points_ego[(h > min_height_m) & (h < max_height_m)]


def corridor_gap_m(obstacles: np.ndarray, y_centre_m: float, half_width_m: float, x_from_m: float,
                   x_to_m: float) -> float:
    """Longitudinal distance (ego x) to the nearest obstacle return inside a lane-wide corridor;
    inf when the corridor is empty. A lone return is ignored: it takes 3 to make an obstacle."""
    if len(obstacles) == 0:
        return math.inf
    inside = obstacles[(np.abs(obstacles[:, 1] - y_centre_m) < half_width_m) & (obstacles[:, 0] > x_from_m)
                       & (obstacles[:, 0] < x_to_m)]
    if len(inside) < 3:
        return math.inf
    return float(np.sort(inside[:, 0])[2])


def camera_free_distance_m(depth: np.ndarray, alpha: np.ndarray) -> float:
    """Median expected depth / alpha over the image centre: what the camera sees straight ahead."""
    h, w = depth.shape
    d = depth[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
    a = alpha[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
    hit = a > 0.5
    return float(np.median(d[hit] / a[hit])) if hit.any() else math.inf


# --- the road -----------------------------------------------------------------------------------

class Road:
    """The log's ego path as a centre line, parametrised by arc length s and extended straight
    along the last heading (a short log still gives a long road)."""

    def __init__(self, poses: Sequence[np.ndarray]):
        if not poses:
            raise ValueError("Road needs at least one pose")
        self.poses = [np.asarray(p, dtype=np.float64) for p in poses]
        xyz = np.array([p[:3, 3] for p in self.poses])
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
        self.length_m = float(self.s[-1])

    def pose_at(self, s_m: float, lateral_m: float = 0.0, heading_offset_rad: float = 0.0) -> np.ndarray:
        """T_world_from_ego at arc length s, `lateral_m` to the left of the centre line, turned by
        `heading_offset_rad` (the yaw of a lane change in progress)."""
        if s_m <= self.length_m and len(self.poses) > 1:
            i = int(np.searchsorted(self.s, s_m, side="right")) - 1
            i = min(max(i, 0), len(self.poses) - 2)
            span = self.s[i + 1] - self.s[i]
            f = 0.0 if span < 1e-6 else (s_m - self.s[i]) / span
            T = self.poses[i if f < 0.5 else i + 1].copy()
            T[:3, 3] = (1 - f) * self.poses[i][:3, 3] + f * self.poses[i + 1][:3, 3]
        else:
            T = self.poses[-1].copy()
            T[:3, 3] += T[:3, 0] * (s_m - self.length_m)
        offset = np.eye(4)
        c, sn = math.cos(heading_offset_rad), math.sin(heading_offset_rad)
        offset[:2, :2] = [[c, -sn], [sn, c]]
        offset[1, 3] = lateral_m
        return T @ offset


# --- the planner ------------------------------------------------------------------------------

@dataclasses.dataclass
class PlannerConfig:
    desired_speed_mps: float = 6.0
    max_accel_mps2: float = 1.5       # IDM a
    comfort_decel_mps2: float = 2.5   # IDM b
    max_decel_mps2: float = 6.0       # hard limit on braking
    time_headway_s: float = 1.5       # IDM T
    min_gap_m: float = 3.0            # IDM s0, bumper to bumper
    front_overhang_m: float = 3.0     # ego origin to the front bumper
    lane_width_m: float = 3.5
    lane_half_width_m: float = 1.3    # corridor checked for the ego's own lane
    lane_change_s: float = 4.0        # duration of a lane change
    held_up_gap_m: float = 25.0       # a lead closer than this ...
    held_up_speed_mps: float = 2.0    # ... and slower than this holds the ego up
    lookahead_m: float = 60.0


@dataclasses.dataclass
class Decision:
    """What the planner did at one step, for the log and the report."""
    step: int
    time_us: int
    s_m: float
    lateral_m: float
    speed_mps: float
    accel_mps2: float
    gap_m: Optional[float]            # bumper to the nearest obstacle in the ego's lane
    lead_speed_mps: Optional[float]
    left_lane_free: bool
    camera_free_m: Optional[float]
    state: str                        # "follow" | "lane_change" | "stopped"


class Planner:
    """Intelligent Driver Model car-following plus one gap-checked lane change to the left."""

    def __init__(self, road: Road, config: PlannerConfig = PlannerConfig(), initial_speed_mps: float = 0.0):
        self.road, self.cfg = road, config
        self.s_m, self.speed_mps, self.lateral_m = 0.0, max(0.0, initial_speed_mps), 0.0
        self._lane_change: Optional[Tuple[float, float, float]] = None  # (start lateral, target, elapsed s)
        self._last_gap: Optional[float] = None
        self._lead_speed: Optional[float] = None
        self.lane_changes = 0
        self.decisions: List[Decision] = []

    def ego_pose(self) -> np.ndarray:
        return self.road.pose_at(self.s_m, self.lateral_m, self._heading_offset())

    def _heading_offset(self) -> float:
        if self._lane_change is None:
            return 0.0
        start, target, t = self._lane_change
        lateral_rate = (target - start) * math.pi / (2 * self.cfg.lane_change_s) * math.sin(
            math.pi * min(t, self.cfg.lane_change_s) / self.cfg.lane_change_s)
        return math.atan2(lateral_rate, max(self.speed_mps, 1.0))

    def idm_accel(self, gap_m: float, lead_speed_mps: Optional[float]) -> float:
        c, v = self.cfg, self.speed_mps
        free = 1 - (v / c.desired_speed_mps) ** 4
        if not math.isfinite(gap_m):
            return c.max_accel_mps2 * free
        dv = v - (lead_speed_mps if lead_speed_mps is not None else 0.0)
        s_star = c.min_gap_m + max(0.0, v * c.time_headway_s + v * dv / (2 * math.sqrt(c.max_accel_mps2 * c.comfort_decel_mps2)))
        return c.max_accel_mps2 * (free - (s_star / max(gap_m, 0.1)) ** 2)

    def step(self, step: int, time_us: int, dt_s: float, points_ego: Optional[np.ndarray],
             camera_free_m: Optional[float] = None) -> Decision:
        """Takes what the sensors returned at the current pose, decides, and advances the ego by
        dt_s; ego_pose() is then the pose for the next step."""
        c = self.cfg
        ground = ground_height_m(points_ego)
        obstacles = obstacle_points(points_ego, ground)
        ahead = corridor_gap_m(obstacles, 0.0, c.lane_half_width_m, 0.5, c.lookahead_m)
        gap = ahead - c.front_overhang_m if math.isfinite(ahead) else math.inf
        # The lead's speed from how the gap changes; a jump means another object: start over.
        if math.isfinite(gap) and self._last_gap is not None and math.isfinite(self._last_gap) \
                and abs(gap - self._last_gap) < 3.0:
            measured = max(0.0, self.speed_mps + (gap - self._last_gap) / dt_s)
            self._lead_speed = measured if self._lead_speed is None else 0.6 * self._lead_speed + 0.4 * measured
        elif math.isfinite(gap):
            self._lead_speed = None
        self._last_gap = gap if math.isfinite(gap) else None
        # The next lane to the left: free from 8 m behind to 30 m ahead of the ego.
        left_free = self._lane_change is None and math.isinf(
            corridor_gap_m(obstacles, c.lane_width_m - self.lateral_m, c.lane_half_width_m, -8.0, 30.0))
        lead_speed = self._lead_speed
        held_up = gap < c.held_up_gap_m and (lead_speed is None or lead_speed < c.held_up_speed_mps)
        if self._lane_change is None and self.lane_changes == 0 and held_up and left_free:
            self._lane_change = (self.lateral_m, self.lateral_m + c.lane_width_m, 0.0)
            self.lane_changes += 1

        accel = self.idm_accel(gap, lead_speed)
        accel = max(-c.max_decel_mps2, min(c.max_accel_mps2, accel))
        state = "lane_change" if self._lane_change is not None else ("stopped" if self.speed_mps < 0.05 and accel <= 0 else "follow")
        decision = Decision(step=step, time_us=int(time_us), s_m=round(self.s_m, 3), lateral_m=round(self.lateral_m, 3),
                            speed_mps=round(self.speed_mps, 3), accel_mps2=round(accel, 3),
                            gap_m=round(gap, 2) if math.isfinite(gap) else None,
                            lead_speed_mps=round(lead_speed, 2) if lead_speed is not None else None,
                            left_lane_free=bool(left_free),
                            camera_free_m=round(camera_free_m, 2) if camera_free_m is not None and math.isfinite(camera_free_m) else None,
                            state=state)
        self.decisions.append(decision)

        new_speed = max(0.0, self.speed_mps + accel * dt_s)
        self.s_m += 0.5 * (self.speed_mps + new_speed) * dt_s
        self.speed_mps = new_speed
        if self._lane_change is not None:
            start, target, t = self._lane_change
            t += dt_s
            f = min(t, c.lane_change_s) / c.lane_change_s
            self.lateral_m = start + (target - start) * (1 - math.cos(math.pi * f)) / 2
            self._lane_change = None if t >= c.lane_change_s else (start, target, t)
        return decision
