"""What streetsim's deployment relies on (docs/deploy.md), checked on the files themselves.

The Kubernetes overlays are built with `kubectl kustomize` (the binary in $KUBECTL, default `kubectl`
on PATH: scripts/install-deps installs Debian's kubernetes-client where there is none; both its
kustomize v2.0.3 and a current kubectl's v5 must build them) and their output is checked against
what `streetsim serve` and `streetsim train` expect: ports, gRPC probes, the drain's time, volumes
and flags, the replica name, the headless Service, GPU settings, resources. The training Job's
shell is run for real with /bin/sh and a stand-in `streetsim` (resume, publish, SIGTERM passed on).
The compose file and the Dockerfiles' runtime stages are checked too. Debian's /usr/bin/python3
with python3-yaml; no build, no cluster, no Docker.
"""

import os
import re
import shutil
import signal
import stat
import subprocess
import tempfile
import textwrap
import time
import unittest
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
K8S = REPO / "docker" / "k8s"
KUBECTL = os.environ.get("KUBECTL", "kubectl")

# docs/server.md "Running": on SIGTERM in-flight calls get 10 s; then a running training job's
# trainer gets up to 30 s for its checkpoint (server/job_runner.cc, 1500 polls of 20 ms).
DRAIN_S = 10
TRAINER_STOP_S = 30
# docs/training.md "Stopping": the trainer's checkpoint on SIGTERM; a KITTI one takes ~20 s.
CHECKPOINT_S = 20
STATE_PVC = "streetsim-state"
LOGS_PVC = "streetsim-logs"
HEADLESS = "streetsim-pods"
SERVING = {"cpu": "overlays/cpu", "gpu": "overlays/gpu"}
TRAINING = {"cpu": "overlays/cpu/train", "gpu": "overlays/gpu/train"}
BACKEND = {"cpu": "cpu", "gpu": "vulkan"}

_builds = {}


def kustomize(rel):
    """The objects `kubectl kustomize docker/k8s/<rel>` prints, built once per run."""
    if rel in _builds:
        return _builds[rel]
    exe = shutil.which(KUBECTL)
    if exe is None:
        raise AssertionError(
            f"kubectl not found (KUBECTL={KUBECTL!r}): these checks build the overlays with `kubectl "
            f"kustomize`; ./scripts/install-deps installs Debian's kubernetes-client when no kubectl is "
            f"on PATH, or point KUBECTL at one")
    r = subprocess.run([exe, "kustomize", str(K8S / rel)], capture_output=True, text=True, timeout=60)
    if r.returncode != 0:
        raise AssertionError(f"{exe} kustomize docker/k8s/{rel} exited {r.returncode}:\n{r.stderr}")
    docs = [d for d in yaml.safe_load_all(r.stdout) if d]
    _builds[rel] = docs
    return docs


def find(docs, kind, name=None):
    found = [d for d in docs if d["kind"] == kind and (name is None or d["metadata"]["name"] == name)]
    if len(found) != 1:
        raise AssertionError(f"expected one {kind} {name or ''} in the build, found {len(found)}")
    return found[0]


def flag(args, name):
    """The value of --name in an argument list (`--name V` or `--name=V`); None if absent."""
    values = []
    for i, a in enumerate(args):
        if a == name and i + 1 < len(args):
            values.append(args[i + 1])
        elif a.startswith(name + "="):
            values.append(a[len(name) + 1:])
    if len(values) > 1:
        raise AssertionError(f"{name} given {len(values)} times in {args}")
    return values[0] if values else None


def port_of(listen):
    host, _, port = listen.rpartition(":")
    return int(port)


def env_of(container):
    names = [e["name"] for e in container.get("env", [])]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise AssertionError(f"container {container['name']}: env {sorted(dup)} set more than once")
    return {e["name"]: e for e in container.get("env", [])}


