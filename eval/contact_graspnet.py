"""`contact-graspnet`: the Contact-GraspNet baseline (Sundermeyer et al., ICRA 2021), out of process.

What runs is `cgn-pytorch` 0.4.3 (PyPI), a third-party PyTorch re-implementation with its own shipped
checkpoint -- not NVlabs' TensorFlow model. It runs in its own Python environment (its pins -- numpy<2,
torch-geometric 2.4.0, a torch-cluster built from source -- clash with sgjax's numpy 2 stack) through
the runner script `eval/cgn_runner.py`, started once per method and kept alive (model loaded once, one
request per plan). The interpreter is $SGJAX_CGN_PYTHON when set, else the environment that
`sgjax baselines setup contact-graspnet` builds at `$SGJAX_CACHE/envs/contact-graspnet`
(eval/cgn_setup.py); without either the method is unavailable and names that command.

What the adapter sends: the observation's finite points in the world frame (z up, metres) with their
mean subtracted -- the package's bundled scenes are stored that way, and a camera-frame or millimetre
cloud gives confident nonsense -- and the object mask. Which points (CGNConfig.scene_bounds, voxel) is
an input choice measured on seen-10 (docs/benchmark.md): the benchmark's workspace (+ 5 cm) on a 3 mm
grid as SuperGrasp's Stage-2 cloud, the crop without the grid, or the whole rendered cloud; then at
most `max_points` (a seeded uniform subsample; 20,000 is what the model was built for). The seed
reaches libc srand in the runner (torch-cluster's fps uses rand()).

The conversion (checked against the wheel's source, cgn_pytorch/contact_graspnet.py `CGN.forward` and
`build_6d_grasps`, gripper/control_points/panda_gripper_coords.yaml, and NVlabs' original):

  * CGN predicts, per sampled point c (a contact), the closing axis x, the approach z and the width w
    between the fingers, and places the Panda hand frame at  c - 0.1034 z + (w / 2) x.  0.1034 m is
    the hand frame to the *contact baseline*, the centre of the finger pads (`gripper_*_center_flat`,
    z = 0.1034), where the training contact rays start; the fingertips (`gripper_*_tip_flat`) are at
    z = 0.112204, i.e. 8.8 mm further. The sgjax gripper (sgjax/geometry/gripper.py: same axes, origin
    at the palm-side face of the closing region, fingertips `finger_length` ahead) gets its fingertips
    on the Panda's fingertip line and its closing region centred between the two contacts:

        centre  = c + offset + (w / 2) x                       (the middle of the contact baseline)
        t_sgjax = centre + (0.112204 - 0.1034 - finger_length) z

  * Width and centring: `cgn_pytorch.inference()` calls the model with gripper_width=0.08, and
    `CGN.forward` clamps the predicted width w to [-gripper_width, gripper_width / 2] = [-8, 4] cm
    *before* placing the hand at c + (w / 2) x, then returns relu(w); its training used forward's
    default 0.16 (clamp [-16, 8] cm). The width is SIGNED: its pose loss (ADD-S against the symmetric
    gripper) cannot tell (x, w) from (-x, -w), and 62 % of the confident grasps on seen-10 scenes have
    w < 0, and the object lies on the hand's side of the contact in 88 % of them (by relu(w): 40 %). The runner
    calls the model with 0.16 and returns the contacts and the signed widths (read off the hand poses);
    the closing region is centred between c and c + w x.
  * Opening: NVlabs' original opens to the predicted width + 5 mm (TEST.extra_opening), at most the
    stroke (CGNConfig.opening "predicted"). cgn-pytorch 0.4.3's |w| are far too small for that (median
    1.7 cm; a finger box holds observed target points in 96 % of its confident grasps), so by default the
    hand opens fully ("full": 20 %); docs/benchmark.md.
  * Table: CGN's training scenes were collision-checked with the table lowered 2 cm (NVlabs'
    tools/create_table_top_scenes.py, TableScene(lower_table=0.02)), so slight table contact counts as
    positive; this harness fails any table contact. Grasps whose open hand (fingers and palm boxes,
    `sgjax.geometry.gripper.lowest_height`) comes closer than `table_clearance` to the observed table
    plane (the median height of the table points) are moved back along their approach by up to
    `table_backoff` (2 cm, that tolerance) until they clear it; those that still do not are dropped, as
    the GPD baseline drops its own.

The grasp executed is the most confident one above `threshold` whose contact lies on an object and
that clears the table and is not the same grasp as one that already failed (`avoid`). Timing: the
network is end-to-end, so stage1_s = 0 and stage2_s = total_s (the request's wall time, transfer
included); info carries CGN's own inference time and the counts behind the choice.
"""

