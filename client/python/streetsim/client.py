"""A thin, typed helper over the generated streetsim.v1 stubs.

- ``Client(target, token=..., root_certificates=...)``: one channel, a deadline and the bearer
  token on every call.
- ``Client.render(...)`` returns ``{sensor_id: Frame}`` with numpy arrays (RAW encodings are
  decoded to arrays; PNG/JPEG come back as bytes, as Debian's python3 has no image codec).
- ``Client.session(...)`` is a context manager; ``Session.step(...)`` advances one step and
  retries idempotently (same step_index) on UNAVAILABLE.
- ``Client.train(...)`` creates a job and ``Client.watch_job(...)`` yields its progress.
- LiDAR: ``Client.render_lidar(...)`` returns a ``Lidar`` (range / intensity / alpha as
  beams x columns float32 arrays, optional points); ``render(..., lidar=LidarOptions(...))`` and
  ``session(..., lidar=...)`` add a sweep beside the cameras (``client.last_lidar``,
  ``session.last_lidar``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import grpc
import numpy as np

from streetsim.health.v1 import health_pb2, health_pb2_grpc
from streetsim.v1 import (
    common_pb2,
    render_pb2,
    render_pb2_grpc,
    scene_pb2,
    scene_pb2_grpc,
    server_info_pb2,
    server_info_pb2_grpc,
    session_pb2,
    session_pb2_grpc,
    training_pb2,
    training_pb2_grpc,
)

ENCODINGS = {
    "raw": common_pb2.IMAGE_ENCODING_RAW,
    "png": common_pb2.IMAGE_ENCODING_PNG,
    "jpeg": common_pb2.IMAGE_ENCODING_JPEG,
}
DEPTH_ENCODINGS = {"f32": common_pb2.DEPTH_ENCODING_F32, "png16": common_pb2.DEPTH_ENCODING_PNG16}


class StreetsimError(Exception):
    """A failed call: ``code`` is the grpc.StatusCode, ``details`` the server's message."""

    def __init__(self, code: grpc.StatusCode, details: str):
        super().__init__(f"{code.name}: {details}")
        self.code = code
        self.details = details


def pose_from_matrix(T) -> common_pb2.Pose:
    """4x4 rigid transform (numpy-like) -> Pose with a unit quaternion (w, x, y, z)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError("pose must be a 4x4 matrix")
    R = T[:3, :3]
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return common_pb2.Pose(
        translation_m=common_pb2.Vec3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=common_pb2.Quaternion(w=w / n, x=x / n, y=y / n, z=z / n),
    )


def matrix_from_pose(p: common_pb2.Pose) -> np.ndarray:
    w, x, y, z = p.rotation.w, p.rotation.x, p.rotation.y, p.rotation.z
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = [p.translation_m.x, p.translation_m.y, p.translation_m.z]
    return T


def _decode(image: common_pb2.Image):
    """RAW -> numpy (RGB8: HxWx3 uint8, F32: HxW float32); encoded images -> bytes."""
    if not image.data:
        return None
    if image.encoding in (common_pb2.IMAGE_ENCODING_RAW, common_pb2.IMAGE_ENCODING_UNSPECIFIED):
        if image.format == common_pb2.IMAGE_FORMAT_RGB8:
            return np.frombuffer(image.data, dtype=np.uint8).reshape(image.height, image.width, 3)
        if image.format == common_pb2.IMAGE_FORMAT_F32:
            return np.frombuffer(image.data, dtype="<f4").reshape(image.height, image.width)
    return bytes(image.data)


@dataclasses.dataclass
class Frame:
    sensor_id: str
    rgb: Optional[object]  # np.ndarray (RAW) or bytes (PNG/JPEG)
    depth: Optional[object]  # np.ndarray metres (F32) or PNG16 bytes (metres = value / 256)
    alpha: Optional[object]
    T_world_from_sensor: np.ndarray
    digest: str
    proto: common_pb2.SensorFrame


def _frames(frames: Iterable[common_pb2.SensorFrame]) -> Dict[str, Frame]:
    out = {}
    for f in frames:
        out[f.sensor_id] = Frame(
            sensor_id=f.sensor_id,
            rgb=_decode(f.rgb) if f.HasField("rgb") else None,
            depth=_decode(f.depth) if f.HasField("depth") else None,
            alpha=_decode(f.alpha) if f.HasField("alpha") else None,
            T_world_from_sensor=matrix_from_pose(f.T_world_from_sensor),
            digest=f.rgb.digest,
            proto=f,
        )
    return out


@dataclasses.dataclass
class LidarOptions:
    """What LiDAR sweep to render (docs/server.md "LiDAR"); 0 means the server's default."""
    columns: int = 0                  # azimuth bins, 1..65536 (0 = 2048)
    min_range_m: float = 0.0          # 0 = 2.5
    max_range_m: float = 0.0          # 0 = 120
    alpha_threshold: float = 0.0      # a ray returns when alpha >= this (0 = 0.5)
    drop_seed: Optional[int] = None   # set: returns drawn with probability alpha from this seed
    points: bool = False              # also return the point cloud
    points_frame: str = "sensor"      # or "ego"

    def to_proto(self) -> common_pb2.LidarRequest:
        if self.points_frame not in POINT_FRAMES:
            raise ValueError(f"points_frame must be one of {sorted(POINT_FRAMES)}")
        return common_pb2.LidarRequest(
            columns=self.columns, min_range_m=self.min_range_m, max_range_m=self.max_range_m,
            return_alpha_threshold=self.alpha_threshold, sample_drop=self.drop_seed is not None,
            drop_seed=self.drop_seed or 0, want_points=self.points,
            points_frame=POINT_FRAMES[self.points_frame])


