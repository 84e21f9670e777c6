#!/usr/bin/env python3
"""Actor edits on a trained scene (docs/actors.md): lists the scene's actors, renders one instant
as the log has it, with an actor removed and with it moved into the ego's lane ahead, writes the
three side by side, and times closed-loop steps with each edit.

  PYTHONPATH=client/python:build/python /usr/bin/python3 examples/server/actor_edits.py \\
      --server 127.0.0.1:50051 --scene kitti [--actor ID] [--time-s 3.9] [--out edits.png]

--actor: the actor to edit (default: the one with the most Gaussians).
"""
import argparse
import time

import numpy as np

import streetsim


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server", default="127.0.0.1:50051")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--actor", type=int, default=0)
    ap.add_argument("--time-s", type=float, default=None, help="seconds after the log's start (default: its middle)")
    ap.add_argument("--ahead-m", type=float, default=9.0, help="where the moved actor stands ahead of the ego")
    ap.add_argument("--steps", type=int, default=20, help="closed-loop steps timed per edit")
    ap.add_argument("--out", default="actor_edits.png")
    args = ap.parse_args()

    c = streetsim.Client(args.server, timeout_s=300)
    c.load_scene(args.scene)
    scene = c.get_scene(args.scene)
    if not scene.actors:
        raise SystemExit("%s has no actors (streetsim actors extract)" % args.scene)
    print("actor  from_s  to_s  box_m (l x w x h)  Gaussians  ghost")
    for a in scene.actors:
        e = a.half_extent_m
        print("%5d %7.2f %5.2f  %4.1f x %3.1f x %3.1f  %9d %6d" % (
            a.actor_id, (a.start_time_us - scene.start_time_us) * 1e-6, (a.end_time_us - scene.start_time_us) * 1e-6,
            2 * e.x, 2 * e.y, 2 * e.z, a.num_gaussians, a.num_ghost_gaussians))
    actor = max(scene.actors, key=lambda a: a.num_gaussians) if not args.actor else \
        next(a for a in scene.actors if a.actor_id == args.actor)
    t = scene.start_time_us + int(1e6 * (args.time_s if args.time_s is not None else
                                         (scene.end_time_us - scene.start_time_us) * 5e-7))
    # The log's ego at t (nearest trajectory pose) and the actor placed in its lane, ahead, at the
    # height the log had the actor at above the ego.
    ego = min(scene.ego_trajectory, key=lambda p: abs(p.time_us - t))
    T_ego = streetsim.matrix_from_pose(ego.T_world_from_ego)
    first = streetsim.matrix_from_pose(actor.trajectory[0].T_world_from_actor)
    z = (np.linalg.inv(streetsim.matrix_from_pose(scene.ego_trajectory[0].T_world_from_ego)) @ first)[2, 3]
    local = np.eye(4)
    local[:3, 3] = [args.ahead_m, 0.0, z]
    T_ahead = T_ego @ local
    edits = {
        "log": [],
        "removed": [streetsim.remove_actor(actor.actor_id)],
        "moved ahead": [streetsim.move_actor(actor.actor_id, [(t, T_ahead)])],
    }
    images = []
    for name, e in edits.items():
        frames = c.render(args.scene, time_us=t, actor_edits=e)
        images.append(next(iter(frames.values())).rgb)
    try:
        from PIL import Image
        Image.fromarray(np.concatenate(images, axis=0)).save(args.out)
        print("wrote %s (top to bottom: %s) of actor %d at %.2f s" % (
            args.out, ", ".join(edits), actor.actor_id, (t - scene.start_time_us) * 1e-6))
    except ImportError:
        print("python3-pil is missing: no image written")

    # What an edit costs per closed-loop step: the log's ego pose each step, a new time each step.
    print("edit          p50 ms  mean ms  (%d steps, every camera of the rig)" % args.steps)
    dt = max(1, (scene.end_time_us - scene.start_time_us) // (args.steps + 1))
    for name, e in edits.items():
        with c.session(args.scene, step_dt_us=dt, start_time_us=scene.start_time_us, actor_edits=e) as s:
            s.step()  # warm
            ms = []
            for _ in range(args.steps - 1):
                t0 = time.perf_counter()
                s.step()
                ms.append(1e3 * (time.perf_counter() - t0))
        print("%-12s %7.1f %8.1f" % (name, np.median(ms), np.mean(ms)))


if __name__ == "__main__":
    main()