def mounts_to_claims(pod_spec, container):
    """{mountPath: (claimName, mount readOnly, claim readOnly)} of a container's PVC mounts."""
    volumes = {v["name"]: v for v in pod_spec.get("volumes", [])}
    out = {}
    for m in container.get("volumeMounts", []):
        v = volumes[m["name"]]
        if "persistentVolumeClaim" in v:
            pvc = v["persistentVolumeClaim"]
            out[m["mountPath"]] = (pvc["claimName"], bool(m.get("readOnly")), bool(pvc.get("readOnly")))
    return out


_UNITS = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12, "m": 1e-3}


def quantity(q):
    m = re.fullmatch(r"([0-9.]+)([A-Za-z]*)", str(q))
    if not m or (m.group(2) and m.group(2) not in _UNITS):
        raise AssertionError(f"unreadable quantity {q!r}")
    return float(m.group(1)) * (_UNITS[m.group(2)] if m.group(2) else 1)


def all_containers(docs):
    for d in docs:
        spec = d.get("spec", {})
        pod = spec.get("template", {}).get("spec")
        if pod is None:
            continue
        for c in pod.get("initContainers", []) + pod.get("containers", []):
            yield d, pod, c


class ServingStackTest(unittest.TestCase):
    """The StatefulSet, its Services and volumes, per overlay."""

    def each(self):
        """(flavour, docs, StatefulSet, pod spec, container) per overlay (and the overlay's path)."""
        for flavour, rel in SERVING.items():
            docs = kustomize(rel)
            sts = find(docs, "StatefulSet", "streetsim")
            pod = sts["spec"]["template"]["spec"]
            self.assertEqual(len(pod["containers"]), 1)
            yield rel, (flavour, docs, sts, pod, pod["containers"][0])

    def test_listen_port_is_the_container_port_and_the_services_target(self):
        for rel, (_, docs, sts, _, c) in self.each():
            with self.subTest(overlay=rel):
                self.assertEqual(c["args"][0], "serve", "the image's entrypoint is streetsim: args start with serve")
                listen = flag(c["args"], "--listen")
                self.assertIsNotNone(listen, "--listen (the default, 127.0.0.1, is unreachable from outside the pod)")
                self.assertEqual(listen.rpartition(":")[0], "0.0.0.0")
                port = port_of(listen)
                self.assertEqual([p["containerPort"] for p in c["ports"]], [port])
                services = [d for d in docs if d["kind"] == "Service"]
                self.assertEqual(sorted(s["metadata"]["name"] for s in services), ["streetsim", HEADLESS])
                labels = sts["spec"]["template"]["metadata"]["labels"]
                for s in services:
                    self.assertEqual([p["targetPort"] for p in s["spec"]["ports"]], [port], s["metadata"]["name"])
                    selector = s["spec"]["selector"]
                    self.assertTrue(selector.items() <= labels.items(), f"{s['metadata']['name']} selects the pods")
                    self.assertEqual(selector.get("app.kubernetes.io/component"), "server")
                self.assertEqual(sts["spec"]["selector"]["matchLabels"].items() <= labels.items(), True)

    def test_headless_service_names_the_pods(self):
        for rel, (_, docs, sts, _, _) in self.each():
            with self.subTest(overlay=rel):
                self.assertEqual(sts["spec"]["serviceName"], HEADLESS)
                headless = find(docs, "Service", HEADLESS)
                self.assertEqual(headless["spec"].get("clusterIP"), "None")
                self.assertIs(headless["spec"].get("publishNotReadyAddresses", False), False)
                balanced = find(docs, "Service", "streetsim")
                self.assertNotEqual(balanced["spec"].get("clusterIP"), "None")
                self.assertEqual(sts["spec"]["replicas"], 3)
                # kustomize v2.0.3's commonLabels would otherwise invent a malformed volumeClaimTemplates.
                self.assertIsInstance(sts["spec"].get("volumeClaimTemplates", []), list)

    def test_probes_are_grpc_on_the_listen_port(self):
        for rel, (_, _, _, _, c) in self.each():
            with self.subTest(overlay=rel):
                port = port_of(flag(c["args"], "--listen"))
                for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                    self.assertIn(probe, c)
                    p = c[probe]
                    self.assertEqual(p.get("grpc"), {"port": port}, f"{probe}: grpc.health.v1, service ''")
                    for other in ("httpGet", "tcpSocket", "exec"):
                        self.assertNotIn(other, p, probe)
                startup = c["startupProbe"]
                self.assertGreaterEqual(startup["periodSeconds"] * startup["failureThreshold"], 120,
                                        "a generous startup (scans of network volumes)")
                live = c["livenessProbe"]
                self.assertGreater(live["periodSeconds"] * live["failureThreshold"], DRAIN_S)

    def test_grace_period_covers_prestop_and_drain(self):
        for rel, (_, _, _, pod, c) in self.each():
            with self.subTest(overlay=rel):
                command = c["lifecycle"]["preStop"]["exec"]["command"]
                self.assertEqual(command[0], "/bin/sleep")
                pre_stop = float(command[1])
                self.assertGreater(pre_stop, 0)
                grace = pod["terminationGracePeriodSeconds"]
                self.assertGreater(grace, pre_stop + DRAIN_S, "preStop counts against the grace period")
                self.assertGreater(grace, pre_stop + DRAIN_S + TRAINER_STOP_S,
                                   "a server's own training job gets up to 30 s for its checkpoint")

    def test_volumes_match_the_flags(self):
        for rel, (_, docs, _, pod, c) in self.each():
            with self.subTest(overlay=rel):
                mounts = mounts_to_claims(pod, c)
                state, data = flag(c["args"], "--state-dir"), flag(c["args"], "--data-root")
                self.assertEqual(mounts.get(state), (STATE_PVC, False, False), "--state-dir: the shared state PVC, writable")
                self.assertEqual(mounts.get(data), (LOGS_PVC, True, True), "--data-root: the logs PVC, read-only")
                for name in (STATE_PVC, LOGS_PVC):
                    pvc = find(docs, "PersistentVolumeClaim", name)
                    self.assertIn("ReadWriteMany", pvc["spec"]["accessModes"], f"{name}: pods on many nodes")
                    self.assertIn("storage", pvc["spec"]["resources"]["requests"])
                    self.assertNotIn("storageClassName", pvc["spec"], "overlays or users choose the class")

    def test_replica_name_is_the_pod_name(self):
        for rel, (_, _, _, pod, c) in self.each():
            with self.subTest(overlay=rel):
                env = env_of(c)
                self.assertEqual(env["STREETSIM_REPLICA"].get("valueFrom"), {"fieldRef": {"fieldPath": "metadata.name"}})
                threads = env["STREETSIM_THREADS"]["valueFrom"]["resourceFieldRef"]
                self.assertEqual(threads["containerName"], c["name"])
                self.assertEqual(threads["resource"], "limits.cpu")
                self.assertIs(pod.get("enableServiceLinks"), False, "no STREETSIM_SERVICE_*/STREETSIM_PORT* variables")

    def test_backend_and_gpu_per_overlay(self):
        for rel, (flavour, _, _, pod, c) in self.each():
            with self.subTest(overlay=rel):
                self.assertEqual(flag(c["args"], "--backend"), BACKEND[flavour])
                limits = c["resources"]["limits"]
                if flavour == "gpu":
                    self.assertEqual(int(limits.get("nvidia.com/gpu", 0)), 1)
                    self.assertIn("graphics", env_of(c)["NVIDIA_DRIVER_CAPABILITIES"]["value"].split(","))
                    self.assertIn("gpu", c["image"])
                else:
                    self.assertNotIn("nvidia.com/gpu", limits)
                    self.assertNotIn("gpu", c["image"])

    def test_disruption_budget(self):
        for rel, (_, docs, sts, _, _) in self.each():
            with self.subTest(overlay=rel):
                pdb = find(docs, "PodDisruptionBudget", "streetsim")
                self.assertEqual(pdb["spec"]["maxUnavailable"], 1)
                labels = sts["spec"]["template"]["metadata"]["labels"]
                self.assertTrue(pdb["spec"]["selector"]["matchLabels"].items() <= labels.items())


