"""streetsim's reliability suite (docs/server.md "Reliability"): traffic on 127.0.0.1 only, bounded
in count and time, against the real `streetsim serve` (and `streetsim train` for jobs).

Checks, each reported as PASS/FAIL with its figures, then the line "N passed, N failed":
  fuzz          a seeded fuzzer over every RPC (messages built from the .proto schema with hostile
                values): no crash, no INTERNAL/UNKNOWN, no call past its deadline, RSS bounded
  sessions      32 concurrent sessions stepping: no error but documented backpressure
  memory        large renders give their memory back; a request over the limits is refused at once
  determinism   identical bytes for identical requests, within a process and across restarts
  auth          every RPC refuses a missing or wrong token (UNAUTHENTICATED); health stays open
  kill-server   kill -9 of the server mid-job: its trainer ends too, the restart resumes the job
                from the last checkpoint with one writer
  kill-trainer  kill -9 of the trainer mid-job: the job goes on from its last checkpoint
  replicas      three servers sharing data and state: renders balanced and failed over, sessions
                routed by id, a job created through one, its replica killed and restarted mid-run,
                the job resumed and its scene served by the others

Usage: reliability.py [--quick] [--seed N] [--only NAME[,NAME]] (STREETSIM_BIN, STREETSIM_DATA_DIR)
"""
import argparse
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback

import grpc
import numpy as np

import streetsim
from streetsim import ReplicaClient, StreetsimError

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))
from test_python_client import write_ply  # noqa: E402  (a wall of Gaussians 10 m ahead along +x)
from test_trainer_ownership import alive, trainer_pids  # noqa: E402
from streetsim.v1 import (common_pb2, render_pb2, render_pb2_grpc, scene_pb2, scene_pb2_grpc, server_info_pb2,
                          server_info_pb2_grpc, session_pb2, session_pb2_grpc, training_pb2,
                          training_pb2_grpc)
from streetsim.health.v1 import health_pb2, health_pb2_grpc

BIN = os.environ.get("STREETSIM_BIN", "build/bin/streetsim")
DATA = os.environ.get("STREETSIM_DATA_DIR", "../shared/data")
CLIP_REL = os.path.join("kitti_raw", "2011_09_26", "2011_09_26_drive_sfnd_sync")
SCENE = "wall"  # wall.ply in the data root
# A training job that is small per iteration and long enough to be acted on.
TINY_JOB = dict(resolution_scale=0.05, field="static", holdout_every=0)
# The jobs here test the server around a trainer, not its scene: no actor extraction (~10 s each).
NO_ACTORS = {"actors": False}


# -- processes -------------------------------------------------------------------------------------
def rss_mib(pid, field="VmRSS"):
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except FileNotFoundError:
        pass
    return float("nan")


def wait_for(predicate, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if predicate():
                return
        except StreetsimError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


class Server:
    """`streetsim serve` on 127.0.0.1 with an ephemeral port (or a fixed one for a restart)."""

    def __init__(self, data_root, state_dir, *extra, port=0, env=None):
        self.args = [BIN, "serve", "--listen", f"127.0.0.1:{port}", "--data-root", data_root, "--state-dir",
                     state_dir, "--backend", "cpu"] + list(extra)
        self.env = dict(os.environ, **(env or {}))
        self.log = tempfile.NamedTemporaryFile(prefix="streetsim_serve_", suffix=".log", delete=False)
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=self.log, text=True, env=self.env)
        line = self.proc.stdout.readline()
        if "listening on" not in line:
            self.proc.kill()
            raise RuntimeError(f"streetsim serve did not start: {line!r} (log {self.log.name})")
        self.address = line.strip().rsplit(" ", 1)[1]
        self.port = int(self.address.rsplit(":", 1)[1])

    @property
    def pid(self):
        return self.proc.pid

    def client(self, **kw):
        c = streetsim.Client(self.address, **kw)
        c.wait_for_ready(15)
        return c

    def kill9(self):
        self.proc.kill()
        self.proc.wait()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def data_root_with(tmp, *rels):
    """A data root holding the test scene (SCENE) and the given shared-data paths (symlinks)."""
    root = os.path.join(tmp, "data")
    os.makedirs(root, exist_ok=True)
    write_ply(os.path.join(root, SCENE + ".ply"), n=20000)
    for rel in rels:
        # The server never follows a symlink out of its data root: hard links (a copy across
        # file systems) of the log's directory with its calibration beside it.
        src = os.path.abspath(os.path.join(DATA, os.path.dirname(rel)))
        dst = os.path.join(root, os.path.dirname(rel))
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        if subprocess.run(["cp", "-rl", src, os.path.dirname(dst)], capture_output=True).returncode != 0:
            shutil.rmtree(dst, ignore_errors=True)
            shutil.copytree(src, dst)
    return root


