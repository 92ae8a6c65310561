"""`contact-graspnet`: the Contact-GraspNet baseline (Sundermeyer et al., ICRA 2021), out of process.

Contact-GraspNet runs in its own Python environment -- its pins (numpy<2, torch-geometric 2.4.0, a
torch-cluster built from source) clash with sgjax's numpy 2 stack -- through the runner script
`eval/cgn_runner.py`, started once per method with the interpreter named by the environment variable
SGJAX_CGN_PYTHON and kept alive (model loaded once, one request per plan). Without that variable, or
when its environment has no `cgn_pytorch`, the method is unavailable and says how to set it up.

Setting up the environment (measured on a 2-core CPU machine: /work/shared/notes/contact-graspnet-on-cpu.md):

    python3.11 -m venv ~/cgn-env
    ~/cgn-env/bin/pip install torch==2.13.0             # the CPU wheel; a CUDA wheel works as well
    ~/cgn-env/bin/pip install "numpy<2" torch-geometric==2.4.0 scipy pyyaml trimesh meshcat importlib-resources tqdm
    FORCE_ONLY_CPU=1 MAX_JOBS=2 ~/cgn-env/bin/pip install --no-build-isolation --no-deps torch-cluster==1.6.3   # ~10 min
    ~/cgn-env/bin/pip install --no-deps cgn-pytorch==0.4.3
    export SGJAX_CGN_PYTHON=~/cgn-env/bin/python
    sgjax declutter --method contact-graspnet ...

(torch-geometric 2.8 ignores torch-cluster and needs pyg-lib, which PyPI lacks; cgn-pytorch's own
pins conflict, hence --no-deps; meshcat is imported when cgn_pytorch loads.)

What the adapter sends: the observation's finite points in the world frame (z up, metres) with
their mean subtracted -- CGN's bundled scenes are stored that way, and a camera-frame or millimetre
cloud gives confident nonsense. The cloud is made like SuperGrasp's Stage-2 scene cloud: cropped to
the benchmark's workspace (+ 5 cm), one point per 3 mm voxel, then at most `max_points` (a seeded
uniform subsample; CGN's inference on 20,000 points takes ~1 s on CPU). Without the crop and grid the
20,000 points were ~90 % table, 8 % objects. With it goes the object mask (labels >= 0, so grasps on
the table are dropped). The seed reaches libc srand in the runner (torch-cluster's fps uses rand()).
The runner keeps its reply channel clean: cgn_pytorch's own prints go to its stderr.

Grasp frames: CGN returns Panda hand poses: columns x = the baseline (closing) direction, y = z cross
x, z = the approach direction; the origin is the hand frame, `gripper_depth` = 0.1034 m behind the
contact baseline, i.e. behind the fingertips (`inference()` uses that depth whatever its config
says). The sgjax gripper (`sgjax/geometry/gripper.py`) has the same axes (x closing, z approach, y = z x x)
and its origin at the palm-side face of the closing region, its fingertips `finger_length` ahead.
So the rotation is kept and the origin moved along the approach axis until the fingertips coincide:

    t_sgjax = t_cgn + mean + (gripper_depth - spec.finger_length) * z

(the Panda's finger pads are ~4.6 cm long, ours `finger_length` = 5 cm, so the two closing regions
nearly coincide). cgn-pytorch returns no widths: the hand opens fully (`spec.max_opening`, 8 cm, the
Panda's stroke too) and the simulator closes it. The most confident grasp is executed; none above the
threshold -> no grasp. Timing: the network is end-to-end, so stage1_s = 0 and stage2_s = total_s
(the request's wall time, transfer included); info carries CGN's own inference time.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from eval.protocol import Decision, MethodUnavailable, near_grasps
from sgjax.geometry import pointcloud
from sgjax.geometry.gripper import GripperSpec

ENV_VAR = "SGJAX_CGN_PYTHON"
RUNNER = Path(__file__).resolve().with_name("cgn_runner.py")
SETUP = (
    "Contact-GraspNet needs its own Python environment (numpy<2, torch CPU, torch-geometric 2.4.0, torch-cluster "
    "1.6.3 built from source, cgn-pytorch 0.4.3 with --no-deps): build it as the docstring of "
    f"eval/contact_graspnet.py shows and set {ENV_VAR} to its python"
)


@dataclasses.dataclass(frozen=True)
class CGNConfig:
    """threshold: CGN's confidence threshold; max_points, voxel, scene_bounds: the cloud sent, made like
    SuperGrasp's Stage-2 scene cloud (`sgjax.geometry.pointcloud.scene_cloud`: optional (lo [3], hi [3]) crop,
    one point per voxel, then a seeded subsample); the method's factory crops to the benchmark's
    workspace as SuperGrasp does; gripper_depth: CGN's hand-origin-to-fingertip distance (Panda, m);
    timeout_s: per request (the first includes loading the model); spec: the sgjax gripper the poses
    are converted to."""

    threshold: float = 0.5
    max_points: int = 20000
    voxel: float = 0.003
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    gripper_depth: float = 0.1034
    timeout_s: float = 600.0
    spec: GripperSpec = dataclasses.field(default_factory=GripperSpec)


def missing() -> str | None:
    """None when Contact-GraspNet can run here, else why not and how to set it up."""
    python = os.environ.get(ENV_VAR, "").strip()
    if not python:
        return f"not available yet: {ENV_VAR} is not set. {SETUP}"
    return _probe(python, os.environ.get("PYTHONPATH", ""))


@functools.lru_cache(maxsize=8)
def _probe(python: str, pythonpath: str) -> str | None:
    """Whether `python` runs and finds cgn_pytorch (cached per interpreter and PYTHONPATH)."""
    del pythonpath  # part of the cache key only: it changes what the interpreter finds
    exe = shutil.which(os.path.expanduser(python))
    if exe is None:
        return f"{ENV_VAR}={python} is not an executable Python. {SETUP}"
    check = "import importlib.util, sys; sys.exit(0 if importlib.util.find_spec('cgn_pytorch') else 3)"
    try:
        done = subprocess.run([exe, "-c", check], capture_output=True, text=True, timeout=120, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{ENV_VAR}={python} could not be run ({type(exc).__name__}: {exc}). {SETUP}"
    if done.returncode == 3:
        return f"the environment of {ENV_VAR}={python} has no cgn_pytorch module. {SETUP}"
    if done.returncode != 0:
        return f"{ENV_VAR}={python} failed ({done.stderr.strip()[-300:]}). {SETUP}"
    return None


def cgn_to_sgjax(grasps: np.ndarray, offset, spec: GripperSpec, gripper_depth: float = 0.1034) -> np.ndarray:
    """CGN Panda grasp poses [K, 4, 4] (in a frame shifted by -offset) -> sgjax gripper poses [K, 4, 4]
    in the world: same rotation, origin moved to the palm-side face of the closing region with the
    fingertips where the Panda's are (see the module doc)."""
    grasps = np.asarray(grasps, np.float64).reshape(-1, 4, 4)
    out = np.tile(np.eye(4), (len(grasps), 1, 1))
    u, _, vt = np.linalg.svd(grasps[:, :3, :3])  # the nearest rotation (CGN's axes are float32 estimates)
    u[:, :, -1] *= np.sign(np.linalg.det(u @ vt))[:, None]
    out[:, :3, :3] = u @ vt
    out[:, :3, 3] = grasps[:, :3, 3] + np.asarray(offset, np.float64) + (gripper_depth - spec.finger_length) * out[:, :3, 2]
    return out