from __future__ import annotations

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

from eval import cgn_setup
from eval.protocol import Decision, MethodUnavailable, near_grasps
from sgjax.geometry import pointcloud
from sgjax.geometry.gripper import GripperSpec, lowest_height

ENV_VAR = "SGJAX_CGN_PYTHON"
RUNNER = Path(__file__).resolve().with_name("cgn_runner.py")
SETUP = (
    f"Contact-GraspNet (cgn-pytorch 0.4.3) needs its own Python environment: run `{cgn_setup.COMMAND}` "
    f"(~15 min on 2 cores; it builds $SGJAX_CACHE/envs/contact-graspnet, found without settings), or set "
    f"{ENV_VAR} to the python of an environment built as docs/benchmark.md shows"
)

# The Panda hand as cgn-pytorch's gripper/control_points/panda_gripper_coords.yaml gives it (metres).
PANDA_CONTACT_DEPTH = 0.1034  # hand frame -> contact baseline (gripper_*_center_flat): CGN's gripper_depth
PANDA_TIP_DEPTH = 0.112204  # hand frame -> fingertips (gripper_*_tip_flat)
CGN_GRIPPER_WIDTH = 0.16  # CGN.forward's default, its training value: widths clamped at 0.16 / 2 = the stroke
EXTRA_OPENING = 0.005  # NVlabs' TEST.extra_opening: the hand opens this much wider than the predicted width


@dataclasses.dataclass(frozen=True)
class CGNConfig:
    """threshold: CGN's confidence threshold; max_points, voxel, scene_bounds: the cloud sent
    (`sgjax.geometry.pointcloud.scene_cloud`: optional (lo [3], hi [3]) crop, one point per voxel (0: no
    grid), then a seeded subsample); the method's factory sets the default input (docs/benchmark.md);
    contact_depth / tip_depth: the Panda hand frame to its contact baseline / fingertips (m);
    gripper_width: the width the model is called with (it clamps widths at half of it);
    extra_opening: with opening "predicted", open this much wider than the predicted width;
    opening: "full" -- the stroke -- or "predicted" -- min(|w| + extra_opening, stroke), NVlabs' rule;
        cgn-pytorch 0.4.3's widths are too small for it (docs/benchmark.md), hence "full";
    table_backoff: grasps too low for the table are first moved back along their approach by up to this
        much (m; 0: only dropped; 2 cm, CGN's training tolerance, measured better in docs/benchmark.md);
    table_clearance: the open hand's lowest point at least this far above the observed table (m; GPD's);
    timeout_s: per request (the first includes loading the model); spec: the sgjax gripper."""

    threshold: float = 0.5
    max_points: int = 20000
    voxel: float = 0.003
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    contact_depth: float = PANDA_CONTACT_DEPTH
    tip_depth: float = PANDA_TIP_DEPTH
    gripper_width: float = CGN_GRIPPER_WIDTH
    extra_opening: float = EXTRA_OPENING
    table_clearance: float = 0.003
    table_backoff: float = 0.02
    opening: str = "full"
    timeout_s: float = 600.0
    spec: GripperSpec = dataclasses.field(default_factory=GripperSpec)

    def __post_init__(self):
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"CGNConfig.threshold must be in [0, 1), got {self.threshold}")
        if self.max_points < 2048:  # CGN samples 2048 contact candidates by FPS
            raise ValueError(f"CGNConfig.max_points must be >= 2048, got {self.max_points}")
        if self.voxel < 0 or self.extra_opening < 0 or self.gripper_width <= 0:
            raise ValueError("CGNConfig.voxel and extra_opening must be >= 0 and gripper_width > 0")
        if self.opening not in ("full", "predicted"):
            raise ValueError(f"CGNConfig.opening must be 'full' or 'predicted', got {self.opening!r}")
        if not 0 < self.contact_depth <= self.tip_depth:
            raise ValueError(f"CGNConfig needs 0 < contact_depth <= tip_depth, got {self.contact_depth}, {self.tip_depth}")