def scene_name(client):
    names = [s.name for s in client.list_scenes()]
    if SCENE not in names:
        raise AssertionError(f"no test scene among {names}")
    return SCENE


# The ego at the origin, x forward: the default rig's cam_front sees the test wall 10 m ahead.
EGO = np.eye(4)


# -- the fuzzer ------------------------------------------------------------------------------------
class Fuzzer:
    """Random well-formed messages for every RPC, from the schema, with hostile values."""

    INTS = [0, 1, -1, 2, 7, 100, 4096, 4097, 65536, 10 ** 6, 2 ** 31 - 1, -2 ** 31, 2 ** 62, 2 ** 63 - 1, -2 ** 63]
    FLOATS = [0.0, 1.0, -1.0, 0.5, 1e-30, 1e30, 1e308, -1e308, float("nan"), float("inf"), float("-inf"), 1000.0]

    def __init__(self, seed, scene, ids):
        self.rng = random.Random(seed)
        self.scene = scene
        self.ids = ids  # session and job ids seen so far: valid ones make deeper paths reachable

    def string(self):
        r = self.rng
        choices = [lambda: "", lambda: self.scene, lambda: self.scene, lambda: "../../../etc/passwd",
                   lambda: "/etc/passwd", lambda: "a" * r.choice([1, 64, 4096, 100000]), lambda: "\x00nul",
                   lambda: "é∂ß漢字" * r.randint(1, 40), lambda: "cam_front", lambda: "kitti_raw",
                   lambda: "%s%n{}\\'\"", lambda: r.choice(self.ids) if self.ids else "s-1-0",
                   lambda: "".join(chr(r.randint(1, 0x2FFF)) for _ in range(r.randint(1, 30)))]
        return r.choice(choices)()

    def scalar(self, field):
        r = self.rng
        t = field.type
        fd = field
        if field.name in ("width", "height", "columns") and r.random() < 0.7:
            return r.choice([1, 2, 16, 64, 96, 256, 257])
        if t in (fd.TYPE_INT32, fd.TYPE_SINT32, fd.TYPE_SFIXED32):
            return max(-2 ** 31, min(2 ** 31 - 1, r.choice(self.INTS + [r.randint(-50, 5000)])))
        if t in (fd.TYPE_INT64, fd.TYPE_SINT64, fd.TYPE_SFIXED64):
            return max(-2 ** 63, min(2 ** 63 - 1, r.choice(self.INTS + [r.randint(-10 ** 7, 10 ** 7)])))
        if t in (fd.TYPE_UINT32, fd.TYPE_FIXED32):
            return max(0, min(2 ** 32 - 1, r.choice(self.INTS)))
        if t in (fd.TYPE_UINT64, fd.TYPE_FIXED64):
            return max(0, min(2 ** 64 - 1, r.choice(self.INTS)))
        if t in (fd.TYPE_DOUBLE, fd.TYPE_FLOAT):
            v = r.choice(self.FLOATS + [r.uniform(-100, 100)])
            return v if t == fd.TYPE_DOUBLE or not np.isfinite(v) or abs(v) < 3e38 else 3e38
        if t == fd.TYPE_BOOL:
            return r.random() < 0.5
        if t == fd.TYPE_STRING:
            # Mostly valid keys, so that requests get past lookup into validation and rendering.
            if field.name in ("scene", "name") and r.random() < 0.8:
                return self.scene
            if field.name in ("session_id", "job_id") and self.ids and r.random() < 0.7:
                return r.choice(self.ids[-50:])
            if field.name == "sensor_id" and r.random() < 0.6:
                return "cam_front"
            return self.string()
        if t == fd.TYPE_BYTES:
            return bytes(r.getrandbits(8) for _ in range(r.choice([0, 1, 16, 300])))
        if t == fd.TYPE_ENUM:
            values = [v.number for v in field.enum_type.values]
            return r.choice(values + [max(values) + 1, 12345])
        raise ValueError(t)

    def valid_pose(self, pose):
        T = EGO.copy()
        T[:3, 3] = [self.rng.uniform(-5, 5) for _ in range(3)]
        pose.CopyFrom(streetsim.pose_from_matrix(T))
        return pose

    def template(self, name, cls):
        """A valid request for the RPC where one is easy to make (None otherwise)."""
        r = self.rng
        msg = cls()
        names = {f.name for f in msg.DESCRIPTOR.fields}
        if "scene" in names:
            msg.scene = self.scene
        if "name" in names:
            msg.name = self.scene
        if "session_id" in names and self.ids:
            msg.session_id = r.choice(self.ids[-50:])
        if "step_index" in names:
            msg.step_index = r.choice([0, 1, 2])
        if "sensors" in names:
            msg.sensors.add(sensor_id="cam_front", width=r.choice([16, 64, 96]), height=r.choice([16, 32]))
        if "T_world_from_ego" in names:
            self.valid_pose(msg.T_world_from_ego)
        if "points" in names:
            for k in range(r.randint(1, 3)):
                self.valid_pose(msg.points.add(time_us=k).T_world_from_ego)
        return msg

    def mutate(self, msg, depth=0):
        """Overwrites one field somewhere in msg with a random value."""
        r = self.rng
        fields = msg.DESCRIPTOR.fields
        if not fields:
            return msg
        field = r.choice(fields)
        repeated = field.label == field.LABEL_REPEATED
        if field.type == field.TYPE_MESSAGE:
            if field.message_type.GetOptions().map_entry:
                return msg
            target = getattr(msg, field.name)
            if repeated:
                target = target[r.randrange(len(target))] if len(target) and r.random() < 0.7 else target.add()
            if depth < 3 and r.random() < 0.6 and target.DESCRIPTOR.fields:
                self.mutate(target, depth + 1)
            else:
                self.fill(target, depth + 1)
                if not repeated:
                    getattr(msg, field.name).SetInParent()
            return msg
        try:
            if repeated:
                getattr(msg, field.name).append(self.scalar(field))
            else:
                setattr(msg, field.name, self.scalar(field))
        except (ValueError, TypeError):
            pass
        return msg

    def request(self, name, cls):
        """Half the time a random message, half a valid one with 1-3 fields made hostile."""
        if self.rng.random() < 0.5:
            return self.fill(cls())
        msg = self.template(name, cls)
        for _ in range(self.rng.randint(0, 3)):
            self.mutate(msg)
        return msg

    def fill(self, msg, depth=0):
        r = self.rng
        for field in msg.DESCRIPTOR.fields:
            if r.random() < (0.35 if depth < 2 else 0.15):
                continue
            repeated = field.label == field.LABEL_REPEATED
            count = r.choice([0, 1, 1, 2, 3, 20]) if repeated else 1
            if field.type == field.TYPE_MESSAGE:
                if field.message_type.GetOptions().map_entry or depth >= 3:
                    continue
                for _ in range(count):
                    self.fill(getattr(msg, field.name).add() if repeated else getattr(msg, field.name), depth + 1)
                    if not repeated:
                        getattr(msg, field.name).SetInParent()
            else:
                try:
                    if repeated:
                        getattr(msg, field.name).extend(self.scalar(field) for _ in range(count))
                    else:
                        setattr(msg, field.name, self.scalar(field))
                except (ValueError, TypeError):
                    pass  # a value the generated code refuses is not a well-formed message
        return msg


