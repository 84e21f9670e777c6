"""ReplicaClient (client/python/streetsim/replicas.py) against two real `streetsim serve --replica`
processes sharing a data root and a state dir: ids name their replica, a session's steps reach the
replica that created it, stateless renders rotate and fail over when a replica dies.
"""
import os
import shutil
import tempfile
import unittest

import grpc
import numpy as np

import streetsim
from test_python_client import ServerProcess, write_ply

EGO = np.eye(4)  # x forward: cam_front sees the wall 10 m ahead


class ReplicaClientTest(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="streetsim_replicas_")
        data = os.path.join(self.tmp, "data")
        os.makedirs(data)
        write_ply(os.path.join(data, "wall.ply"))
        state = os.path.join(self.tmp, "state")
        self.servers = {n: ServerProcess(data, state, ["--replica", n]) for n in ("r0", "r1")}

    def tearDown(self):
        for s in self.servers.values():
            if s.proc.poll() is None:
                s.proc.kill()
                s.proc.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def test_sessions_are_routed_and_renders_fail_over(self):
        rc = streetsim.ReplicaClient({n: s.address for n, s in self.servers.items()}, timeout_s=30)
        sessions = [rc.session("wall", sensors=["cam_front"], width=96, height=32, initial_ego_pose=EGO)
                    for _ in range(4)]
        owners = sorted(streetsim.replica_of(s.id) for s in sessions)
        self.assertEqual(owners, ["r0", "r0", "r1", "r1"])  # created in turn
        for s in sessions:
            frames = s.step(ego_pose=EGO)
            self.assertGreater(frames["cam_front"].rgb.mean(), 0.0)
            self.assertIs(s.client, rc.session_client(s.id))
        # A session's id sent to the other replica: NOT_FOUND naming the owner.
        other = "r1" if streetsim.replica_of(sessions[0].id) == "r0" else "r0"
        with self.assertRaises(streetsim.StreetsimError) as e:
            streetsim.Session(rc.client_for(other), sessions[0].proto).step()
        self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
        self.assertIn("belongs to replica", e.exception.details)
        # r1 dies: every render still succeeds (on r0), r0's sessions go on.
        self.servers["r1"].proc.kill()
        self.servers["r1"].proc.wait()
        for _ in range(4):
            frames = rc.render("wall", ego_pose=EGO, sensors=["cam_front"], width=96, height=32)
            self.assertIn("cam_front", frames)
        for s in sessions:
            if streetsim.replica_of(s.id) == "r0":
                s.step(ego_pose=EGO)
        rc.close()

    def test_a_replica_client_needs_replicas(self):
        with self.assertRaises(ValueError):
            streetsim.ReplicaClient({})
        with self.assertRaises(ValueError):
            streetsim.ReplicaClient(names=["a"], address_template="no-placeholder:1")
        rc = streetsim.ReplicaClient(names=["streetsim-0", "streetsim-1"],
                                     address_template="{replica}.streetsim-pods.default.svc:50051")
        self.assertEqual(rc.names, ["streetsim-0", "streetsim-1"])
        self.assertEqual(streetsim.replica_of("streetsim-1.s-4-0a1b2c3d"), "streetsim-1")
        self.assertEqual(streetsim.replica_of("s-4-0a1b2c3d"), "")


if __name__ == "__main__":
    unittest.main()