POINT_FRAMES = {"sensor": common_pb2.LIDAR_POINT_FRAME_SENSOR, "ego": common_pb2.LIDAR_POINT_FRAME_EGO}


@dataclasses.dataclass
class Lidar:
    """One sweep. Images are beams x columns (row = beam, beam 0 the highest; column 0 straight
    behind, turning clockwise seen from above); range in metres, 0 = no return."""
    sensor_id: str
    range: np.ndarray
    intensity: np.ndarray
    alpha: np.ndarray
    beam_elevation_deg: np.ndarray
    T_world_from_lidar: np.ndarray        # at the sweep start
    T_world_from_lidar_end: np.ndarray    # at its end (equal when the sweep is static)
    points: Optional[np.ndarray]          # N x 3 float32 (sensor or ego frame), when asked for
    points_intensity: Optional[np.ndarray]
    points_time_us: Optional[np.ndarray]  # int64
    points_beam: Optional[np.ndarray]     # uint16
    points_column: Optional[np.ndarray]   # uint16
    digest: str
    proto: common_pb2.LidarResult


def _lidar(r: common_pb2.LidarResult) -> Lidar:
    shape = (r.beams, r.columns)
    img = lambda b: np.frombuffer(b, dtype="<f4").reshape(shape)  # noqa: E731
    pts = r.points if r.HasField("points") else None
    return Lidar(
        sensor_id=r.sensor_id, range=img(r.range), intensity=img(r.intensity), alpha=img(r.alpha),
        beam_elevation_deg=np.asarray(r.beam_elevation_deg, dtype=np.float64),
        T_world_from_lidar=matrix_from_pose(r.T_world_from_lidar),
        T_world_from_lidar_end=matrix_from_pose(r.T_world_from_lidar_end),
        points=np.frombuffer(pts.xyz, dtype="<f4").reshape(-1, 3) if pts else None,
        points_intensity=np.frombuffer(pts.intensity, dtype="<f4") if pts else None,
        points_time_us=np.frombuffer(pts.time_us, dtype="<i8") if pts else None,
        points_beam=np.frombuffer(pts.beam, dtype="<u2") if pts else None,
        points_column=np.frombuffer(pts.column, dtype="<u2") if pts else None,
        digest=r.digest, proto=r)