def interpreter() -> tuple[str | None, str]:
    """(the Contact-GraspNet python to use or None, where it came from): $SGJAX_CGN_PYTHON when set,
    else the finished environment at the setup's default location."""
    python = os.environ.get(ENV_VAR, "").strip()
    if python:
        return python, f"{ENV_VAR}={python}"
    found = cgn_setup.installed_python()
    if found is not None:
        return str(found), f"the environment at {cgn_setup.default_prefix()}"
    return None, ""


def missing() -> str | None:
    """None when Contact-GraspNet can run here, else why not and how to set it up."""
    python, _ = interpreter()
    if python is None:
        prefix = cgn_setup.default_prefix()
        if cgn_setup.state(prefix) == "incomplete":
            return (f"not available yet: the environment at {prefix} is incomplete (an interrupted setup); "
                    f"rerun `{cgn_setup.COMMAND}` to finish it")
        return f"not available yet: {ENV_VAR} is not set and {prefix} holds no environment. {SETUP}"
    return _probe(python, os.environ.get("PYTHONPATH", ""))


@functools.lru_cache(maxsize=8)
def _probe(python: str, pythonpath: str) -> str | None:
    """Whether `python` runs and finds cgn_pytorch (cached per interpreter and PYTHONPATH)."""
    del pythonpath  # part of the cache key only: it changes what the interpreter finds
    exe = shutil.which(os.path.expanduser(python))
    if exe is None:
        return f"{python} is not an executable Python. {SETUP}"
    check = "import importlib.util, sys; sys.exit(0 if importlib.util.find_spec('cgn_pytorch') else 3)"
    try:
        done = subprocess.run([exe, "-c", check], capture_output=True, text=True, timeout=120, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{python} could not be run ({type(exc).__name__}: {exc}). {SETUP}"
    if done.returncode == 3:
        return f"the environment of {python} has no cgn_pytorch module. {SETUP}"
    if done.returncode != 0:
        return f"{python} failed ({done.stderr.strip()[-300:]}). {SETUP}"
    return None


def _rotations(grasps: np.ndarray) -> np.ndarray:
    """The nearest rotations [K, 3, 3] to CGN's rotation blocks (float32 estimates of orthonormal axes)."""
    u, _, vt = np.linalg.svd(np.asarray(grasps, np.float64).reshape(-1, 4, 4)[:, :3, :3])
    u[:, :, -1] *= np.sign(np.linalg.det(u @ vt))[:, None]
    return u @ vt


def cgn_to_sgjax(grasps: np.ndarray, contacts: np.ndarray, widths: np.ndarray, offset, spec: GripperSpec,
                 contact_depth: float = PANDA_CONTACT_DEPTH, tip_depth: float = PANDA_TIP_DEPTH,
                 extra_opening: float = EXTRA_OPENING) -> tuple[np.ndarray, np.ndarray]:
    """CGN predictions -> sgjax grasps (module doc): grasps [K, 4, 4] (only their rotations are used: x the
    closing axis, z the approach), contacts [K, 3] and SIGNED widths [K] (the hand lies at contact +
    w/2 x; a negative w puts it on the -x side), in a frame shifted by -offset [3] -> (poses [K, 4, 4] in
    the world, opening widths [K]). The closing region is centred between the contact c and c + w x, the
    fingertips lie tip_depth - contact_depth beyond the contact baseline, and the hand opens to
    min(|w| + extra_opening, spec.max_opening)."""
    rotation = _rotations(grasps)
    contacts = np.asarray(contacts, np.float64).reshape(-1, 3)
    widths = np.asarray(widths, np.float64).reshape(-1)
    if not len(rotation) == len(contacts) == len(widths):
        raise ValueError(f"got {len(rotation)} grasps, {len(contacts)} contacts and {len(widths)} widths")
    if not (np.isfinite(contacts).all() and np.isfinite(widths).all()):
        raise ValueError("contacts and widths must be finite")
    x, z = rotation[:, :, 0], rotation[:, :, 2]
    centre = contacts + np.asarray(offset, np.float64) + 0.5 * widths[:, None] * x
    out = np.tile(np.eye(4), (len(rotation), 1, 1))
    out[:, :3, :3] = rotation
    out[:, :3, 3] = centre + (tip_depth - contact_depth - spec.finger_length) * z
    return out, np.minimum(np.abs(widths) + extra_opening, spec.max_opening)


def table_height(points: np.ndarray, labels: np.ndarray) -> float:
    """The observed table's height: the median z of the finite table points (labels < 0); -inf if none."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    table = np.isfinite(points).all(axis=1) & (np.asarray(labels).reshape(-1) < 0)
    return float(np.median(points[table, 2])) if table.any() else -np.inf


def clears_table(poses: np.ndarray, widths: np.ndarray, table_z: float, spec: GripperSpec,
                 clearance: float) -> np.ndarray:
    """Whether each open hand (poses [K, 4, 4], widths [K]: fingers and palm) stays `clearance` above the
    table plane z = table_z -> bool [K]; every grasp clears a table that was not seen (-inf)."""
    if not np.isfinite(table_z):
        return np.ones(len(poses), bool)
    plane = np.array([0.0, 0.0, 1.0, -table_z])
    return np.asarray(lowest_height(np.asarray(poses, np.float32), np.asarray(widths, np.float32), spec, plane)) >= clearance


def back_off(poses: np.ndarray, widths: np.ndarray, table_z: float, spec: GripperSpec, clearance: float,
             max_shift: float) -> np.ndarray:
    """Grasps too close to the table moved back along their approach axis until the open hand clears it by
    `clearance`, by at most max_shift (m): poses [K, 4, 4], widths [K] -> poses [K, 4, 4] (a copy; those
    that need more, or approach upwards, are left where they are). CGN's training counted grasps that
    touch a table lowered by 2 cm as positives; backing off by up to that much is the same grasp, shallower."""
    poses = np.array(poses, np.float64)
    if max_shift <= 0 or not np.isfinite(table_z) or len(poses) == 0:
        return poses
    plane = np.array([0.0, 0.0, 1.0, -table_z])
    low = clearance - np.asarray(lowest_height(poses.astype(np.float32), np.asarray(widths, np.float32), spec, plane), np.float64)
    down = -poses[:, 2, 2]  # how fast backing off raises the hand: -z_world of the approach axis
    shift = np.where(down > 1e-3, (low + 1e-4) / np.maximum(down, 1e-3), np.inf)
    move = (low > 0) & (shift <= max_shift)
    poses[move, :3, 3] -= shift[move, None] * poses[move, :3, 2]
    return poses


def choose(poses: np.ndarray, widths: np.ndarray, confidence: np.ndarray, on_object: np.ndarray, table_z: float,
           config: CGNConfig, avoid=None) -> tuple[int | None, str, dict]:
    """The grasp to execute among K converted predictions (poses [K, 4, 4], widths [K], confidence [K],
    on_object bool [K]): the most confident one above the threshold, on an object, clear of the table and
    not one that already failed (avoid [F, 4, 4]). -> (index or None, reason when None, counts)."""
    confidence = np.asarray(confidence, np.float64).reshape(-1)
    keep = (confidence > config.threshold) & np.asarray(on_object, bool).reshape(-1)
    counts = {"grasps": int(keep.sum())}
    if not keep.any():
        return None, f"Contact-GraspNet found no grasp on an object above confidence {config.threshold:g}", counts
    low = keep & ~clears_table(poses, widths, table_z, config.spec, config.table_clearance)
    counts["table"] = int(low.sum())
    keep &= ~low
    if not keep.any():
        return None, f"all {counts['grasps']} grasps come closer than {config.table_clearance * 1000:g} mm to the table", counts
    avoided = keep & near_grasps(poses, avoid, config.spec)
    counts["avoided"] = int(avoided.sum())
    keep &= ~avoided
    if not keep.any():
        return None, (f"all {counts['grasps'] - counts['table']} grasps clear of the table are the same grasp "
                      "as one that already failed"), counts
    return int(np.argmax(np.where(keep, confidence, -np.inf))), "", counts


class ContactGraspNetMethod:
    """The benchmark method; holds one runner process (closed by `close()` or at exit)."""

    name = "contact-graspnet"

    def __init__(self, config: CGNConfig | None = None, python: str | None = None):
        self.config = config or CGNConfig()
        if python is None:
            reason = missing()
            python = interpreter()[0]
        else:
            reason = _probe(python, os.environ.get("PYTHONPATH", ""))
        if reason is not None:
            raise MethodUnavailable(f"method {self.name!r} cannot run: {reason}")
        self.python = shutil.which(os.path.expanduser(python))
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
        try:  # at interpreter shutdown, parts (modules included) may already be gone
            self.close()
            self._stderr.close()
            self._dir.cleanup()
        except Exception:  # noqa: BLE001
            pass

    # -- the method ---------------------------------------------------------------------------

    def predict(self, points: np.ndarray, obj_mask: np.ndarray, seed: int = 0) -> dict:
        """CGN's raw predictions for a cloud points [N, 3] (world frame, z up; mean-subtracted here) with
        obj_mask [N]: {"grasps" [K, 4, 4], "contacts" [K, 3], "widths" [K], "confidence" [K],
        "on_object" [K], "inference_s"} in the world frame, sorted by confidence (K = 2048 FPS samples)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        mean = points.mean(axis=0)
        request = os.path.join(self._dir.name, "request.npz")
        reply = os.path.join(self._dir.name, "reply.npz")
        np.savez(request, points=(points - mean).astype(np.float32), obj_mask=np.asarray(obj_mask, np.float32).reshape(-1),
                 seed=np.int64(int(seed) & 0xFFFFFFFF), gripper_width=np.float64(self.config.gripper_width),
                 gripper_depth=np.float64(self.config.contact_depth))
        answer = self._request(request, reply)
        with np.load(reply, allow_pickle=False) as data:
            out = {k: data[k] for k in ("grasps", "contacts", "widths", "confidence", "on_object")}
        out["grasps"] = out["grasps"].copy()
        out["grasps"][:, :3, 3] += mean
        out["contacts"] = out["contacts"] + mean
        out["inference_s"] = float(answer.get("inference_s", 0.0))
        return out

    def plan(self, points: np.ndarray, labels: np.ndarray, viewpoint, seed: int = 0, avoid=None) -> Decision:
        cfg = self.config
        start = time.perf_counter()
        points = np.asarray(points, np.float64).reshape(-1, 3)
        labels = np.asarray(labels).reshape(-1)
        table_z = table_height(points, labels)
        cloud, mask, cloud_labels = pointcloud.scene_cloud(points, cfg.max_points, cfg.voxel, labels,
                                                           cfg.scene_bounds, seed)
        cloud, cloud_labels = cloud[mask].astype(np.float64), cloud_labels[mask]
        obj = cloud_labels >= 0
        info = {"points": len(cloud), "table_z": table_z if np.isfinite(table_z) else None}
        if not obj.any() or len(cloud) < 2048:
            elapsed = time.perf_counter() - start
            why = "no object points" if not obj.any() else f"{len(cloud)} points, fewer than CGN's 2048 samples"
            return Decision(None, 0.0, 0.0, why, _timing(elapsed), info)
        pred = self.predict(cloud, obj, seed)
        zero = np.zeros(3)
        poses, widths = cgn_to_sgjax(pred["grasps"], pred["contacts"], pred["widths"], zero, cfg.spec,
                                     cfg.contact_depth, cfg.tip_depth, cfg.extra_opening)
        if cfg.opening == "full":
            widths = np.full_like(widths, cfg.spec.max_opening)
        poses = back_off(poses, widths, table_z, cfg.spec, cfg.table_clearance, cfg.table_backoff)
        best, reason, counts = choose(poses, widths, pred["confidence"], pred["on_object"], table_z, cfg, avoid)
        elapsed = time.perf_counter() - start
        info.update(counts, inference_s=pred["inference_s"])
        if best is None:
            return Decision(None, 0.0, 0.0, reason, _timing(elapsed), info)
        info.update(predicted_width=float(pred["widths"][best]), contact=pred["contacts"][best].tolist())
        return Decision(poses[best], float(widths[best]), float(pred["confidence"][best]), "", _timing(elapsed), info)


def _timing(total: float) -> dict:
    return {"stage1_s": 0.0, "stage2_s": total, "total_s": total}