class ResourcesTest(unittest.TestCase):
    def test_every_container_has_requests_and_limits(self):
        for rel in list(SERVING.values()) + list(TRAINING.values()):
            for d, _, c in all_containers(kustomize(rel)):
                with self.subTest(overlay=rel, kind=d["kind"], container=c["name"]):
                    res = c.get("resources", {})
                    for part in ("requests", "limits"):
                        for r in ("cpu", "memory"):
                            self.assertIn(r, res.get(part, {}), f"{part}.{r}")
                    for r in ("cpu", "memory"):
                        self.assertLessEqual(quantity(res["requests"][r]), quantity(res["limits"][r]), r)
                    # The demo's trainer peaked at 1.7 GB RSS (docs/benchmarks.md "Demo"); the servers
                    # run their own jobs' trainers in their container.
                    self.assertGreaterEqual(quantity(res["limits"]["memory"]), 1.7e9)


class TrainingJobTest(unittest.TestCase):
    """The training Job template against the servers it publishes for."""

    def each(self):
        """(flavour, Job, pod spec, container, the overlay's StatefulSet) per overlay (and its path)."""
        for flavour, rel in TRAINING.items():
            docs = kustomize(rel)
            self.assertEqual([d["kind"] for d in docs], ["Job"], "the template is the Job alone")
            job = find(docs, "Job", "streetsim-train")
            pod = job["spec"]["template"]["spec"]
            self.assertEqual(len(pod["containers"]), 1)
            server = find(kustomize(SERVING[flavour]), "StatefulSet", "streetsim")
            yield rel, (flavour, job, pod, pod["containers"][0], server)

    def test_same_image_and_volumes_as_the_servers(self):
        for rel, (_, _, pod, c, server) in self.each():
            with self.subTest(overlay=rel):
                spod = server["spec"]["template"]["spec"]
                sc = spod["containers"][0]
                self.assertEqual(c["image"], sc["image"])
                self.assertEqual(mounts_to_claims(pod, c), mounts_to_claims(spod, sc))
                env = env_of(c)
                self.assertEqual(env["DATA_ROOT"]["value"], flag(sc["args"], "--data-root"))
                self.assertEqual(env["STATE_DIR"]["value"], flag(sc["args"], "--state-dir"))
                threads = env["STREETSIM_THREADS"]["valueFrom"]["resourceFieldRef"]
                self.assertEqual(threads["containerName"], c["name"])
                self.assertIs(pod.get("enableServiceLinks"), False)

    def test_retries_resume(self):
        for rel, (_, job, pod, c, _) in self.each():
            with self.subTest(overlay=rel):
                self.assertGreater(job["spec"]["backoffLimit"], 0, "a killed pod is replaced")
                self.assertIn(pod["restartPolicy"], ("OnFailure", "Never"))
                self.assertGreater(pod["terminationGracePeriodSeconds"], CHECKPOINT_S, "time for the checkpoint")
                self.assertEqual(c["command"][:2], ["/bin/sh", "-c"])
                script = c["command"][2]
                self.assertIn("--resume", script)
                self.assertIn("checkpoint.bin", script)
                self.assertIn("mv -T", script)
                self.assertNotIn("selector", job["spec"], "the Job's selector is generated")
                labels = job["spec"]["template"]["metadata"]["labels"]
                self.assertEqual(labels.get("app.kubernetes.io/component"), "train")

    def test_one_job_per_scene_through_a_kustomization(self):
        # The form docs/deploy.md gives: the overlay as a base, a name suffix, SCENE and LOG patched in.
        tmp = Path(tempfile.mkdtemp(prefix="streetsim-scene-"))
        self.addCleanup(shutil.rmtree, tmp, ignore_errors=True)
        (tmp / "kustomization.yaml").write_text(textwrap.dedent(f"""\
            bases:
            - {os.path.relpath(K8S / TRAINING['gpu'], tmp)}
            nameSuffix: -kitti-0001
            patchesStrategicMerge:
            - scene.yaml
            """))
        (tmp / "scene.yaml").write_text(textwrap.dedent("""\
            apiVersion: batch/v1
            kind: Job
            metadata:
              name: streetsim-train
            spec:
              template:
                spec:
                  containers:
                  - name: train
                    env:
                    - {name: SCENE, value: kitti-0001}
                    - {name: LOG, value: kitti_raw/2011_09_26/2011_09_26_drive_0001_sync}
                    - {name: TRAIN_ARGS, value: --iterations 30000 --checkpoint-every 250}
            """))
        job = find(kustomize(os.path.relpath(tmp, K8S)), "Job")
        self.assertEqual(job["metadata"]["name"], "streetsim-train-kitti-0001")
        pod = job["spec"]["template"]["spec"]
        env = env_of(pod["containers"][0])
        self.assertEqual(env["SCENE"]["value"], "kitti-0001")
        self.assertEqual(env["BACKEND"]["value"], "vulkan")
        template = find(kustomize(TRAINING["gpu"]), "Job")["spec"]["template"]["spec"]
        self.assertEqual(mounts_to_claims(pod, pod["containers"][0]),
                         mounts_to_claims(template, template["containers"][0]), "claims keep their names")

    def test_training_pods_stay_out_of_the_services(self):
        for rel, (flavour, _, pod, _, _) in self.each():
            with self.subTest(overlay=rel):
                labels = kustomize(TRAINING[flavour])[0]["spec"]["template"]["metadata"]["labels"]
                for s in (d for d in kustomize(SERVING[flavour]) if d["kind"] == "Service"):
                    self.assertFalse(s["spec"]["selector"].items() <= labels.items(), s["metadata"]["name"])

    def test_backend_and_gpu_per_overlay(self):
        scripts = set()
        for rel, (flavour, _, _, c, _) in self.each():
            with self.subTest(overlay=rel):
                scripts.add(c["command"][2])
                env = env_of(c)
                self.assertEqual(env["BACKEND"]["value"], BACKEND[flavour])
                self.assertIn('--backend "$BACKEND"', c["command"][2])
                gpus = int(c["resources"]["limits"].get("nvidia.com/gpu", 0))
                self.assertEqual(gpus, 1 if flavour == "gpu" else 0)
                if flavour == "gpu":
                    self.assertIn("graphics", env["NVIDIA_DRIVER_CAPABILITIES"]["value"].split(","))
        self.assertEqual(len(scripts), 1, "one script for both overlays")