def rpc_table(channel):
    """(name, callable(request, timeout, metadata), request class, streaming) for every RPC."""
    stubs = [server_info_pb2_grpc.ServerInfoServiceStub(channel), scene_pb2_grpc.SceneServiceStub(channel),
             render_pb2_grpc.RenderServiceStub(channel), session_pb2_grpc.SessionServiceStub(channel),
             training_pb2_grpc.TrainingServiceStub(channel)]
    modules = [server_info_pb2, scene_pb2, render_pb2, session_pb2, training_pb2]
    table = []
    for stub, module in zip(stubs, modules):
        for service in module.DESCRIPTOR.services_by_name.values():
            for m in service.methods:
                table.append((f"{service.name}.{m.name}", getattr(stub, m.name), _message_class(m.input_type),
                              m.server_streaming or m.client_streaming, m.client_streaming))
    return table


def _message_class(descriptor):
    from google.protobuf import symbol_database
    return symbol_database.Default().GetSymbol(descriptor.full_name)


class Report:
    def __init__(self):
        self.passed, self.failed = 0, 0

    def check(self, name, ok, detail):
        print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)
        if ok:
            self.passed += 1
        else:
            self.failed += 1


# -- checks ----------------------------------------------------------------------------------------
def check_fuzz(report, tmp, args):
    data = data_root_with(tmp)
    server = Server(data, os.path.join(tmp, "state_fuzz"), "--max-image-side", "256", "--max-request-pixels",
                    "200000", "--max-sessions", "64", "--session-lease-s", "20", "--max-queued-renders", "4")
    try:
        client = server.client()
        scene = scene_name(client)
        channel = grpc.insecure_channel(server.address)
        table = rpc_table(channel)
        ids = []
        fuzz = Fuzzer(args.seed, scene, ids)
        n = args.fuzz_requests
        codes, per_rpc, bad, hangs, slowest = {}, {}, [], 0, 0.0
        deadline_s = 20.0
        rss_start = rss_mib(server.pid)
        t0 = time.monotonic()
        for i in range(n):
            name, call, cls, streaming, client_streaming = fuzz.rng.choice(table)
            req = fuzz.request(name, cls)
            t = time.monotonic()
            try:
                if client_streaming:
                    stream = call(iter([req, fuzz.fill(cls())]), timeout=deadline_s)
                    for _ in zip(range(3), stream):
                        pass
                elif streaming:
                    for _ in zip(range(3), call(req, timeout=deadline_s)):
                        pass
                else:
                    resp = call(req, timeout=deadline_s)
                    for attr in ("session_id", "job_id"):
                        if getattr(resp, attr, ""):
                            ids.append(getattr(resp, attr))
                code = grpc.StatusCode.OK
            except grpc.RpcError as e:
                code = e.code()
            dt = time.monotonic() - t
            slowest = max(slowest, dt)
            codes[code.name] = codes.get(code.name, 0) + 1
            per_rpc.setdefault(name, {}).setdefault(code.name, 0)
            per_rpc[name][code.name] += 1
            if code in (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN):
                bad.append((name, code.name, str(req)[:200]))
            if code == grpc.StatusCode.DEADLINE_EXCEEDED:
                hangs += 1
            if server.proc.poll() is not None:
                break
        # Garbage bytes on every method: the server may refuse them any way it likes, but lives.
        for name, call, cls, streaming, client_streaming in table:
            raw = channel.unary_unary(f"/streetsim.v1.{name.replace('.', '/')}",
                                      request_serializer=lambda b: b, response_deserializer=lambda b: b)
            for k in range(5):
                try:
                    raw(bytes(fuzz.rng.getrandbits(8) for _ in range(37 * k + 1)), timeout=deadline_s)
                except grpc.RpcError:
                    pass
        wall = time.monotonic() - t0
        if args.verbose:
            for name, c in sorted(per_rpc.items()):
                print(f"  {name}: {c}")
        crashed = server.proc.poll() is not None
        peak = rss_mib(server.pid, "VmHWM")
        now = rss_mib(server.pid)
        ok = not crashed and not bad and hangs == 0 and i + 1 == n and peak < 2048
        report.check("fuzz", ok, f"{i + 1} requests over {len(table)} RPCs in {wall:.0f} s (seed {args.seed}); "
                     f"codes {dict(sorted(codes.items()))}; {len(bad)} INTERNAL/UNKNOWN {bad[:3]}; "
                     f"{hangs} past the deadline; slowest {slowest * 1000:.0f} ms; crashed {crashed}; "
                     f"RSS {rss_start:.0f} -> {now:.0f} MiB, peak {peak:.0f} MiB")
    finally:
        server.stop()