class ContactGraspNetMethod:
    """The benchmark method; holds one runner process (closed by `close()` or at exit)."""

    name = "contact-graspnet"

    def __init__(self, config: CGNConfig | None = None, python: str | None = None):
        self.config = config or CGNConfig()
        reason = missing() if python is None else _probe(python, os.environ.get("PYTHONPATH", ""))
        if reason is not None:
            raise MethodUnavailable(f"method {self.name!r} cannot run: {reason}")
        self.python = shutil.which(os.path.expanduser(python or os.environ[ENV_VAR].strip()))
        self._dir = tempfile.TemporaryDirectory(prefix="sgjax-cgn-")
        self._stderr = open(os.path.join(self._dir.name, "runner.log"), "w+")  # noqa: SIM115 - lives with the process
        self._process: subprocess.Popen | None = None
        self.load_s = None

    # -- the runner process -----------------------------------------------------------------

    def _runner(self) -> subprocess.Popen:
        if self._process is not None and self._process.poll() is None:
            return self._process
        self._process = subprocess.Popen(
            [self.python, str(RUNNER), "--serve"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=self._stderr, text=True, bufsize=1,
        )
        first = self._read()
        if not first.get("ready"):
            self.close()
            raise RuntimeError(f"the Contact-GraspNet runner did not start: {first.get('error')}{self._log_tail()}")
        self.load_s = first.get("load_s")
        return self._process

    def _read(self) -> dict:
        line = self._process.stdout.readline()
        if not line:
            code = self._process.wait(timeout=10)
            raise RuntimeError(f"the Contact-GraspNet runner exited (code {code}){self._log_tail()}")
        try:
            return json.loads(line)
        except json.JSONDecodeError:
            raise RuntimeError(f"the Contact-GraspNet runner wrote a line that is not a reply: {line[:200]!r}"
                               f"{self._log_tail()}") from None

    def _log_tail(self) -> str:
        self._stderr.flush()
        self._stderr.seek(0)
        tail = self._stderr.read()[-2000:].strip()
        self._stderr.seek(0, os.SEEK_END)
        return f"; its stderr ends with:\n{tail}" if tail else ""

    def _request(self, request: str, reply: str) -> dict:
        process = self._runner()
        process.stdin.write(json.dumps({"input": request, "output": reply}) + "\n")
        process.stdin.flush()
        answer = self._read()
        if not answer.get("ok"):
            raise RuntimeError(f"Contact-GraspNet failed: {answer.get('error')}{self._log_tail()}")
        return answer

    def close(self) -> None:
        """Stop the runner (the next plan starts a new one)."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.stdin.close()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def __del__(self):
        with contextlib.suppress(Exception):  # at interpreter shutdown, parts may already be gone
            self.close()
            self._stderr.close()
            self._dir.cleanup()

    # -- the method ---------------------------------------------------------------------------

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        cfg = self.config
        start = time.perf_counter()
        points, mask, labels = pointcloud.scene_cloud(
            np.asarray(points, np.float64).reshape(-1, 3), cfg.max_points, cfg.voxel,
            np.asarray(labels).reshape(-1), cfg.scene_bounds, seed)
        points, labels = points[mask].astype(np.float64), labels[mask]
        obj = labels >= 0
        if not obj.any():
            elapsed = time.perf_counter() - start
            return Decision(None, 0.0, 0.0, "no object points", _timing(elapsed), {"points": len(points)})
        mean = points.mean(axis=0)
        request = os.path.join(self._dir.name, "request.npz")
        reply = os.path.join(self._dir.name, "reply.npz")
        np.savez(request, points=(points - mean).astype(np.float32), obj_mask=obj.astype(np.float32),
                 seed=np.int64(int(seed) & 0xFFFFFFFF), threshold=np.float64(cfg.threshold))
        answer = self._request(request, reply)
        with np.load(reply, allow_pickle=False) as data:
            grasps, confidence = data["grasps"], data["confidence"]
        elapsed = time.perf_counter() - start
        info = {"points": len(points), "grasps": len(confidence), "inference_s": float(answer.get("inference_s", 0.0))}
        if len(confidence) == 0:
            return Decision(None, 0.0, 0.0, f"Contact-GraspNet found no grasp above confidence {cfg.threshold:g}",
                            _timing(elapsed), info)
        poses = cgn_to_sgjax(grasps, mean, cfg.spec, cfg.gripper_depth)
        avoided = near_grasps(poses, avoid, cfg.spec)
        info["avoided"] = int(avoided.sum())
        if avoided.all():
            return Decision(None, 0.0, 0.0, f"all {len(confidence)} grasps are the same grasp as one that already failed",
                            _timing(elapsed), info)
        best = int(np.argmax(np.where(avoided, -np.inf, confidence)))
        pose = poses[best]
        return Decision(pose, cfg.spec.max_opening, float(confidence[best]), "", _timing(elapsed), info)


def _timing(total: float) -> dict:
    return {"stage1_s": 0.0, "stage2_s": total, "total_s": total}
