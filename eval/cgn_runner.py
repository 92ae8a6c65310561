"""Contact-GraspNet runner: executed by the Contact-GraspNet environment's Python, NOT by sgjax's.

It imports only the standard library, numpy and `cgn_pytorch` (plus torch when present), so it runs
in the separate environment that `eval/contact_graspnet.py` describes (numpy<2, torch CPU,
torch-geometric 2.4.0, torch-cluster 1.6.3, cgn-pytorch 0.4.3). sgjax talks to it out of process.

Request (an .npz written by sgjax):
    points        float32 [N, 3]  world frame, z up, metres, MEAN SUBTRACTED (as CGN's own scenes are)
    obj_mask      float32 [N]     1 for object points, 0 for the table
    seed          int             libc srand(seed) before inference: torch-cluster's fps seeds from rand(),
                                  so torch.manual_seed alone is not repeatable; numpy and torch are seeded too
    gripper_width float           passed to the model, which clamps its widths at gripper_width / 2 before
                                  placing the hand: 0.16, its training value (cgn_pytorch.inference() passes
                                  0.08, which clamps at 4 cm and puts wider grasps off-centre)
    gripper_depth float           the hand frame to the contact baseline the model places the hand by (0.1034)
Reply (an .npz written here), one row per FPS-sampled point (2048), sorted by confidence, best first:
    grasps      float64 [K, 4, 4]  the model's Panda hand poses in the request's frame
    contacts    float64 [K, 3]     the contact points the grasps are built on
    widths      float64 [K]        the SIGNED widths the hands were placed by (hand = contact - depth z + w/2 x;
                                   -gripper_width .. gripper_width / 2): the model's own width output is
                                   relu(w), which loses the side of the contact the hand is on
    confidence  float64 [K]        sigmoid of the model's score
    on_object   bool    [K]        obj_mask at the contact point
    inference_s float              wall seconds of the forward pass alone

Usage:
    python eval/cgn_runner.py REQUEST.npz REPLY.npz   # one request
    python eval/cgn_runner.py --serve                 # the model stays loaded; one JSON line per
        request on stdin, {"input": REQUEST.npz, "output": REPLY.npz}; one JSON line per reply on
        stdout, {"ok": true, "grasps": K, "inference_s": t} or {"ok": false, "error": "..."}; the
        first line written is {"ready": true, "load_s": t} (or {"ok": false, ...} and exit 1).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import json
import sys
import time
import traceback

import numpy as np


def seed_everything(seed: int) -> None:
    """libc srand (torch-cluster's fps), numpy and torch (when installed)."""
    seed = int(seed) & 0xFFFFFFFF
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.srand(ctypes.c_uint(seed))
    except OSError:  # no libc to seed (not Linux/macOS): runs stay valid, only not repeatable
        pass
    np.random.seed(seed)
    try:
        import torch
    except ImportError:
        return
    torch.manual_seed(seed)


def _no_grad():
    try:
        import torch
    except ImportError:
        return contextlib.nullcontext()
    return torch.no_grad()


def load_model():
    """CGN's pretrained model on the CPU (the checkpoint ships in the wheel)."""
    from cgn_pytorch import from_pretrained

    model, _, _ = from_pretrained(device="cpu")
    if hasattr(model, "eval"):
        model.eval()
    return model


def predict(model, points: np.ndarray, obj_mask: np.ndarray, gripper_width: float, gripper_depth: float) -> dict:
    """The model's forward pass on points [N, 3] (N >= 2048) -> the reply's arrays (unsorted).

    What `cgn_pytorch.inference()` does, but with the caller's gripper_width and every output kept:
    2048 contacts by farthest point sampling, the model on the whole cloud."""
    import torch
    from torch_geometric.nn import fps

    if len(points) < 2048:
        raise ValueError(f"Contact-GraspNet samples 2048 contacts; got a cloud of {len(points)} points")
    pos = torch.as_tensor(points, dtype=torch.float32)
    batch = torch.zeros(len(pos), dtype=torch.int64)
    idx = fps(pos, batch, ratio=2048 / len(pos))
    contacts, grasps, score, widths, _, _ = model(
        pos[:, 3:], pcd_poses=pos, batch=batch, idxs=idx, gripper_depth=gripper_depth, gripper_width=gripper_width)
    contacts = _numpy(contacts).reshape(-1, 3).astype(np.float64)
    sampled = points[_numpy(idx)]
    if contacts.shape != sampled.shape or not np.allclose(contacts, sampled, atol=1e-6):
        # The object flags are read at the FPS indices: that needs the model's outputs in their order.
        raise RuntimeError("the model's contact points are not the FPS-sampled input points in order")
    grasps = _numpy(grasps).reshape(-1, 4, 4).astype(np.float64)
    # The signed width, read off the hand the model built: (hand + depth z - contact) . x = w / 2.
    signed = 2.0 * np.sum((grasps[:, :3, 3] + gripper_depth * grasps[:, :3, 2] - contacts) * grasps[:, :3, 0], axis=1)
    if not np.allclose(np.maximum(signed, 0.0), _numpy(widths).reshape(-1), atol=1e-5):
        raise RuntimeError("the model's widths are not relu of the offsets its hands were placed by")
    return {
        "grasps": grasps,
        "contacts": contacts,
        "widths": signed,
        "confidence": _numpy(torch.sigmoid(score)).reshape(-1).astype(np.float64),
        "on_object": obj_mask[_numpy(idx)] > 0.5,
    }


def run(model, request_path: str, reply_path: str) -> dict:
    """One request -> reply file; returns {"grasps": K, "inference_s": t}."""
    with np.load(request_path, allow_pickle=False) as data:
        points = np.asarray(data["points"], np.float32).reshape(-1, 3)
        obj_mask = np.asarray(data["obj_mask"], np.float32).reshape(-1)
        seed = int(data["seed"])
        gripper_width = float(data["gripper_width"])
        gripper_depth = float(data["gripper_depth"])
    if len(obj_mask) != len(points):
        raise ValueError(f"got {len(points)} points but {len(obj_mask)} mask entries")
    seed_everything(seed)
    start = time.perf_counter()
    with _no_grad():
        out = predict(model, points, obj_mask, gripper_width, gripper_depth)
    elapsed = time.perf_counter() - start
    order = np.argsort(-out["confidence"], kind="stable")
    np.savez(reply_path, **{k: v[order] for k, v in out.items()}, inference_s=np.float64(elapsed))
    return {"grasps": len(order), "inference_s": elapsed}


def _numpy(value):
    """torch tensors (CPU or not) and arrays -> numpy."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return value


# Replies go to the process's real stdout; everything else printed to stdout (cgn_pytorch prints
# "Initializing net..." when loading) is sent to stderr, so it cannot corrupt the reply channel.
_REPLIES = sys.stdout


def _reply(record: dict) -> None:
    _REPLIES.write(json.dumps(record) + "\n")
    _REPLIES.flush()


def serve() -> int:
    sys.stdout = sys.stderr
    start = time.perf_counter()
    try:
        model = load_model()
    except Exception as exc:  # noqa: BLE001 - reported to the caller, which raises
        _reply({"ok": False, "error": f"loading Contact-GraspNet failed: {type(exc).__name__}: {exc}"})
        traceback.print_exc()
        return 1
    _reply({"ready": True, "load_s": time.perf_counter() - start})
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            request = json.loads(line)
            _reply({"ok": True, **run(model, request["input"], request["output"])})
        except Exception as exc:  # noqa: BLE001 - one bad request must not end the server
            traceback.print_exc()
            _reply({"ok": False, "error": f"{type(exc).__name__}: {exc}"})
    return 0


def main(argv: list[str]) -> int:
    if argv == ["--serve"]:
        return serve()
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    sys.stdout = sys.stderr
    _reply(run(load_model(), argv[0], argv[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