def check_sessions(report, tmp, args):
    data = data_root_with(tmp)
    server = Server(data, os.path.join(tmp, "state_sessions"), "--max-sessions", "64")
    try:
        client = server.client()
        scene = scene_name(client)
        n_sessions, steps = 32, args.steps
        errors, backpressure, latencies = [], [0], []
        lock = threading.Lock()

        def run(k):
            c = streetsim.Client(server.address)
            try:
                s = c.session(scene, sensors=["cam_front"], width=160, height=96, seed=k,
                              initial_ego_pose=EGO)
            except StreetsimError as e:
                with lock:
                    errors.append(f"create: {e}")
                return
            for step in range(steps):
                pose = EGO.copy()
                pose[0, 3] = 0.05 * step
                while True:
                    t = time.monotonic()
                    try:
                        s.step(ego_pose=pose, retries=0)
                        with lock:
                            latencies.append(time.monotonic() - t)
                        break
                    except StreetsimError as e:
                        if e.code == grpc.StatusCode.RESOURCE_EXHAUSTED:  # documented backpressure: retry
                            with lock:
                                backpressure[0] += 1
                            time.sleep(0.02)
                            continue
                        with lock:
                            errors.append(f"session {k} step {step}: {e}")
                        return
            s.close()
            c.close()

        t0 = time.monotonic()
        threads = [threading.Thread(target=run, args=(k,)) for k in range(n_sessions)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.monotonic() - t0
        lat = np.array(latencies) * 1000 if latencies else np.array([float("nan")])
        report.check("sessions", not errors and len(latencies) == n_sessions * steps,
                     f"{n_sessions} sessions x {steps} steps: {len(latencies)} steps in {wall:.0f} s "
                     f"({len(latencies) / wall:.0f} steps/s), p50 {np.percentile(lat, 50):.0f} ms, p99 "
                     f"{np.percentile(lat, 99):.0f} ms, {backpressure[0]} RESOURCE_EXHAUSTED retried, "
                     f"{len(errors)} errors {errors[:3]}; RSS {rss_mib(server.pid):.0f} MiB")
    finally:
        server.stop()


def _render_bytes(client, scene):
    r = client.render_stub.Render(render_pb2.RenderRequest(
        scene=scene, time_us=0, T_world_from_ego=streetsim.pose_from_matrix(EGO),
        sensors=[common_pb2.SensorRequest(sensor_id="cam_front", width=320, height=96)],
        outputs=common_pb2.OutputSpec(rgb=True, depth=True, alpha=True)), timeout=60)
    return b"".join(f.rgb.data + f.depth.data + f.alpha.data for f in r.frames), r.content_digest


def check_determinism(report, tmp, args):
    data = data_root_with(tmp)
    state = os.path.join(tmp, "state_det")
    results = []
    for run in range(2):
        server = Server(data, state)
        try:
            client = server.client()
            scene = scene_name(client)
            results.append(_render_bytes(client, scene))
            results.append(_render_bytes(client, scene))
        finally:
            server.stop()
    same = all(r == results[0] for r in results)
    rgb = np.frombuffer(results[0][0][:320 * 96 * 3], dtype=np.uint8)
    covered = float((rgb > 0).mean())  # the wall fills part of the view: not a blank frame
    report.check("determinism", same and covered > 0.1,
                 f"4 renders (2 per process, 2 processes) of {len(results[0][0])} bytes, {covered:.0%} of RGB "
                 "values non-zero: "
                 f"{'identical' if same else 'DIFFERENT'} (digests {sorted(set(r[1] for r in results))})")


def check_auth(report, tmp, args):
    data = data_root_with(tmp)
    token_file = os.path.join(tmp, "token")
    with open(token_file, "w") as f:
        f.write("s3cret-token\n")
    server = Server(data, os.path.join(tmp, "state_auth"), "--auth-token-file", token_file)
    try:
        channel = grpc.insecure_channel(server.address)
        grpc.channel_ready_future(channel).result(timeout=15)
        failures, checked = [], 0
        for name, call, cls, streaming, client_streaming in rpc_table(channel):
            for metadata in (None, [("authorization", "Bearer wrong")], [("authorization", "s3cret-token")]):
                checked += 1
                try:
                    if client_streaming:
                        list(call(iter([cls()]), timeout=10, metadata=metadata))
                    elif streaming:
                        list(call(cls(), timeout=10, metadata=metadata))
                    else:
                        call(cls(), timeout=10, metadata=metadata)
                    failures.append(f"{name} with {metadata}: OK")
                except grpc.RpcError as e:
                    if e.code() != grpc.StatusCode.UNAUTHENTICATED:
                        failures.append(f"{name} with {metadata}: {e.code().name}")
        ok_call = server_info_pb2_grpc.ServerInfoServiceStub(channel).GetServerInfo(
            server_info_pb2.GetServerInfoRequest(), timeout=10,
            metadata=[("authorization", "Bearer s3cret-token")])
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10)
        ok = not failures and ok_call.api_version != "" and health.status == health_pb2.HealthCheckResponse.SERVING
        report.check("auth", ok, f"{checked} calls without, with a wrong and with a malformed token: "
                     f"{len(failures)} not UNAUTHENTICATED {failures[:3]}; the right token works; health open "
                     "to probes")
    finally:
        server.stop()


