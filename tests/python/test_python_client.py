"""The Python client against the real `streetsim serve` binary on 127.0.0.1 (no mocks).

Run by ctest with PYTHONPATH=client/python:<build>/python and STREETSIM_BIN=<build>/bin/streetsim.
"""
import os
import shutil
import signal
import struct
import subprocess
import tempfile
import unittest

import grpc
import numpy as np

import streetsim
from streetsim.v1 import training_pb2


def write_ply(path, n=3000, seed=0):
    """A small INRIA-layout 3DGS PLY (SH degree 0): a wall of Gaussians 10 m ahead along +x."""
    rng = np.random.default_rng(seed)
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros((n, len(props)), dtype="<f4")
    data[:, 0] = 10 + rng.uniform(-0.5, 0.5, n)
    data[:, 1] = rng.uniform(-6, 6, n)
    data[:, 2] = rng.uniform(-1, 4, n)
    data[:, 3:6] = rng.uniform(-1, 1, (n, 3))
    data[:, 6] = 3.0
    data[:, 7:10] = np.log(0.15)
    data[:, 10] = 1.0
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join("property float %s\n" % p for p in props) + "end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(data.tobytes())


class ServerProcess:
    def __init__(self, data_root, state_dir, extra=()):
        self.proc = subprocess.Popen(
            [os.environ.get("STREETSIM_BIN", "streetsim"), "serve", "--listen", "127.0.0.1:0", "--data-root",
             data_root, "--state-dir", state_dir, "--backend", "cpu", *extra],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        line = self.proc.stdout.readline()
        if "listening on" not in line:
            self.proc.kill()
            raise RuntimeError("server did not start: %r" % line)
        self.address = line.strip().rsplit(" ", 1)[1]

    def stop(self):
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=30)


class PythonClientTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="streetsim_py_")
        cls.data = os.path.join(cls.tmp, "data")
        os.makedirs(os.path.join(cls.data, "logs", "fake"))
        write_ply(os.path.join(cls.data, "wall.ply"))
        write_ply(os.path.join(cls.data, "logs", "fake", "source.ply"))
        with open(os.path.join(cls.tmp, "token"), "w") as f:
            f.write("py-token\n")
        fake_init = os.path.join(os.environ["STREETSIM_SOURCE_DIR"], "tests", "server", "fake_init.sh")
        cls.server = ServerProcess(cls.data, os.path.join(cls.tmp, "state"),
                                   ["--auth-token-file", os.path.join(cls.tmp, "token"),
                                    "--init-command", "/bin/sh " + fake_init])
        cls.client = streetsim.Client(cls.server.address, token="py-token", timeout_s=30)

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        rc = cls.server.stop()
        shutil.rmtree(cls.tmp, ignore_errors=True)
        assert rc == 0, rc

    def test_info_health_scenes(self):
        info = self.client.server_info()
        self.assertEqual(info.api_version, "1.0.0")
        self.assertTrue(info.auth_required)
        self.assertTrue(self.client.is_serving())
        names = [s.name for s in self.client.list_scenes()]
        self.assertIn("wall", names)
        scene = self.client.load_scene("wall")
        self.assertEqual(scene.num_gaussians, 3000)

    def test_auth(self):
        with streetsim.Client(self.server.address) as anonymous:
            with self.assertRaises(streetsim.StreetsimError) as e:
                anonymous.list_scenes()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAUTHENTICATED)
        with streetsim.Client(self.server.address, token="nope") as wrong:
            with self.assertRaises(streetsim.StreetsimError) as e:
                wrong.server_info()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAUTHENTICATED)

    def test_render_returns_numpy(self):
        frames = self.client.render("wall", ego_pose=np.eye(4), sensors=["cam_front"], width=160, height=48,
                                    depth=True, alpha=True)
        f = frames["cam_front"]
        self.assertEqual(f.rgb.shape, (48, 160, 3))
        self.assertEqual(f.rgb.dtype, np.uint8)
        self.assertEqual(f.depth.shape, (48, 160))
        # The wall is ~10 m ahead of the camera at the ego origin.
        centre = f.depth[20:28, 70:90] / np.maximum(f.alpha[20:28, 70:90], 1e-6)
        self.assertTrue(np.all(np.abs(centre - 10) < 1.0), centre)
        self.assertGreater(f.rgb.mean(), 1)
        # Validation reaches Python as canonical codes.
        bad = np.eye(4)
        bad[0, 3] = float("nan")
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.render("wall", ego_pose=bad)
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.render("nope", ego_pose=np.eye(4))
        self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_actor_edits_reach_the_server(self):
        # The helpers build the wire edits (docs/actors.md); a scene without actors refuses them
        # through render, session creation and step alike.
        T = np.eye(4)
        T[1, 3] = 3.5
        move = streetsim.move_actor(2, [(0, np.eye(4)), (100000, T)])
        self.assertEqual(move.actor_id, 2)
        self.assertEqual(len(move.trajectory), 2)
        self.assertAlmostEqual(move.trajectory[1].T_world_from_actor.translation_m.y, 3.5)
        self.assertEqual(len(streetsim.remove_actor(1).trajectory), 0)
        self.assertEqual(len(streetsim.insert_actor(1, [(0, np.eye(4))]).trajectory), 1)
        for call in (lambda: self.client.render("wall", ego_pose=np.eye(4), actor_edits=[streetsim.remove_actor(1)]),
                     lambda: self.client.session("wall", actor_edits=[move]).step()):
            with self.assertRaises(streetsim.StreetsimError) as e:
                call()
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            self.assertIn("no actors", e.exception.details)
        with self.client.session("wall", sensors=["cam_front"], width=32, height=16) as s:
            s.step()
            with self.assertRaises(streetsim.StreetsimError) as e:
                s.step(actor_edits=[streetsim.remove_actor(1)])
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            s.step(actor_edits=[])  # none: fine

    def test_session_context_manager_and_fork(self):
        with self.client.session("wall", sensors=["cam_front"], width=96, height=32, depth=True) as s:
            digests = []
            for k in range(3):
                T = np.eye(4)
                T[0, 3] = 0.5 * k
                frames = s.step(ego_pose=T)
                digests.append(frames["cam_front"].digest)
            self.assertEqual(len(set(digests)), 3)
            self.assertEqual(s.info().last_step_index, 2)
            with s.fork() as branch:
                self.assertEqual(branch.next_step, 3)
                branch.step()
                self.assertEqual(branch.info().last_step_index, 3)
            self.assertEqual(s.info().last_step_index, 2)
        with self.assertRaises(streetsim.StreetsimError) as e:
            s.info()
        self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_lidar_returns_numpy(self):
        lidar = self.client.render_lidar("wall", ego_pose=np.eye(4),
                                         options=streetsim.LidarOptions(columns=1024, points=True))
        self.assertEqual(lidar.range.shape, (64, 1024))
        self.assertEqual(lidar.range.dtype, np.float32)
        self.assertEqual(lidar.alpha.shape, (64, 1024))
        self.assertEqual(lidar.beam_elevation_deg.shape, (64,))
        # Straight ahead (between columns 511 and 512) the beam nearest the horizon sees the wall
        # 9.5-10.5 m away; straight behind there is nothing.
        beam = int(np.argmin(np.abs(lidar.beam_elevation_deg)))
        ahead = lidar.range[beam, 508:516]
        self.assertTrue(np.all((ahead > 9) & (ahead < 11)), ahead)
        self.assertEqual(lidar.range[:, :64].max(), 0.0)
        returns = int((lidar.range > 0).sum())
        self.assertGreater(returns, 100)
        self.assertEqual(lidar.points.shape, (returns, 3))
        self.assertEqual(lidar.points_time_us.shape, (returns,))
        hit = lidar.range[lidar.points_beam, lidar.points_column]
        np.testing.assert_allclose(np.linalg.norm(lidar.points, axis=1), hit, rtol=1e-5)
        np.testing.assert_allclose(lidar.T_world_from_lidar, np.eye(4), atol=1e-12)
        # Beside the cameras, and in a session.
        frames = self.client.render("wall", ego_pose=np.eye(4), sensors=["cam_front"], width=64, height=32,
                                    lidar=streetsim.LidarOptions(columns=256))
        self.assertIn("cam_front", frames)
        self.assertEqual(self.client.last_lidar.range.shape, (64, 256))
        with self.client.session("wall", sensors=["cam_front"], width=64, height=32,
                                 lidar=streetsim.LidarOptions(columns=128, drop_seed=3)) as s:
            s.step(ego_pose=np.eye(4))
            self.assertEqual(s.last_lidar.range.shape, (64, 128))
            s.step(ego_pose=np.eye(4), lidar=streetsim.LidarOptions(columns=64))
            self.assertEqual(s.last_lidar.range.shape, (64, 64))
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.render_lidar("wall", ego_pose=np.eye(4), options=streetsim.LidarOptions(columns=70000))
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.render_lidar("wall", ego_pose=np.eye(4),
                                     options=streetsim.LidarOptions(min_range_m=float("nan")))
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)

    def test_render_trajectory_streams_frames_and_sweeps(self):
        pose = np.eye(4)
        pose[1, 3] = 0.5
        out = list(self.client.render_trajectory("wall", [(0, np.eye(4)), (0, pose)], sensors=["cam_front"],
                                                 width=64, height=32, lidar=streetsim.LidarOptions(columns=128)))
        self.assertEqual([i for i, _, _ in out], [0, 1])
        for _, frames, lidar in out:
            self.assertEqual(frames["cam_front"].rgb.shape, (32, 64, 3))
            self.assertEqual(lidar.range.shape, (64, 128))
        # The same as single renders; the two poses differ.
        single = self.client.render("wall", ego_pose=pose, sensors=["cam_front"], width=64, height=32,
                                    lidar=streetsim.LidarOptions(columns=128))
        np.testing.assert_array_equal(out[1][1]["cam_front"].rgb, single["cam_front"].rgb)
        np.testing.assert_array_equal(out[1][2].range, self.client.last_lidar.range)
        self.assertFalse(np.array_equal(out[0][2].range, out[1][2].range))
        with self.assertRaises(streetsim.StreetsimError) as e:
            list(self.client.render_trajectory("wall", [(0, np.eye(4))], lidar=streetsim.LidarOptions(columns=-1)))
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)

    def test_training_helper_streams_progress(self):
        job = self.client.train("logs/fake", scene_name="py_trained", request_id="py-1", max_iterations=0)
        updates = list(self.client.watch_job(job.job_id))
        self.assertGreaterEqual(len(updates), 1)
        self.assertEqual(updates[-1].state, training_pb2.JOB_STATE_SUCCEEDED, updates[-1].error)
        self.assertEqual(self.client.load_scene("py_trained").num_gaussians, 3000)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.train("../outside", scene_name="x")
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)

    def test_training_options(self):
        # Options are TrainingConfig's fields; the server checks their values before a job exists.
        job = self.client.train("logs/fake", scene_name="py_options", max_iterations=0)
        self.assertEqual(job.config.max_iterations, 0)
        with self.assertRaises(ValueError):
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=100, low_res_scael=0.25)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=100, low_res_scale=0.25)
        self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn("low-res-iterations", e.exception.details)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=100, field="dynamic")
        self.assertIn("config.field", e.exception.details)
        with self.assertRaises(streetsim.StreetsimError) as e:  # the motion prior needs a field
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=100, field_motion_prior=0.3)
        self.assertIn("field-motion-prior needs a field", e.exception.details)
        with self.assertRaises(streetsim.StreetsimError) as e:  # which scans: last or all
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=9000, field_motion_prior_scans="first")
        self.assertIn("config.field_motion_prior_scans: field-motion-prior-scans must be", e.exception.details)
        with self.assertRaises(streetsim.StreetsimError) as e:  # densification's end: a stage iteration
            self.client.train("logs/fake", scene_name="py_bad", max_iterations=9000, densify_until=-1)
        self.assertIn("config.densify_until: densify-until must be an integer in 0..10000000", e.exception.details)
        # Settings by name and presets (docs/training.md "Settings"), checked by the trainer's table.
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.train("logs/fake", scene_name="py_bad", settings={"iterations": "many"})
        self.assertIn("config.settings['iterations']: iterations must be an integer", e.exception.details)
        with self.assertRaises(streetsim.StreetsimError) as e:
            self.client.train("logs/fake", scene_name="py_bad", preset="fastest")
        self.assertIn("no preset 'fastest'", e.exception.details)
        job = self.client.train("logs/fake", scene_name="py_set", settings={"iterations": 40, "pose-refinement": False})
        self.assertEqual(dict(job.config.settings), {"iterations": "40", "pose-refinement": "false"})
        self.client.cancel_job(job.job_id)
        # No settings at all: the default preset, as `streetsim train --log LOG --out DIR` runs it.
        job = self.client.train("logs/fake", scene_name="py_default")
        self.assertEqual(job.config.preset, "quality")
        self.client.cancel_job(job.job_id)
        job = self.client.train("logs/fake", scene_name="py_static", max_iterations=0, request_id="py-opt")
        self.assertEqual(job.config.scene_name, "py_static")


if __name__ == "__main__":
    unittest.main()