def _outputs(rgb=True, depth=False, alpha=False, encoding="raw", depth_encoding="f32", jpeg_quality=0):
    return common_pb2.OutputSpec(
        rgb=rgb,
        depth=depth,
        alpha=alpha,
        rgb_encoding=ENCODINGS[encoding],
        jpeg_quality=jpeg_quality,
        depth_encoding=DEPTH_ENCODINGS[depth_encoding],
    )


def remove_actor(actor_id: int) -> common_pb2.ActorEdit:
    """An edit that takes actor ``actor_id`` (Scene.actors) out of the scene (docs/actors.md)."""
    return common_pb2.ActorEdit(kind=common_pb2.ACTOR_EDIT_REMOVE, actor_id=int(actor_id))


def move_actor(actor_id: int, trajectory: Sequence) -> common_pb2.ActorEdit:
    """Actor ``actor_id`` follows ``trajectory``, [(time_us, 4x4 T_world_from_actor), ...], instead
    of the log's path (it holds the first pose before the first time and the last after)."""
    return _actor_edit(common_pb2.ACTOR_EDIT_MOVE, actor_id, trajectory)


def insert_actor(actor_id: int, trajectory: Sequence) -> common_pb2.ActorEdit:
    """A copy of actor ``actor_id`` on ``trajectory``; the original stays where the log has it."""
    return _actor_edit(common_pb2.ACTOR_EDIT_INSERT, actor_id, trajectory)


def _actor_edit(kind, actor_id, trajectory) -> common_pb2.ActorEdit:
    e = common_pb2.ActorEdit(kind=kind, actor_id=int(actor_id))
    for t, T in trajectory:
        e.trajectory.add(time_us=int(t), T_world_from_actor=pose_from_matrix(T))
    return e


def _sensors(sensors, width=0, height=0) -> List[common_pb2.SensorRequest]:
    out = []
    for s in sensors or []:
        if isinstance(s, common_pb2.SensorRequest):
            out.append(s)
        else:
            out.append(common_pb2.SensorRequest(sensor_id=s, width=width, height=height))
    return out