def _checkpoint_iteration(work):
    try:
        with open(os.path.join(work, "checkpoint.json")) as f:
            return int(re.search(r'"iteration":\s*(\d+)', f.read()).group(1))
    except (OSError, AttributeError):
        return -1


def check_kill_server(report, tmp, args):
    data = data_root_with(tmp, CLIP_REL)
    state = os.path.join(tmp, "state_kill_server")
    server = Server(data, state)
    try:
        client = server.client()
        job = client.train(CLIP_REL, scene_name="killed", max_iterations=args.job_iterations, settings=NO_ACTORS,
                           **TINY_JOB)
        work = os.path.join(state, "jobs", job.job_id, "work")
        wait_for(lambda: client.get_job(job.job_id).progress.iteration >= 20, 300, "iteration 20")
        pids = trainer_pids(work)
        server.kill9()
        wait_for(lambda: not any(alive(p) for p in pids), 120, "the orphaned trainer to end")
        stopped_at = _checkpoint_iteration(work)
        server = Server(data, state)
        client = server.client()
        wait_for(lambda: client.get_job(job.job_id).progress.iteration > stopped_at, 300, "the resumed trainer")
        writers = len(trainer_pids(work))
        done = list(client.watch_job(job.job_id, timeout_s=900))[-1]
        ok = (len(pids) == 1 and stopped_at >= 20 and writers == 1 and done.state == training_pb2.JOB_STATE_SUCCEEDED
              and done.attempts == 2 and done.progress.iteration == args.job_iterations)
        report.check("kill-server", ok, f"trainer {pids} ended with its server; checkpoint at iteration {stopped_at}; "
                     f"{writers} writer after the restart; job {training_pb2.JobState.Name(done.state)} after "
                     f"{done.attempts} attempts at iteration {done.progress.iteration}/{args.job_iterations}")
    finally:
        server.stop()


