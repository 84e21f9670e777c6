"""One writer per training directory, with the real binaries on the bundled KITTI clip: a second
`streetsim train` cannot write beside a running one, and a training job's trainer dies with its
server (even on kill -9 of the server), leaving a checkpoint that the restarted server resumes.

Run by ctest with PYTHONPATH=client/python:<build>/python, STREETSIM_BIN, STREETSIM_DATA_DIR.
"""
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
import unittest

import streetsim

BIN = os.environ.get("STREETSIM_BIN", "streetsim")
DATA = os.environ.get("STREETSIM_DATA_DIR", "../../../shared/data")
CLIP_REL = os.path.join("kitti_raw", "2011_09_26", "2011_09_26_drive_sfnd_sync")
# Small and long: a run that is still going when the test acts on it.
TRAIN_FLAGS = ["--iterations", "1000000", "--resolution-scale", "0.05", "--field", "static", "--holdout-every", "0",
               "--voxel", "1.0", "--checkpoint-every", "20"]


def alive(pid):
    """True while the process exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def wait_for(predicate, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def trainer_pids(out_dir):
    """`streetsim train` processes writing to out_dir."""
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as f:
                args = f.read().split(b"\0")
        except OSError:
            continue
        if b"train" in args and out_dir.encode() in args and alive(int(d)):
            pids.append(int(d))
    return pids


class TrainerOwnershipTest(unittest.TestCase):
    def setUp(self):
        if not os.path.isdir(os.path.join(DATA, CLIP_REL)):
            self.skipTest(f"no KITTI clip under {DATA}")
        self.tmp = tempfile.mkdtemp(prefix="streetsim_owner_")
        self.procs = []

    def tearDown(self):
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for pid in trainer_pids(self.tmp):
            os.kill(pid, signal.SIGKILL)
        shutil.rmtree(self.tmp, ignore_errors=True)

    def test_a_second_trainer_cannot_write_beside_a_running_one(self):
        out = os.path.join(self.tmp, "run")
        first = subprocess.Popen([BIN, "train", "--log", os.path.join(DATA, CLIP_REL), "--out", out] + TRAIN_FLAGS,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.procs.append(first)
        wait_for(lambda: os.path.exists(os.path.join(out, ".train.lock")), 60, "the first trainer's lock")
        second = subprocess.run([BIN, "train", "--log", os.path.join(DATA, CLIP_REL), "--out", out, "--resume"]
                                + TRAIN_FLAGS, capture_output=True, text=True, timeout=60)
        self.assertEqual(second.returncode, 2, second.stderr)
        self.assertIn(".train.lock", second.stderr)
        self.assertIn(f"pid {first.pid}", second.stderr)
        self.assertIsNone(first.poll())  # the first one goes on undisturbed
        first.send_signal(signal.SIGTERM)
        self.assertEqual(first.wait(timeout=120), 128 + signal.SIGTERM)
        # The lock went with its holder: the directory can be resumed now.
        third = subprocess.run([BIN, "train", "--log", os.path.join(DATA, CLIP_REL), "--out", out, "--resume",
                                "--iterations", "1"], capture_output=True, text=True, timeout=300)
        self.assertNotIn(".train.lock", third.stderr)

    def test_a_jobs_trainer_dies_with_its_server_and_the_restart_resumes_it(self):
        state = os.path.join(self.tmp, "state")

        def serve():
            p = subprocess.Popen([BIN, "serve", "--listen", "127.0.0.1:0", "--data-root", DATA, "--state-dir", state,
                                  "--backend", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            self.procs.append(p)
            line = p.stdout.readline()
            self.assertIn("listening on", line)
            client = streetsim.Client(line.strip().rsplit(" ", 1)[1])
            client.wait_for_ready(10)
            return p, client

        server, client = serve()
        job = client.train(CLIP_REL, scene_name="owned", max_iterations=1000000, resolution_scale=0.05,
                           field="static", holdout_every=0)
        work = os.path.join(state, "jobs", job.job_id, "work")

        def training():
            j = client.get_job(job.job_id)
            return j.progress.stage == "train" and j.progress.iteration >= 30

        wait_for(training, 240, "the job's trainer to pass iteration 30")
        pids = trainer_pids(work)
        self.assertEqual(len(pids), 1, pids)
        server.kill()  # kill -9: no chance to stop its children itself
        server.wait()
        wait_for(lambda: not alive(pids[0]), 120, f"the orphaned trainer {pids[0]} to end")
        self.assertTrue(os.path.exists(os.path.join(work, "checkpoint.bin")))  # it checkpointed on its way out
        with open(os.path.join(work, "checkpoint.json")) as f:
            stopped_at = int(re.search(r'"iteration":\s*(\d+)', f.read()).group(1))
        self.assertGreaterEqual(stopped_at, 30)

        server, client = serve()
        wait_for(lambda: client.get_job(job.job_id).progress.iteration > stopped_at, 240,
                 "the restarted server's trainer to go on from the checkpoint")
        j = client.get_job(job.job_id)
        self.assertEqual(j.attempts, 2)
        self.assertEqual(len(trainer_pids(work)), 1)  # one writer
        client.cancel_job(job.job_id)
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)


if __name__ == "__main__":
    unittest.main()
