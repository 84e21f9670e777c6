#!/usr/bin/env python3
"""streetsim's main job, end to end, on a KITTI raw log (the demo's pipeline; ./scripts/demo runs it):

  1. train a dynamic scene from the log (`streetsim train`, every 4th frame held out);
  2. evaluate it on the held-out frames (`streetsim eval`: metrics, renders, a video);
  3. serve it (`streetsim serve` on 127.0.0.1);
  4. drive it in a closed loop through the Python client: a reactive planner (planner.py) keeps
     its distance to the vehicle ahead from the rendered LiDAR and changes lane, while the log's
     vehicles move as the scene's field replays them;
  5. write a side-by-side video, report.html and summary.json.

    PYTHONPATH=client/python:build/python /usr/bin/python3 examples/demo/pipeline.py \
        --bin build/bin/streetsim --log ../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync \
        --out demo-out [--preset preview|tiny]

Any step that fails stops the pipeline with its reason and exit status 1; nothing is skipped.
"""
import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np

import streetsim

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import media  # noqa: E402
import planner as planner_lib  # noqa: E402
import report  # noqa: E402

# What each demo preset trains and drives. `preview` is the trainer's preset of that name, the best
# scene measured within 10 minutes of training on 2 CPU cores (docs/benchmarks.md "Demo"); `tiny`
# is the same with every step cut to seconds (the pipeline's test).
PRESETS = {
    "preview": {
        "train": ["--preset", "preview", "--seed", "0"],
        "camera_scale": 0.5, "lidar_columns": 1024, "steps": 0, "report_frames": 12,
    },
    "tiny": {
        "train": ["--preset", "preview", "--seed", "0", "--resolution-scale", "0.125", "--static-iterations", "20",
                  "--iterations", "40", "--voxel", "0.6", "--no-actors"],
        "camera_scale": 0.125, "lidar_columns": 256, "steps": 6, "report_frames": 3,
    },
}

PROGRESS = re.compile(r"(\d+)/(\d+)\s+loss ([-\d.e+na]+)\s+psnr ([-\d.e+nainf]+) dB\s+(\d+) Gaussians\s+([\d.]+) it/s")


class StepFailed(Exception):
    def __init__(self, step, reason):
        super().__init__(f"{step}: {reason}")
        self.step, self.reason = step, reason


def run_logged(step, cmd, log_path, on_line=None, stdout_path=None):
    """Runs cmd, writing its stderr with wall-clock offsets to log_path; fails the step on a
    non-zero exit with the command's last lines as the reason."""
    t0 = time.monotonic()
    tail = []
    with open(log_path, "w") as log, open(stdout_path or os.devnull, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.PIPE, text=True, bufsize=1)
        try:
            for line in proc.stderr:
                t = time.monotonic() - t0
                log.write(f"{t:9.2f} {line}")
                tail = (tail + [line.rstrip()])[-8:]
                if on_line:
                    on_line(t, line)
            rc = proc.wait()
        except BaseException:
            proc.kill()
            proc.wait()
            raise
    if rc != 0:
        raise StepFailed(step, f"`{' '.join(cmd[:2])} ...` exited {rc}:\n    " + "\n    ".join(tail))
    return time.monotonic() - t0