def check_kill_trainer(report, tmp, args):
    """The trainer checkpoints every 1000 iterations: kill -9 it after its first checkpoint."""
    data = data_root_with(tmp, CLIP_REL)
    state = os.path.join(tmp, "state_kill_trainer")
    server = Server(data, state)
    iterations = 1150
    try:
        client = server.client()
        job = client.train(CLIP_REL, scene_name="trainer_killed", max_iterations=iterations, settings=NO_ACTORS, **TINY_JOB)
        work = os.path.join(state, "jobs", job.job_id, "work")
        wait_for(lambda: _checkpoint_iteration(work) >= 1000, 600, "the trainer's checkpoint at iteration 1000")
        pids = trainer_pids(work)
        before = _checkpoint_iteration(work)
        at_kill = client.get_job(job.job_id).progress.iteration
        for p in pids:
            os.kill(p, signal.SIGKILL)
        done = list(client.watch_job(job.job_id, timeout_s=900))[-1]
        with open(os.path.join(state, "jobs", job.job_id, "train.log"), errors="replace") as f:
            resumed = [int(m) for m in re.findall(r"resumed from \S+ at iteration (\d+)", f.read())]
        ok = (len(pids) == 1 and resumed and resumed[-1] >= before and done.state == training_pb2.JOB_STATE_SUCCEEDED
              and done.progress.iteration == iterations)
        report.check("kill-trainer", ok, f"trainer {pids} killed at iteration ~{at_kill} (checkpoint {before}); the "
                     f"server resumed it at iteration {resumed[-1:] or '(not in the log)'}, losing "
                     f"{at_kill - resumed[-1] if resumed else '?'} iterations (interval 1000); job "
                     f"{training_pb2.JobState.Name(done.state)} at iteration {done.progress.iteration}/{iterations}")
    finally:
        server.stop()


