#!/usr/bin/env python3
"""LiDAR from a served scene: re-drives the scene's log (or stands still on a static scene) and
prints, per sweep, the returns, the nearest return ahead and the latency; optionally saves the
range images and point clouds as .npz.

    PYTHONPATH=client/python:build/python /usr/bin/python3 examples/server/lidar_sweeps.py \
        --server 127.0.0.1:50051 --scene NAME [--sweeps 10] [--columns 2048] [--out sweeps.npz]

On a scene with an ego trajectory (scene.json from `streetsim init`) each sweep follows the log
from its time over the sweep duration (a rolling sweep); a bare .ply is swept from the origin.
"""
import argparse
import time

import numpy as np

import streetsim


def nearest_ahead_m(lidar):
    """Nearest return within +-10 degrees of straight ahead (columns around columns / 2)."""
    w = lidar.range.shape[1]
    half = max(1, w * 10 // 360)
    ahead = lidar.range[:, w // 2 - half: w // 2 + half]
    hits = ahead[ahead > 0]
    return float(hits.min()) if hits.size else float("inf")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--scene", required=True)
    p.add_argument("--sweeps", type=int, default=10)
    p.add_argument("--columns", type=int, default=2048)
    p.add_argument("--token", default=None)
    p.add_argument("--out", default=None, help=".npz with range images (and points)")
    a = p.parse_args()

    client = streetsim.Client(a.server, token=a.token)
    scene = client.get_scene(a.scene)
    times = [0] * a.sweeps
    ego = np.eye(4)
    if scene.has_time_range and len(scene.ego_trajectory) > 0:
        step = max(1, (scene.end_time_us - scene.start_time_us) // max(1, a.sweeps))
        times = [scene.start_time_us + k * step for k in range(a.sweeps)]
        ego = None  # the log's pose at each time
    options = streetsim.LidarOptions(columns=a.columns, points=a.out is not None)
    saved = {}
    for k, t in enumerate(times):
        t0 = time.perf_counter()
        lidar = client.render_lidar(a.scene, time_us=t, ego_pose=ego, options=options)
        ms = (time.perf_counter() - t0) * 1e3
        returns = int((lidar.range > 0).sum())
        print(f"sweep {k:3d} t={t} us: {returns} returns of {lidar.range.size}, nearest ahead "
              f"{nearest_ahead_m(lidar):.2f} m, {ms:.1f} ms (server sweep "
              f"{lidar.proto.timings.total_ms:.1f} ms){' rolling' if lidar.proto.rolling_sweep else ''}")
        if a.out:
            saved[f"range_{k}"] = lidar.range
            saved[f"intensity_{k}"] = lidar.intensity
            saved[f"points_{k}"] = lidar.points
    if a.out:
        np.savez_compressed(a.out, **saved)
        print("wrote", a.out)


if __name__ == "__main__":
    main()