def train(args, preset, scene_dir, out):
    curve = []  # (wall_s, iteration, loss, psnr of the iteration's view, Gaussians)

    def on_line(t, line):
        m = PROGRESS.search(line)
        if not m:
            if line.startswith("streetsim train:"):
                print("   ", line.rstrip(), flush=True)
            return
        it, total = int(m.group(1)), int(m.group(2))
        curve.append((round(t, 2), it, float(m.group(3)), float(m.group(4)), int(m.group(5))))
        if it % 100 == 0 or it == total:
            print(f"    train {it}/{total}  psnr {m.group(4)} dB  {m.group(5)} Gaussians  {t:.0f} s", flush=True)

    cmd = [args.bin, "train", "--log", args.log, "--out", scene_dir] + preset["train"]
    wall = run_logged("train", cmd, os.path.join(out, "train.log"), on_line)
    if not curve:
        raise StepFailed("train", "the trainer reported no iteration (see train.log)")
    # What the run resolved its settings to (the preset's and the flags'), as it recorded them.
    with open(os.path.join(scene_dir, "config.json")) as f:
        settings = json.load(f)["settings"]
    expected = int(settings["iterations"])
    if curve[-1][1] != expected:
        raise StepFailed("train", f"the run ended at iteration {curve[-1][1]}, not {expected}")
    for f in ("scene.ply", "scene.json"):
        if not os.path.isfile(os.path.join(scene_dir, f)):
            raise StepFailed("train", f"{scene_dir}/{f} was not written")
    with open(os.path.join(out, "train_curve.json"), "w") as f:
        json.dump({"columns": ["wall_s", "iteration", "loss", "psnr_db", "gaussians"], "rows": curve}, f)
    return {"wall_s": round(wall, 1), "iterations": curve[-1][1], "gaussians": curve[-1][4], "curve": curve,
            "static_iterations": int(settings["static-iterations"]),
            "command": " ".join(["streetsim", "train", "--log", "LOG", "--out", "DIR"] + preset["train"])}


def evaluate(args, scene_dir, out):
    eval_json = os.path.join(out, "eval.json")
    cmd = [args.bin, "eval", "--scene", scene_dir, "--log", args.log, "--decomposition",
           os.path.join(out, "heldout"), "--video", os.path.join(out, "heldout.avi")]
    wall = run_logged("eval", cmd, os.path.join(out, "eval.log"), stdout_path=eval_json)
    with open(eval_json) as f:
        result = json.load(f)
    mean = result.get("mean", {})
    if not result.get("frames") or not isinstance(mean.get("psnr"), (int, float)) or not math.isfinite(mean["psnr"]):
        raise StepFailed("eval", f"{eval_json} holds no held-out metrics")
    result["wall_s"] = round(wall, 1)
    return result


class Server:
    def __init__(self, args, data_root, out):
        self.log = open(os.path.join(out, "serve.log"), "w")
        self.proc = subprocess.Popen(
            [args.bin, "serve", "--listen", "127.0.0.1:0", "--data-root", data_root, "--state-dir",
             os.path.join(out, "state")], stdout=subprocess.PIPE, stderr=self.log, text=True)
        line = self.proc.stdout.readline()
        if "listening on" not in line:
            self.stop()
            raise StepFailed("serve", f"the server did not start (serve.log): {line.strip()!r}")
        self.address = line.strip().rsplit(" ", 1)[1]

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def logged_image(log_dir, time_us, t0_us, dt_us, count):
    """The log's own camera image nearest in time (KITTI raw: image_02/data/NNNNNNNNNN.png)."""
    k = min(max(int(round((time_us - t0_us) / dt_us)), 0), count - 1)
    path = os.path.join(log_dir, "image_02", "data", f"{k:010d}.png")
    if not os.path.isfile(path):
        raise StepFailed("drive", f"the logged image {path} is missing")
    return media.load_rgb(path)