def check_replicas(report, tmp, args):
    data = data_root_with(tmp, CLIP_REL)
    state = os.path.join(tmp, "state_replicas")
    servers = {n: Server(data, state, "--replica", n, "--max-sessions", "32") for n in ("r0", "r1", "r2")}
    notes, failures = [], []
    try:
        rc = ReplicaClient({n: s.address for n, s in servers.items()}, timeout_s=60)
        scene = scene_name(rc.client_for("r0"))
        sessions = {n: [rc.session(scene, sensors=["cam_front"], width=160, height=96,
                                   initial_ego_pose=EGO) for _ in range(2)] for n in ("x", "y", "z")}
        by_replica = {}
        for group in sessions.values():
            for s in group:
                by_replica.setdefault(streetsim.replica_of(s.id), []).append(s)
        notes.append("sessions per replica " + str({k: len(v) for k, v in sorted(by_replica.items())}))
        job = rc.train(CLIP_REL, scene_name="shared", max_iterations=args.job_iterations, settings=NO_ACTORS,
                           **TINY_JOB)
        owner = streetsim.replica_of(job.job_id)
        wait_for(lambda: rc.get_job(job.job_id).progress.iteration >= 20, 300, "the job at iteration 20")
        # Traffic on every replica while the job's replica is killed and restarted.
        stop = threading.Event()
        counts = {"renders": 0, "render_errors": [], "steps": 0, "step_errors": []}

        def traffic():
            i = 0
            while not stop.is_set():
                i += 1
                try:
                    rc.render(scene, ego_pose=EGO, sensors=["cam_front"], width=160, height=96)
                    counts["renders"] += 1
                except StreetsimError as e:
                    counts["render_errors"].append(str(e))
                for name, group in by_replica.items():
                    if name == owner:
                        continue
                    for s in group:
                        try:
                            s.step(ego_pose=EGO, retries=0)
                            counts["steps"] += 1
                        except StreetsimError as e:
                            counts["step_errors"].append(f"{s.id}: {e}")

        t = threading.Thread(target=traffic)
        t.start()
        time.sleep(1.0)
        port = servers[owner].port
        servers[owner].kill9()
        time.sleep(2.0)
        servers[owner] = Server(data, state, "--replica", owner, "--max-sessions", "32", port=port)
        time.sleep(1.0)
        stop.set()
        t.join()
        # The old channel to the owner backs off after the failed reconnects while it was down (a
        # call in backoff fails at once with "connection refused"); as a user would, wait until it
        # reaches the restarted server. On a loaded machine the backoff outlasted the second above.
        rc.client_for(owner).wait_for_ready(30)
        done = list(rc.watch_job(job.job_id, timeout_s=900))[-1]
        if done.state != training_pb2.JOB_STATE_SUCCEEDED or done.attempts != 2:
            failures.append(f"job {training_pb2.JobState.Name(done.state)} after {done.attempts} attempts: {done.error}")
        served = []
        for n in rc.names:
            if n == owner:
                continue
            frames = rc.client_for(n).render("shared", time_us=0, width=64, height=24)
            served.append(f"{n}: {sum(f.rgb.size for f in frames.values())} values")
        if counts["render_errors"] or counts["step_errors"]:
            failures.append(f"errors: {counts['render_errors'][:2]} {counts['step_errors'][:2]}")
        notes.append(f"job {job.job_id} on {owner}: killed at iteration >= 20, restarted, "
                     f"{training_pb2.JobState.Name(done.state)} after {done.attempts} attempts; "
                     f"{counts['renders']} renders and {counts['steps']} steps on the others meanwhile; "
                     f"its scene served by {served}")
        report.check("replicas", not failures, "; ".join(notes + failures))
    finally:
        for s in servers.values():
            s.stop()


