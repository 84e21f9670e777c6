"""The demo's pipeline (examples/demo/pipeline.py, what ./scripts/demo runs) at a tiny size on the
bundled KITTI clip, with the real binary: it must really train (a field run to its last iteration),
evaluate, serve and drive, and its report must open in a real browser (Debian's chromium,
headless) with every image decoded and no script error.

Run by ctest with PYTHONPATH=client/python:<build>/python, STREETSIM_BIN, STREETSIM_SOURCE_DIR and
STREETSIM_DATA_DIR.
"""
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import unittest

SOURCE = os.environ.get("STREETSIM_SOURCE_DIR", "../..")
CLIP = os.path.join(os.environ.get("STREETSIM_DATA_DIR", os.path.join(SOURCE, "..", "shared", "data")),
                    "kitti_raw", "2011_09_26", "2011_09_26_drive_sfnd_sync")


def chromium_selfcheck(html_path, tmp):
    """Loads the page in headless Chromium and returns its <body data-selfcheck> after load."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise unittest.SkipTest("chromium is not installed (scripts/install-deps installs it)")
    r = subprocess.run([chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                        f"--user-data-dir={os.path.join(tmp, 'chromium-profile')}", "--virtual-time-budget=15000",
                        "--dump-dom", "file://" + os.path.abspath(html_path)],
                       capture_output=True, text=True, timeout=180)
    m = re.search(r'<body[^>]*data-selfcheck="([^"]*)"', r.stdout)
    if m is None:
        raise AssertionError(f"chromium returned no page (exit {r.returncode}): {r.stderr[-2000:]}")
    return m.group(1)


def avi_frame_count(path):
    with open(path, "rb") as f:
        data = f.read()
    assert data[:4] == b"RIFF" and data[8:12] == b"AVI ", "not an AVI file"
    return struct.unpack("<I", data[data.index(b"avih") + 8 + 16: data.index(b"avih") + 8 + 20])[0]


class DemoPipelineTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        if not os.path.isdir(CLIP):
            raise unittest.SkipTest(f"no KITTI clip at {CLIP}")
        cls.tmp = tempfile.mkdtemp(prefix="streetsim_demo_")
        cls.out = os.path.join(cls.tmp, "out")
        cls.proc = subprocess.run(
            [sys.executable, os.path.join(SOURCE, "examples", "demo", "pipeline.py"), "--bin",
             os.environ.get("STREETSIM_BIN", "streetsim"), "--log", CLIP, "--out", cls.out, "--preset", "tiny"],
            capture_output=True, text=True, timeout=900)
        if cls.proc.returncode == 0:
            with open(os.path.join(cls.out, "summary.json")) as f:
                cls.summary = json.load(f)

    @classmethod
    def tearDownClass(cls):
        if hasattr(cls, "tmp"):
            shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_pipeline_succeeds(self):
        self.assertEqual(self.proc.returncode, 0, self.proc.stdout[-3000:] + self.proc.stderr[-3000:])

    def test_it_really_trains_a_dynamic_scene(self):
        self.test_pipeline_succeeds()
        s = self.summary
        self.assertEqual(s["train_iterations"], 40)  # the tiny preset's --iterations, reached
        self.assertGreater(s["train_wall_s"], 0)
        scene = s["outputs"]["scene"]
        for f in ("scene.ply", "scene.json", "field.bin"):
            self.assertTrue(os.path.isfile(os.path.join(scene, f)), f)
        self.assertTrue(s["dynamic"])  # served with its field: the log's vehicles move
        with open(os.path.join(self.out, "train_curve.json")) as f:
            rows = json.load(f)["rows"]
        self.assertGreaterEqual(len(rows), 4)
        self.assertEqual([r[1] for r in rows], sorted(r[1] for r in rows))

    def test_summary_holds_the_metrics_and_outputs(self):
        self.test_pipeline_succeeds()
        s = self.summary
        for key in ("heldout_psnr", "heldout_ssim", "train_wall_s", "steps", "step_p50_ms", "dynamic", "outputs"):
            self.assertIn(key, s)
        self.assertGreater(s["heldout_psnr"], 8.0)  # a trained scene, not noise
        self.assertLess(s["heldout_psnr"], 60.0)
        self.assertGreater(s["heldout_views"], 0)
        self.assertEqual(s["steps"], 6)
        self.assertGreater(s["step_p50_ms"], 0)
        for key, path in s["outputs"].items():
            self.assertTrue(os.path.exists(path), f"{key}: {path}")

    def test_videos_hold_every_step(self):
        self.test_pipeline_succeeds()
        self.assertEqual(avi_frame_count(self.summary["outputs"]["video"]), self.summary["steps"])
        self.assertEqual(avi_frame_count(self.summary["outputs"]["heldout_video"]), self.summary["heldout_views"])

    def test_report_opens_in_a_browser(self):
        self.test_pipeline_succeeds()
        report = self.summary["outputs"]["report"]
        with open(report) as f:
            page = f.read()
        self.assertNotIn("src=\"file:", page)  # self-contained
        self.assertNotIn("src=\"http", page)
        self.assertEqual(chromium_selfcheck(report, self.tmp), "ok")

    def test_the_browser_check_catches_a_broken_image_and_a_script_error(self):
        self.test_pipeline_succeeds()
        with open(self.summary["outputs"]["report"]) as f:
            page = f.read()
        broken = os.path.join(self.tmp, "broken_image.html")
        with open(broken, "w") as f:
            f.write(page.replace("base64,", "base64,AAAA", 1))
        self.assertTrue(chromium_selfcheck(broken, self.tmp).startswith("failed: "))
        erring = os.path.join(self.tmp, "script_error.html")
        with open(erring, "w") as f:
            f.write(page.replace("</body>", "<script>undefinedFunction();</script></body>", 1))
        self.assertIn("script", chromium_selfcheck(erring, self.tmp))

    def test_a_failing_step_fails_the_pipeline_with_its_reason(self):
        out = os.path.join(self.tmp, "missing_log")
        r = subprocess.run([sys.executable, os.path.join(SOURCE, "examples", "demo", "pipeline.py"), "--bin",
                            os.environ.get("STREETSIM_BIN", "streetsim"), "--log", os.path.join(self.tmp, "no_such_log"),
                            "--out", out, "--preset", "tiny"], capture_output=True, text=True, timeout=120)
        self.assertEqual(r.returncode, 1)
        self.assertIn("demo: train failed", r.stderr)
        self.assertFalse(os.path.exists(os.path.join(out, "summary.json")))


if __name__ == "__main__":
    unittest.main()