class Client:
    def __init__(self, target: str = "127.0.0.1:50051", token: Optional[str] = None,
                 root_certificates: Optional[bytes] = None, timeout_s: float = 60.0,
                 max_message_bytes: int = 64 << 20):
        options = [
            ("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes),
            ("grpc.keepalive_time_ms", 30000),
        ]
        if root_certificates is not None:
            creds = grpc.ssl_channel_credentials(root_certificates=root_certificates)
            self._channel = grpc.secure_channel(target, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        self._metadata = [("authorization", f"Bearer {token}")] if token else []
        self.timeout_s = timeout_s
        self.last_lidar: Optional[Lidar] = None
        self.info_stub = server_info_pb2_grpc.ServerInfoServiceStub(self._channel)
        self.scene_stub = scene_pb2_grpc.SceneServiceStub(self._channel)
        self.render_stub = render_pb2_grpc.RenderServiceStub(self._channel)
        self.session_stub = session_pb2_grpc.SessionServiceStub(self._channel)
        self.training_stub = training_pb2_grpc.TrainingServiceStub(self._channel)
        self.health_stub = health_pb2_grpc.HealthStub(self._channel)

    # -- plumbing -------------------------------------------------------------------------
    def _call(self, method, request, timeout_s=None):
        try:
            return method(request, timeout=timeout_s or self.timeout_s, metadata=self._metadata)
        except grpc.RpcError as e:  # noqa: PERF203
            raise StreetsimError(e.code(), e.details()) from None

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def wait_for_ready(self, timeout_s: float = 10.0):
        grpc.channel_ready_future(self._channel).result(timeout=timeout_s)

    # -- info, health, scenes ---------------------------------------------------------------
    def server_info(self) -> server_info_pb2.ServerInfo:
        return self._call(self.info_stub.GetServerInfo, server_info_pb2.GetServerInfoRequest())

    def is_serving(self, service: str = "") -> bool:
        r = self._call(self.health_stub.Check, health_pb2.HealthCheckRequest(service=service))
        return r.status == health_pb2.HealthCheckResponse.SERVING

    def list_scenes(self) -> List[scene_pb2.Scene]:
        return list(self._call(self.scene_stub.ListScenes, scene_pb2.ListScenesRequest()).scenes)

    def get_scene(self, name: str) -> scene_pb2.Scene:
        return self._call(self.scene_stub.GetScene, scene_pb2.GetSceneRequest(name=name))

    def load_scene(self, name: str, wait: bool = True) -> scene_pb2.Scene:
        return self._call(self.scene_stub.LoadScene, scene_pb2.LoadSceneRequest(name=name, wait=wait)).scene

    def unload_scene(self, name: str):
        self._call(self.scene_stub.UnloadScene, scene_pb2.UnloadSceneRequest(name=name))

    # -- rendering ----------------------------------------------------------------------------
    def render(self, scene: str, time_us: int = 0, ego_pose=None, sensor_pose=None,
               sensors: Optional[Sequence] = None, width: int = 0, height: int = 0, rgb: bool = True,
               depth: bool = False, alpha: bool = False, encoding: str = "raw",
               depth_encoding: str = "f32", timeout_s: Optional[float] = None,
               lidar: Optional[LidarOptions] = None, no_cameras: bool = False,
               actor_edits: Sequence = ()) -> Dict[str, Frame]:
        """Renders one instant. Poses are 4x4 matrices (T_world_from_ego / T_world_from_sensor);
        neither: the scene log's ego pose at time_us. With ``lidar`` the sweep is in
        ``self.last_lidar``. ``actor_edits``: remove_actor / move_actor / insert_actor edits."""
        req = render_pb2.RenderRequest(scene=scene, time_us=time_us,
                                       sensors=_sensors(sensors, width, height),
                                       outputs=_outputs(rgb, depth, alpha, encoding, depth_encoding),
                                       no_cameras=no_cameras, actor_edits=list(actor_edits))
        if lidar is not None:
            req.lidar.CopyFrom(lidar.to_proto())
        if ego_pose is not None:
            req.T_world_from_ego.CopyFrom(pose_from_matrix(ego_pose))
        if sensor_pose is not None:
            req.T_world_from_sensor.CopyFrom(pose_from_matrix(sensor_pose))
        self.last_render = self._call(self.render_stub.Render, req, timeout_s)
        self.last_lidar = _lidar(self.last_render.lidar) if self.last_render.HasField("lidar") else None
        return _frames(self.last_render.frames)

    def render_lidar(self, scene: str, time_us: int = 0, ego_pose=None, lidar_pose=None,
                     options: Optional[LidarOptions] = None, timeout_s: Optional[float] = None) -> Lidar:
        """One LiDAR sweep and no camera. ego_pose: 4x4 T_world_from_ego (the scene's mounting
        applies); lidar_pose: the LiDAR's own T_world_from_lidar; neither: the log's ego
        trajectory (a rolling sweep from time_us over the sweep duration)."""
        self.render(scene, time_us, ego_pose=ego_pose, sensor_pose=lidar_pose, rgb=False,
                    timeout_s=timeout_s, lidar=options or LidarOptions(), no_cameras=True)
        return self.last_lidar

    def render_trajectory(self, scene: str, points: Sequence, sensors: Optional[Sequence] = None,
                          width: int = 0, height: int = 0, rgb: bool = True, depth: bool = False,
                          alpha: bool = False, encoding: str = "raw", depth_encoding: str = "f32",
                          lidar: Optional[LidarOptions] = None,
                          timeout_s: Optional[float] = None,
                          actor_edits: Sequence = ()) -> Iterator[Tuple[int, Dict[str, Frame], Optional[Lidar]]]:
        """Renders a list of instants in one call, streamed in order: points are (time_us, 4x4
        T_world_from_ego or None for the log's pose). Yields (index, frames, lidar); with
        ``lidar`` every point also gets a sweep from its time (the server validates every point
        before rendering any)."""
        req = render_pb2.RenderTrajectoryRequest(scene=scene, sensors=_sensors(sensors, width, height),
                                                 outputs=_outputs(rgb, depth, alpha, encoding, depth_encoding),
                                                 actor_edits=list(actor_edits))
        for time_us, ego_pose in points:
            p = req.points.add(time_us=int(time_us))
            if ego_pose is not None:
                p.T_world_from_ego.CopyFrom(pose_from_matrix(ego_pose))
        if lidar is not None:
            req.lidar.CopyFrom(lidar.to_proto())
        try:
            for f in self.render_stub.RenderTrajectory(req, timeout=timeout_s or self.timeout_s,
                                                       metadata=self._metadata):
                r = f.response
                yield f.index, _frames(r.frames), (_lidar(r.lidar) if r.HasField("lidar") else None)
        except grpc.RpcError as e:
            raise StreetsimError(e.code(), e.details()) from None

    # -- sessions -------------------------------------------------------------------------------
    def session(self, scene: str, step_dt_us: int = 100000, start_time_us: int = 0, seed: int = 0,
                sensors: Optional[Sequence] = None, width: int = 0, height: int = 0, rgb: bool = True,
                depth: bool = False, alpha: bool = False, encoding: str = "raw",
                initial_ego_pose=None, request_id: str = "",
                lidar: Optional[LidarOptions] = None, actor_edits: Sequence = ()) -> "Session":
        """With ``lidar`` every step also returns a sweep (``Session.last_lidar``);
        ``actor_edits`` are in force from the first step (``Session.step`` can replace them)."""
        req = session_pb2.CreateSessionRequest(
            scene=scene, step_dt_us=step_dt_us, start_time_us=start_time_us, seed=seed,
            sensors=_sensors(sensors, width, height), outputs=_outputs(rgb, depth, alpha, encoding),
            request_id=request_id, actor_edits=list(actor_edits))
        if lidar is not None:
            req.lidar.CopyFrom(lidar.to_proto())
        if initial_ego_pose is not None:
            req.initial_T_world_from_ego.CopyFrom(pose_from_matrix(initial_ego_pose))
        return Session(self, self._call(self.session_stub.CreateSession, req))

    # -- training -------------------------------------------------------------------------------
    def train(self, log_path: str, scene_name: str = "", request_id: str = "",
              max_iterations: Optional[int] = None, preset: str = "",
              settings: Optional[Dict[str, object]] = None, **options) -> training_pb2.Job:
        """A training job for a log under the server's data root.

        ``preset`` and ``settings`` are ``streetsim train``'s (docs/training.md "Settings"):
        ``train(log)`` alone runs the default preset, the measured best, as ``streetsim train
        --log LOG --out DIR`` does; ``settings={"iterations": 2000, "pose-refinement": True}``
        sets any setting by its name (``streetsim train --help-all``). A value the trainer would
        refuse is INVALID_ARGUMENT from the server, naming the setting.

        Deprecated: ``max_iterations`` (the setting ``iterations``; 0 alone: init only) and
        ``options``, TrainingConfig's older fields (proto/streetsim/v1/training.proto), each the
        setting of its name; ``continue_from_scene`` (train on from a scene an earlier job trained)
        stays. An unknown name raises ValueError here.
        """
        text = {}
        for name, value in (settings or {}).items():
            if isinstance(value, bool):
                value = "true" if value else "false"
            text[str(name)] = str(value)
        if max_iterations is None and not preset and not text and not options:
            preset = "quality"  # the default, as `streetsim train --log LOG --out DIR` runs it
        try:
            config = training_pb2.TrainingConfig(scene_name=scene_name, max_iterations=max_iterations or 0,
                                                 preset=preset, settings=text, **options)
        except (ValueError, TypeError) as e:
            raise ValueError(f"train(): {e}") from None
        req = training_pb2.CreateTrainingJobRequest(log_path=log_path, request_id=request_id, config=config)
        return self._call(self.training_stub.CreateTrainingJob, req)

    def get_job(self, job_id: str) -> training_pb2.Job:
        return self._call(self.training_stub.GetJob, training_pb2.GetJobRequest(job_id=job_id))

    def list_jobs(self) -> List[training_pb2.Job]:
        return list(self._call(self.training_stub.ListJobs, training_pb2.ListJobsRequest()).jobs)

    def cancel_job(self, job_id: str) -> training_pb2.Job:
        return self._call(self.training_stub.CancelJob, training_pb2.CancelJobRequest(job_id=job_id))

    def watch_job(self, job_id: str, timeout_s: float = 24 * 3600) -> Iterator[training_pb2.Job]:
        """Yields the job on every change until it ends (the last one is final)."""
        try:
            for job in self.training_stub.WatchJob(training_pb2.WatchJobRequest(job_id=job_id),
                                                   timeout=timeout_s, metadata=self._metadata):
                yield job
        except grpc.RpcError as e:
            raise StreetsimError(e.code(), e.details()) from None


class Session:
    """A closed-loop session; ``with client.session(...) as s:`` closes it at the end."""

    def __init__(self, client: Client, proto: session_pb2.Session):
        self.client = client
        self.proto = proto
        self.id = proto.session_id
        self.next_step = proto.last_step_index + 1
        self.last_response: Optional[session_pb2.StepResponse] = None
        self.last_lidar: Optional[Lidar] = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        try:
            self.client._call(self.client.session_stub.CloseSession,
                              session_pb2.CloseSessionRequest(session_id=self.id))
        except StreetsimError as e:
            if e.code != grpc.StatusCode.NOT_FOUND:
                raise

    def step(self, ego_pose=None, trajectory: Optional[Sequence] = None, timeout_s: Optional[float] = None,
             retries: int = 2, lidar: Optional[LidarOptions] = None,
             actor_edits: Optional[Sequence] = None) -> Dict[str, Frame]:
        """Advances one step. ego_pose: 4x4 T_world_from_ego; trajectory: [(time_us, 4x4), ...]
        for the server to follow; neither: the ego stays. Retries (same step_index) are
        idempotent, so UNAVAILABLE / DEADLINE_EXCEEDED are retried ``retries`` times. lidar:
        this step's sweep (replaces the session's); the sweep lands in ``self.last_lidar``.
        actor_edits: the session's edits from this step on (a list, [] for none); None keeps them."""
        req = session_pb2.StepRequest(session_id=self.id, step_index=self.next_step)
        if actor_edits is not None:
            req.actor_edits.SetInParent()
            req.actor_edits.edits.extend(list(actor_edits))
        if lidar is not None:
            req.lidar.CopyFrom(lidar.to_proto())
        if ego_pose is not None:
            req.T_world_from_ego.CopyFrom(pose_from_matrix(ego_pose))
        elif trajectory is not None:
            for t, T in trajectory:
                req.trajectory.poses.add(time_us=int(t), T_world_from_ego=pose_from_matrix(T))
        for attempt in range(retries + 1):
            try:
                resp = self.client._call(self.client.session_stub.Step, req, timeout_s)
                break
            except StreetsimError as e:
                if attempt == retries or e.code not in (grpc.StatusCode.UNAVAILABLE,
                                                        grpc.StatusCode.DEADLINE_EXCEEDED):
                    raise
        self.last_response = resp
        self.last_lidar = _lidar(resp.lidar) if resp.HasField("lidar") else None
        self.next_step += 1
        return _frames(resp.frames)

    def fork(self) -> "Session":
        return Session(self.client, self.client._call(self.client.session_stub.ForkSession,
                                                      session_pb2.ForkSessionRequest(session_id=self.id)))

    def info(self) -> session_pb2.Session:
        return self.client._call(self.client.session_stub.GetSession,
                                 session_pb2.GetSessionRequest(session_id=self.id))
