#!/usr/bin/env python3
"""Scripted replay through the Python client: the ego re-drives the log's trajectory with a
lateral offset, one closed-loop session step per logged frame, and the script writes the frames,
an MJPEG video and a JSON summary.

    PYTHONPATH=client/python:build/python /usr/bin/python3 examples/replay_kitti.py \
        --server 127.0.0.1:50051 --scene kitti_sfnd --out demo-out/replay [--lateral-offset-m 0.5]

The offset moves the ego to its left (ego frame: x forward, y left, z up), so the rendered views
are novel views the log never recorded.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

import streetsim

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "demo"))
from media import write_mjpeg_avi  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--token", default=None)
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--lateral-offset-m", type=float, default=0.5)
    p.add_argument("--steps", type=int, default=0, help="0: one per logged frame")
    p.add_argument("--width", type=int, default=0, help="0: the rig camera's size")
    p.add_argument("--height", type=int, default=0)
    args = p.parse_args()

    client = streetsim.Client(args.server, token=args.token)
    client.wait_for_ready(30)
    scene = client.get_scene(args.scene)
    trajectory = [(tp.time_us, streetsim.matrix_from_pose(tp.T_world_from_ego)) for tp in scene.ego_trajectory]
    if not trajectory:
        raise SystemExit(f"scene {args.scene} has no ego trajectory (no scene.json from a log)")
    if args.steps:
        trajectory = trajectory[: args.steps]
    camera = scene.rig.cameras[0]
    sensor = camera.sensor_id
    os.makedirs(os.path.join(args.out, "frames"), exist_ok=True)
    offset = np.eye(4)
    offset[1, 3] = args.lateral_offset_m
    dt_us = trajectory[1][0] - trajectory[0][0] if len(trajectory) > 1 else 100000

    steps, jpegs = [], []
    width = height = 0
    with client.session(args.scene, step_dt_us=dt_us, start_time_us=trajectory[0][0], sensors=[sensor],
                        width=args.width, height=args.height, depth=True, alpha=True,
                        encoding="jpeg", initial_ego_pose=trajectory[0][1] @ offset) as session:
        for i, (time_us, T_world_from_ego) in enumerate(trajectory):
            ego = T_world_from_ego @ offset
            t0 = time.perf_counter()
            frame = session.step(ego_pose=ego)[sensor]
            latency_ms = (time.perf_counter() - t0) * 1e3
            jpeg = frame.rgb
            with open(os.path.join(args.out, "frames", f"step_{i:05d}_{sensor}.jpg"), "wb") as f:
                f.write(jpeg)
            jpegs.append(jpeg)
            width, height = frame.proto.rgb.width, frame.proto.rgb.height
            # Free distance straight ahead: expected depth / alpha over the image centre.
            h, w = frame.depth.shape
            d = frame.depth[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
            a = frame.alpha[h // 3: 2 * h // 3, 2 * w // 5: 3 * w // 5]
            hit = a > 0.5
            steps.append({
                "step": i,
                "time_us": int(time_us),
                "T_world_from_ego": [float(v) for v in ego.reshape(-1)],
                "digest": frame.digest,
                "latency_ms": round(latency_ms, 2),
                "free_distance_m": float(np.median(d[hit] / a[hit])) if hit.any() else None,
                "coverage": float((frame.alpha > 0.5).mean()),
            })

    fps = max(1, round(1e6 / dt_us))
    write_mjpeg_avi(os.path.join(args.out, f"{sensor}.avi"), jpegs, width, height, fps)
    latencies = sorted(s["latency_ms"] for s in steps)
    summary = {
        "scene": args.scene,
        "sensor": sensor,
        "lateral_offset_m": args.lateral_offset_m,
        "steps": len(steps),
        "image_size": [width, height],
        "latency_ms": {"p50": latencies[len(latencies) // 2],
                       "p99": latencies[min(len(latencies) - 1, int(0.99 * len(latencies)))]},
        "per_step": steps,
    }
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(f"replay: {len(steps)} steps of {args.scene}/{sensor} at {width}x{height}, "
          f"p50 {summary['latency_ms']['p50']} ms, p99 {summary['latency_ms']['p99']} ms -> {args.out}")


if __name__ == "__main__":
    main()