# A stand-in for `streetsim train`: records its arguments, then does what TRAINER_MODE says.
FAKE_STREETSIM = textwrap.dedent("""\
    #!/bin/sh
    [ "$1" = train ] || { echo "fake streetsim: only train" >&2; exit 9; }
    printf '%s\\n' "$@" > "$FAKE_DIR/argv"
    out=""; prev=""
    for a in "$@"; do [ "$prev" = --out ] && out="$a"; prev="$a"; done
    mkdir -p "$out"
    case "$TRAINER_MODE" in
      ok) echo ply > "$out/scene.ply"; echo '{}' > "$out/scene.json"; echo ck > "$out/checkpoint.bin"; exit 0 ;;
      fail) exit 1 ;;
      wait-for-term)
        trap 'sleep 0.3; echo ck > "$out/checkpoint.bin"; echo stopped > "$FAKE_DIR/stopped"; exit 143' TERM
        echo started > "$FAKE_DIR/started"
        while :; do sleep 0.05; done ;;
    esac
    exit 8
    """)


class TrainingJobScriptTest(unittest.TestCase):
    """The Job's shell run with /bin/sh, a stand-in trainer and temporary volumes."""

    @classmethod
    def setUpClass(cls):
        job = find(kustomize(TRAINING["cpu"]), "Job", "streetsim-train")
        cls.command = job["spec"]["template"]["spec"]["containers"][0]["command"]

    def setUp(self):
        self.tmp = Path(tempfile.mkdtemp(prefix="streetsim-deploy-"))
        self.addCleanup(shutil.rmtree, self.tmp, ignore_errors=True)
        self.bin = self.tmp / "bin"
        self.bin.mkdir()
        fake = self.bin / "streetsim"
        fake.write_text(FAKE_STREETSIM)
        fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
        self.state, self.data = self.tmp / "state", self.tmp / "data"
        self.state.mkdir()
        (self.data / "logs" / "drive").mkdir(parents=True)

    def env(self, scene="drive1", mode="ok", train_args="--iterations 5 --seed 3"):
        return {"PATH": f"{self.bin}:/usr/bin:/bin", "FAKE_DIR": str(self.tmp), "TRAINER_MODE": mode,
                "SCENE": scene, "LOG": "logs/drive", "TRAIN_ARGS": train_args, "BACKEND": "cpu",
                "DATA_ROOT": str(self.data), "STATE_DIR": str(self.state)}

    def run_job(self, **kw):
        return subprocess.run(self.command, env=self.env(**kw), capture_output=True, text=True, timeout=30)

    def argv(self):
        return (self.tmp / "argv").read_text().split("\n")[:-1]

    def test_trains_then_publishes(self):
        r = self.run_job()
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertEqual(self.argv(), ["train", "--log", f"{self.data}/logs/drive", "--out",
                                       f"{self.state}/work/drive1", "--backend", "cpu", "--iterations", "5",
                                       "--seed", "3"])
        self.assertTrue((self.state / "scenes" / "drive1" / "scene.ply").exists())
        self.assertTrue((self.state / "scenes" / "drive1" / "scene.json").exists())
        self.assertFalse((self.state / "work" / "drive1").exists())

    def test_resumes_a_begun_run(self):
        for marker in ("checkpoint.bin", "clips.json"):
            with self.subTest(marker=marker):
                shutil.rmtree(self.state, ignore_errors=True)
                (self.state / "work" / "drive1").mkdir(parents=True)
                (self.state / "work" / "drive1" / marker).write_text("x")
                r = self.run_job()
                self.assertEqual(r.returncode, 0, r.stderr)
                self.assertEqual(self.argv()[-1], "--resume")
                self.assertTrue((self.state / "scenes" / "drive1" / "scene.ply").exists())

    def test_failed_training_publishes_nothing(self):
        r = self.run_job(mode="fail")
        self.assertEqual(r.returncode, 1)
        self.assertFalse((self.state / "scenes" / "drive1").exists())

    def test_published_scene(self):
        (self.state / "scenes" / "drive1").mkdir(parents=True)
        r = self.run_job()
        self.assertEqual(r.returncode, 0, "an attempt after the rename: done")
        self.assertFalse((self.tmp / "argv").exists(), "no training")
        (self.state / "work" / "drive1").mkdir(parents=True)
        r = self.run_job()
        self.assertEqual(r.returncode, 2, "another run's scene of that name: refused before training")
        self.assertFalse((self.tmp / "argv").exists())

    def test_bad_names(self):
        for scene in ("", "../x", "a/b", ".hidden", "a b"):
            with self.subTest(scene=scene):
                self.assertEqual(self.run_job(scene=scene).returncode, 2)
        self.assertFalse((self.tmp / "argv").exists())

    def test_sigterm_reaches_the_trainer_and_is_waited_for(self):
        p = subprocess.Popen(self.command, env=self.env(mode="wait-for-term"), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 10
            while not (self.tmp / "started").exists():
                self.assertLess(time.monotonic(), deadline, "the trainer did not start")
                self.assertIsNone(p.poll(), p.stderr.read() if p.poll() is not None else "")
                time.sleep(0.02)
            p.send_signal(signal.SIGTERM)
            _, err = p.communicate(timeout=10)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        self.assertEqual(p.returncode, 143, "the shell exits with the trainer's status, not by the signal")
        self.assertTrue((self.tmp / "stopped").exists(), "the trainer got SIGTERM")
        self.assertTrue((self.state / "work" / "drive1" / "checkpoint.bin").exists())
        self.assertFalse((self.state / "scenes" / "drive1").exists(), "a stopped run is not published")
        self.assertIn("exited 143", err)


def dockerfile_final_stage(path):
    text = path.read_text().replace("\\\n", " ")
    lines = [line for line in text.splitlines() if not line.lstrip().startswith("#")]
    last_from = max(i for i, line in enumerate(lines) if line.upper().startswith("FROM "))
    return lines[last_from:]


def apt_packages(stage):
    pkgs = set()
    for line in stage:
        for cmd in re.findall(r"apt-get install ([^&;]*)", line):
            pkgs |= {t for t in cmd.split() if not t.startswith("-")}
    return pkgs


class ImagesTest(unittest.TestCase):
    def test_runtime_stages(self):
        stages = {name: dockerfile_final_stage(REPO / "docker" / name) for name in ("Dockerfile", "Dockerfile.gpu")}
        pkgs = {name: apt_packages(stage) for name, stage in stages.items()}
        for name, stage in stages.items():
            with self.subTest(dockerfile=name):
                self.assertTrue(pkgs[name], "installs its runtime libraries")
                self.assertFalse({p for p in pkgs[name] if p.endswith("-dev")}, "no -dev packages at run time")
                self.assertIn("libvulkan1", pkgs[name])
                self.assertIn('ENTRYPOINT ["/usr/local/bin/streetsim"]', stage)
        self.assertIn("mesa-vulkan-drivers", pkgs["Dockerfile"])
        self.assertNotIn("mesa-vulkan-drivers", pkgs["Dockerfile.gpu"], "no lavapipe beside the GPU")
        libs = lambda s: {p for p in s if not re.match(r"(mesa-|libgl|libegl|libopengl|libgles)", p)}
        self.assertEqual(libs(pkgs["Dockerfile"]), libs(pkgs["Dockerfile.gpu"]), "the same binary's libraries")
        gpu_env = " ".join(line for line in stages["Dockerfile.gpu"] if line.startswith("ENV "))
        caps = re.search(r"NVIDIA_DRIVER_CAPABILITIES=(\S+)", gpu_env)
        self.assertIsNotNone(caps)
        self.assertIn("graphics", caps.group(1).split(","), "graphics: the toolkit's Vulkan ICD")
        self.assertIn("NVIDIA_VISIBLE_DEVICES=all", gpu_env)


class ComposeTest(unittest.TestCase):
    def test_services(self):
        compose = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())
        services = compose["services"]
        for name, backend in (("serve", "cpu"), ("serve-gpu", "vulkan")):
            with self.subTest(service=name):
                s = services[name]
                cmd = s["command"]
                self.assertEqual(cmd[0], "serve")
                self.assertEqual(flag(cmd, "--backend"), backend)
                port = port_of(flag(cmd, "--listen"))
                self.assertTrue(any(str(p).endswith(f":{port}") for p in s["ports"]), s["ports"])
                # SOURCE:TARGET[:MODE]; the source may hold ${VAR:-default}.
                volumes = dict(re.fullmatch(r"(?:.*):(/[^:]*)(?::(ro|rw))?", v).groups() for v in s["volumes"])
                self.assertEqual(volumes.get(flag(cmd, "--data-root"), "missing"), "ro")
                self.assertIn(flag(cmd, "--state-dir"), volumes)
                grace = int(re.fullmatch(r"(\d+)s", s["stop_grace_period"]).group(1))
                self.assertGreater(grace, DRAIN_S + TRAINER_STOP_S)
                self.assertEqual(s["healthcheck"]["test"][1:4], ["/usr/local/bin/streetsim", "scenes", "--server"])
        self.assertEqual(services["serve-gpu"]["profiles"], ["gpu"])
        self.assertEqual(services["cli"]["volumes"], services["serve"]["volumes"], "one-shot CLI on the same volumes")
        self.assertNotIn("restart", services["cli"], "`run --rm cli` and a restart policy conflict")
        devices = services["serve-gpu"]["deploy"]["resources"]["reservations"]["devices"]
        self.assertEqual(devices[0]["driver"], "nvidia")
        self.assertIn("graphics", devices[0]["capabilities"])


if __name__ == "__main__":
    unittest.main()
