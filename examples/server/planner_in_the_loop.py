#!/usr/bin/env python3
"""A planner in the loop: drives the ego along +x through a scene served by `streetsim serve`,
reading the rendered depth straight ahead each step and braking when something is close.

    PYTHONPATH=client/python:build/python /usr/bin/python3 examples/server/planner_in_the_loop.py \
        --server 127.0.0.1:50051 --scene NAME [--steps 50] [--speed 8] [--start-x 0]

The planner is deliberately simple (a replay/lane-keeping planner): it keeps its lane (y, yaw
fixed), targets --speed m/s and scales the speed down by the free distance ahead (median
depth / alpha in the image centre), stopping below 4 m.
"""
import argparse
import json

import numpy as np

import streetsim


def free_distance_m(frame):
    """Median of depth / alpha over the central window (expected depth is not divided by alpha)."""
    h, w = frame.depth.shape
    d = frame.depth[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
    a = frame.alpha[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
    hit = a > 0.5
    return float(np.median(d[hit] / a[hit])) if hit.any() else float("inf")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--token", default=None)
    p.add_argument("--scene", required=True)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--speed", type=float, default=8.0)
    p.add_argument("--start-x", type=float, default=0.0)
    p.add_argument("--height-m", type=float, default=1.65, help="ego origin height in the scene")
    args = p.parse_args()

    client = streetsim.Client(args.server, token=args.token)
    client.wait_for_ready(10)
    scene = client.get_scene(args.scene)
    sensor = scene.rig.cameras[0].sensor_id
    dt_s = 0.1
    ego = np.eye(4)
    ego[0, 3], ego[2, 3] = args.start_x, args.height_m
    log = []
    with client.session(args.scene, step_dt_us=int(dt_s * 1e6), sensors=[sensor], width=320, height=96,
                        depth=True, alpha=True, initial_ego_pose=ego) as session:
        speed = args.speed
        for k in range(args.steps):
            frames = session.step(ego_pose=ego)
            free = free_distance_m(frames[sensor])
            # Brake in proportion to the free distance; stop below 4 m.
            target = 0.0 if free < 4 else min(args.speed, args.speed * (free - 4) / 16)
            speed += np.clip(target - speed, -6 * dt_s, 2 * dt_s)  # comfort limits (m/s^2)
            ego[0, 3] += speed * dt_s
            log.append({"step": k, "x_m": round(ego[0, 3], 3), "free_m": round(free, 2), "speed_mps": round(speed, 2)})
            print("step %3d  x %7.2f m  free %7.2f m  speed %5.2f m/s" % (k, ego[0, 3], free, speed))
    print(json.dumps({"scene": args.scene, "steps": len(log), "final_x_m": log[-1]["x_m"] if log else None}))


if __name__ == "__main__":
    main()
