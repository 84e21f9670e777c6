"""The demo planner (examples/demo/planner.py) in a small simulated world: it must keep its distance
to a vehicle ahead, never drive into it, change lane only when the next lane is free, and follow
the road it is given."""
import math
import os
import sys
import unittest

import numpy as np

sys.path.insert(0, os.path.join(os.environ.get("STREETSIM_SOURCE_DIR", "../.."), "examples", "demo"))
import planner  # noqa: E402


def box_points(x_from, x_to, y_centre, ground=-1.7, width=1.8, height=1.5, step=0.2):
    """LiDAR-like returns on a box standing on the road, in the ego frame."""
    g = np.meshgrid(np.arange(x_from, x_to, step), np.arange(y_centre - width / 2, y_centre + width / 2, step),
                    np.arange(ground + 0.3, ground + height, step), indexing="ij")
    return np.stack([a.ravel() for a in g], axis=1).astype(np.float32)


def road_points(ground=-1.7):
    g = np.mgrid[-10:40:1.0, -8:8:1.0].reshape(2, -1).T
    return np.column_stack([g, np.full(len(g), ground)]).astype(np.float32)


def straight_road(length_m=5.0, n=10):
    poses = []
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = length_m * i / (n - 1)
        poses.append(T)
    return planner.Road(poses)


def world_to_ego(points_world, T_world_from_ego):
    T = np.linalg.inv(T_world_from_ego)
    return (points_world @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


class RoadTest(unittest.TestCase):
    def test_interpolates_and_extends_straight(self):
        road = straight_road()
        np.testing.assert_allclose(road.pose_at(2.5)[:3, 3], [2.5, 0, 0], atol=1e-9)
        np.testing.assert_allclose(road.pose_at(30.0)[:3, 3], [30.0, 0, 0], atol=1e-9)
        np.testing.assert_allclose(road.pose_at(1.0, lateral_m=3.5)[:3, 3], [1.0, 3.5, 0], atol=1e-9)

    def test_a_standing_log_is_still_a_road(self):
        T = np.eye(4)
        road = planner.Road([T, T.copy(), T.copy()])
        self.assertEqual(road.length_m, 0.0)
        np.testing.assert_allclose(road.pose_at(7.0)[:3, 3], [7.0, 0, 0], atol=1e-9)


class PerceptionTest(unittest.TestCase):
    def test_ground_and_gap(self):
        pts = np.vstack([road_points(), box_points(20, 24, 0.0)])
        g = planner.ground_height_m(pts)
        self.assertAlmostEqual(g, -1.7, delta=0.05)
        obstacles = planner.obstacle_points(pts, g)
        self.assertAlmostEqual(planner.corridor_gap_m(obstacles, 0.0, 1.3, 0.5, 60), 20.0, delta=0.5)
        self.assertTrue(math.isinf(planner.corridor_gap_m(obstacles, 3.5, 1.3, -8, 30)))


class PlannerTest(unittest.TestCase):
    def drive(self, lead_world, steps=150, lead_speed=0.0, left_blocked=False, v0=6.0):
        """Closed loop against a lead box moving along +x; returns the planner and the minimum gap."""
        road = straight_road()
        p = planner.Planner(road, initial_speed_mps=v0)
        min_gap = math.inf
        for k in range(steps):
            ego = p.ego_pose()
            lead_x = lead_world + lead_speed * 0.1 * k
            world = [box_points(lead_x, lead_x + 4.5, 0.0)]
            if left_blocked:
                world.append(box_points(ego[0, 3] - 6, ego[0, 3] + 40, 3.5))
            pts = np.vstack([road_points()] + [world_to_ego(w, ego) for w in world])
            d = p.step(k, k * 100000, 0.1, pts)
            bumper_gap = lead_x - (ego[0, 3] + p.cfg.front_overhang_m)
            if abs(ego[1, 3]) < 1.5:
                min_gap = min(min_gap, bumper_gap)
        return p, min_gap

    def test_stops_behind_a_standing_vehicle_when_the_left_lane_is_taken(self):
        p, min_gap = self.drive(lead_world=40.0, left_blocked=True)
        self.assertEqual(p.lane_changes, 0)
        self.assertGreater(min_gap, 1.0)  # never touches it
        self.assertLess(p.speed_mps, 0.2)  # and waits behind it
        self.assertLess(min_gap, 12.0)    # close, not at the horizon

    def test_changes_lane_round_a_standing_vehicle_when_the_left_lane_is_free(self):
        p, min_gap = self.drive(lead_world=40.0)
        self.assertEqual(p.lane_changes, 1)
        self.assertAlmostEqual(p.lateral_m, 3.5, delta=0.05)
        self.assertGreater(min_gap, 1.0)
        self.assertGreater(p.s_m, 45.0)  # drove past it

    def test_follows_a_moving_vehicle_at_its_speed(self):
        p, min_gap = self.drive(lead_world=25.0, lead_speed=4.0, left_blocked=True, steps=300)
        self.assertEqual(p.lane_changes, 0)
        self.assertAlmostEqual(p.speed_mps, 4.0, delta=0.5)
        self.assertGreater(min_gap, 4.0)

    def test_free_road_reaches_the_desired_speed(self):
        p = planner.Planner(straight_road(), initial_speed_mps=0.0)
        for k in range(200):
            p.step(k, k * 100000, 0.1, road_points())
        self.assertAlmostEqual(p.speed_mps, p.cfg.desired_speed_mps, delta=0.3)
        self.assertEqual(p.decisions[-1].state, "follow")


if __name__ == "__main__":
    unittest.main()