def check_memory(report, tmp, args):
    """Large admitted renders give their memory back; a request over the limits is refused at once."""
    data = data_root_with(tmp)
    server = Server(data, os.path.join(tmp, "state_memory"))
    try:
        client = server.client(timeout_s=120)
        scene = scene_name(client)
        client.render(scene, ego_pose=EGO, sensors=["cam_front"], width=320, height=96)
        base = rss_mib(server.pid)
        for _ in range(3):  # one 4096x4096 camera: at the pixel limit, ~600 MB while it renders
            client.render(scene, ego_pose=EGO, sensors=["cam_front"], width=4096, height=4096,
                          encoding="jpeg")
        peak, after = rss_mib(server.pid, "VmHWM"), rss_mib(server.pid)
        big = common_pb2.SensorRequest(sensor_id="cam_front", width=4096, height=4096)
        extra = common_pb2.SensorRequest(sensor_id="cam_extra", intrinsics=common_pb2.PinholeIntrinsics(
            width=4096, height=4096, fx=2000, fy=2000, cx=2047.5, cy=2047.5),
            T_ego_from_sensor=streetsim.pose_from_matrix(np.eye(4)))
        t = time.monotonic()
        try:
            client.render_stub.Render(render_pb2.RenderRequest(
                scene=scene, T_world_from_ego=streetsim.pose_from_matrix(EGO), sensors=[big, extra],
                outputs=common_pb2.OutputSpec(rgb=True, depth=True, alpha=True)), timeout=60)
            refused = "rendered"
        except grpc.RpcError as e:
            refused = e.code().name
        refused_s = time.monotonic() - t
        after_refused = rss_mib(server.pid)
        ok = after <= base + 64 and refused == "RESOURCE_EXHAUSTED" and refused_s < 1.0 and after_refused <= after + 20
        report.check("memory", ok, f"RSS {base:.0f} MiB, peak {peak:.0f} MiB over three 4096x4096 renders, "
                     f"{after:.0f} MiB after them; two 4096x4096 cameras with raw outputs: {refused} in "
                     f"{refused_s * 1000:.0f} ms, RSS then {after_refused:.0f} MiB")
    finally:
        server.stop()


CHECKS = {"fuzz": check_fuzz, "sessions": check_sessions, "memory": check_memory, "determinism": check_determinism,
          "auth": check_auth,
          "kill-server": check_kill_server, "kill-trainer": check_kill_trainer, "replicas": check_replicas}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CI size: every check, fewer steps")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--verbose", action="store_true", help="per-RPC figures")
    parser.add_argument("--only", default="", help="comma-separated checks: " + ",".join(CHECKS))
    args = parser.parse_args()
    args.fuzz_requests = 10000
    args.steps = 100 if args.quick else 1000
    args.job_iterations = 60 if args.quick else 200
    if not os.path.exists(BIN):
        print(f"no streetsim binary at {BIN} (STREETSIM_BIN)", file=sys.stderr)
        return 2
    names = [n for n in args.only.split(",") if n] or list(CHECKS)
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        print(f"unknown checks {unknown}; known: {list(CHECKS)}", file=sys.stderr)
        return 2
    report = Report()
    t0 = time.monotonic()
    for name in names:
        tmp = tempfile.mkdtemp(prefix=f"streetsim_rel_{name}_")
        started = time.monotonic()
        try:
            CHECKS[name](report, tmp, args)
        except Exception as e:  # a check that cannot finish is a failure with its reason
            traceback.print_exc()
            report.check(name, False, f"{type(e).__name__}: {e}")
        finally:
            print(f"  ({name}: {time.monotonic() - started:.0f} s)", flush=True)
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"reliability{' --quick' if args.quick else ''}: {time.monotonic() - t0:.0f} s", flush=True)
    print(f"{report.passed} passed, {report.failed} failed", flush=True)
    return 1 if report.failed else 0


if __name__ == "__main__":
    sys.exit(main())