def drive(args, preset, address, scene_name, out):
    client = streetsim.Client(address)
    client.wait_for_ready(30)
    client.load_scene(scene_name, wait=True)
    scene = client.get_scene(scene_name)  # with the ego trajectory, which LoadScene's answer lacks
    trajectory = [(tp.time_us, streetsim.matrix_from_pose(tp.T_world_from_ego)) for tp in scene.ego_trajectory]
    if len(trajectory) < 2:
        raise StepFailed("drive", f"scene {scene_name} has no ego trajectory")
    t0_us = trajectory[0][0]
    dt_us = trajectory[1][0] - trajectory[0][0]
    road = planner_lib.Road([T for _, T in trajectory])
    # The log's own speed over its first half second starts the ego as the log did.
    k = min(5, len(trajectory) - 1)
    v0 = float(np.linalg.norm(trajectory[k][1][:3, 3] - trajectory[0][1][:3, 3]) / ((trajectory[k][0] - t0_us) * 1e-6))
    plan = planner_lib.Planner(road, initial_speed_mps=v0)
    camera = scene.rig.cameras[0]
    width = max(16, int(round(camera.intrinsics.width * preset["camera_scale"])))
    height = max(16, int(round(camera.intrinsics.height * preset["camera_scale"])))
    steps = preset["steps"] or len(trajectory)
    lidar = streetsim.LidarOptions(columns=preset["lidar_columns"], points=True, points_frame="ego")

    os.makedirs(os.path.join(out, "frames"), exist_ok=True)
    jpegs, latencies, panels = [], [], []
    with client.session(scene_name, step_dt_us=dt_us, start_time_us=t0_us, sensors=[camera.sensor_id],
                        width=width, height=height, depth=True, alpha=True, lidar=lidar,
                        initial_ego_pose=plan.ego_pose()) as session:
        for k in range(steps):
            t = time.perf_counter()
            frames = session.step(ego_pose=plan.ego_pose())
            latencies.append((time.perf_counter() - t) * 1e3)
            frame, sweep = frames[camera.sensor_id], session.last_lidar
            if sweep is None or sweep.points is None:
                raise StepFailed("drive", f"step {k} returned no LiDAR points")
            time_us = session.last_response.time_us
            d = plan.step(k, time_us, dt_us * 1e-6, sweep.points,
                          planner_lib.camera_free_distance_m(frame.depth, frame.alpha))
            logged = logged_image(args.log, time_us, t0_us, dt_us, len(trajectory))
            panel = media.side_by_side(frame.rgb, logged, sweep.range)
            panel = media.caption(panel, f"t {(time_us - t0_us) * 1e-6:4.1f} s  {d.state:<11} speed {d.speed_mps:4.1f} m/s  "
                                  f"gap {'-' if d.gap_m is None else f'{d.gap_m:.1f} m'}  lateral {d.lateral_m:+.1f} m"
                                  f"   | rendered (left), logged (right), rendered LiDAR range (below)")
            jpegs.append(media.encode(panel, "JPEG", 85))
            panels.append(panel)
            print(f"    step {k:3d}  {latencies[-1]:6.0f} ms  {d.state:<11} v {d.speed_mps:4.1f} m/s  "
                  f"gap {d.gap_m}  lateral {d.lateral_m:+.2f} m", flush=True)
    h, w = panels[0].shape[:2]
    video = os.path.join(out, "closed_loop.avi")
    media.write_mjpeg_avi(video, jpegs, w, h, max(1, round(1e6 / dt_us)))
    picks = sorted(set(int(round(i)) for i in np.linspace(0, len(panels) - 1, preset["report_frames"])))
    for i in picks:
        with open(os.path.join(out, "frames", f"step_{i:04d}.jpg"), "wb") as f:
            f.write(jpegs[i])
    with open(os.path.join(out, "closed_loop.json"), "w") as f:
        json.dump({"camera": [width, height], "lidar_columns": preset["lidar_columns"],
                   "latency_ms": [round(x, 2) for x in latencies],
                   "decisions": [d.__dict__ for d in plan.decisions]}, f, indent=1)
    lat = np.array(latencies)
    return {
        "steps": steps, "dynamic": bool(scene.has_field), "camera": [width, height],
        "lidar": [len(sweep.beam_elevation_deg), preset["lidar_columns"]],
        "step_p50_ms": round(float(np.percentile(lat, 50)), 1), "step_p99_ms": round(float(np.percentile(lat, 99)), 1),
        "latency_ms": latencies, "decisions": plan.decisions, "lane_changes": plan.lane_changes,
        "frames": [(i, jpegs[i]) for i in picks], "video": video, "scene_gaussians": int(scene.num_gaussians),
    }


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bin", required=True, help="the streetsim binary")
    p.add_argument("--log", required=True, help="a KITTI raw drive folder")
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="preview", choices=sorted(PRESETS))
    p.add_argument("--scene-name", default="kitti_demo")
    args = p.parse_args()
    preset = PRESETS[args.preset]
    out = os.path.abspath(args.out)
    scene_dir = os.path.join(out, "scenes", args.scene_name)
    for stale in ("scenes", "state", "heldout", "frames"):
        shutil.rmtree(os.path.join(out, stale), ignore_errors=True)
    os.makedirs(scene_dir)
    t_start = time.monotonic()
    step = "train"
    try:
        print(f"== 1/4 train ({args.preset}): {' '.join(preset['train'])}", flush=True)
        trained = train(args, preset, scene_dir, out)
        step = "eval"
        print(f"== 2/4 evaluate the held-out frames", flush=True)
        heldout = evaluate(args, scene_dir, out)
        print(f"    held-out PSNR {heldout['mean']['psnr']:.2f} dB, SSIM {heldout['mean']['ssim']:.3f} "
              f"({len(heldout['frames'])} views)", flush=True)
        step = "serve"
        print("== 3/4 serve and drive it in a closed loop", flush=True)
        server = Server(args, os.path.join(out, "scenes"), out)
        try:
            step = "drive"
            drove = drive(args, preset, server.address, args.scene_name, out)
        finally:
            server.stop()
        step = "report"
        print("== 4/4 report", flush=True)
        outputs = {"report": os.path.join(out, "report.html"), "video": drove["video"],
                   "heldout_video": os.path.join(out, "heldout.avi"), "eval": os.path.join(out, "eval.json"),
                   "train_log": os.path.join(out, "train.log"), "closed_loop": os.path.join(out, "closed_loop.json"),
                   "scene": scene_dir}
        summary = {
            "preset": args.preset, "log": os.path.abspath(args.log),
            "heldout_psnr": round(heldout["mean"]["psnr"], 3), "heldout_ssim": round(heldout["mean"]["ssim"], 4),
            "heldout_psnr_dynamic": heldout["mean"].get("psnr_dynamic"), "heldout_views": len(heldout["frames"]),
            "train_wall_s": trained["wall_s"], "train_iterations": trained["iterations"],
            "gaussians": trained["gaussians"], "train_command": trained["command"],
            "eval_wall_s": heldout["wall_s"], "steps": drove["steps"], "step_p50_ms": drove["step_p50_ms"],
            "step_p99_ms": drove["step_p99_ms"], "camera": drove["camera"], "lidar": drove["lidar"],
            "dynamic": drove["dynamic"], "lane_changes": drove["lane_changes"],
            "left_lane_free_steps": sum(1 for d in drove["decisions"] if d.left_lane_free),
            "min_gap_m": min((d.gap_m for d in drove["decisions"] if d.gap_m is not None), default=None),
            "total_wall_s": None, "outputs": outputs,
        }
        report.write(outputs["report"], summary, trained, heldout, drove, os.path.join(out, "heldout"), args.log)
        summary["total_wall_s"] = round(time.monotonic() - t_start, 1)
        with open(os.path.join(out, "summary.json.tmp"), "w") as f:
            json.dump(summary, f, indent=1)
        os.replace(os.path.join(out, "summary.json.tmp"), os.path.join(out, "summary.json"))
    except StepFailed as e:
        print(f"demo: {e.step} failed: {e.reason}", file=sys.stderr)
        return 1
    except (streetsim.StreetsimError, OSError, ValueError) as e:
        print(f"demo: {step} failed: {e}", file=sys.stderr)
        return 1
    print(f"demo: held-out PSNR {summary['heldout_psnr']} dB, {summary['steps']} closed-loop steps at "
          f"p50 {summary['step_p50_ms']} ms, {'dynamic' if summary['dynamic'] else 'static'} scene; "
          f"{summary['total_wall_s']:.0f} s in all -> {out}/report.html", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
