"""`sgjax example-frame` and `sgjax plan --depth`: a simulated depth frame written as a camera would give it,
planned on in the camera's and the world's frame, with masks, several objects and alternatives, pictures;
every bad input a user can give ends in one line on stderr and exit status 2; and the frame-free helpers
beneath (`draw_grasps`' up, `draw.project`, `table_plane`'s up)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from sgjax.draw import draw_grasps, project, up_rotation
from sgjax.geometry.pointcloud import table_plane
from sgjax.perception import Frame, Intrinsics, back_project, read_intrinsics
from sgjax_cli import main

# The tiny object set (five solids) is built in seconds on an empty cache; `example-frame`'s default, the seen
# set, takes minutes to prepare there.
N_OBJECTS, SEED = 3, 0
NEAR = 0.02  # a grasp's tool-centre point lies within this of a point of the object it names (metres)


@pytest.fixture(scope="module")
def frame_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("frame") / "frame"
    assert main(["example-frame", str(out), "--set", "tiny", "--objects", str(N_OBJECTS), "--seed", str(SEED)]) == 0
    return out


def files(d) -> dict:
    """The example frame's files by name: depth, masks, intrinsics, extrinsics."""
    return {"depth": str(d / "depth.png"), "masks": str(d / "masks.png"), "intrinsics": str(d / "intrinsics.json"),
            "extrinsics": str(d / "extrinsics.json")}


def plan_json(capsys, *argv) -> dict:
    capsys.readouterr()
    code = main(["plan", *argv, "--small-db", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert len(out.strip().splitlines()) == 1  # exactly one JSON document
    return json.loads(out)


def assert_grasps_on_their_objects(doc, frame):
    assert doc["frame"] == frame.frame
    assert [o["id"] for o in doc["objects"]] == frame.object_ids
    for o in doc["objects"]:
        assert o["points"] == len(frame.object_points(o["id"]))
        np.testing.assert_allclose(o["centroid"], frame.object_points(o["id"]).mean(0), atol=1e-5)
    np.testing.assert_allclose(doc["table"], frame.table.plane, atol=1e-5)
    for g in doc["grasps"]:
        pose = np.array(g["pose"])
        assert pose.shape == (4, 4) and np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-5)
        np.testing.assert_allclose(g["approach"], pose[:3, 2], atol=1e-6)
        np.testing.assert_allclose(g["center"], pose[:3, 3] + 0.025 * pose[:3, 2], atol=1e-5)  # finger_length / 2
        gap = np.linalg.norm(frame.object_points(g["object"]) - g["center"], axis=1).min()
        assert gap < NEAR, (g["object"], gap)
        assert 0 < g["width"] <= 0.08 and g["kind"] in ("evaluated", "refined", "alternative")


def test_example_frame_writes_a_camera_frame(frame_dir):
    f = files(frame_dir)
    with Image.open(f["depth"]) as image:
        depth = np.asarray(image)
    with Image.open(f["masks"]) as image:
        masks = np.asarray(image)
    assert depth.shape == masks.shape == (480, 640) and depth.dtype == np.uint16 and masks.dtype.kind == "u"
    assert 300 < np.median(depth[depth > 0]) < 2000  # millimetres
    ids = np.unique(masks)
    assert ids[0] == 0 and 1 <= len(ids) - 1 <= N_OBJECTS and ids.max() <= N_OBJECTS
    intrinsics = json.loads((frame_dir / "intrinsics.json").read_text())
    assert (intrinsics["width"], intrinsics["height"]) == (640, 480) and np.array(intrinsics["K"]).shape == (3, 3)
    assert intrinsics["K"][0][2] == 319.5 and intrinsics["K"][1][2] == 239.5  # OpenCV: pixel centres at integers
    T = np.array(json.loads((frame_dir / "extrinsics.json").read_text())["T"])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and T[2, 3] > 0.3  # above the table
    with Image.open(frame_dir / "picture.png") as image:
        assert image.size[0] > 300
    assert not [p.name for p in frame_dir.iterdir() if ".tmp-" in p.name]  # atomic writes left nothing behind


def test_plan_depth_in_camera_and_world_frames(frame_dir, capsys):
    f = files(frame_dir)
    base = ["--depth", f["depth"], "--intrinsics", f["intrinsics"]]
    camera = plan_json(capsys, *base)
    world = plan_json(capsys, *base, "--extrinsics", f["extrinsics"])
    camera_frame = Frame.from_depth(f["depth"], f["intrinsics"])
    world_frame = Frame.from_depth(f["depth"], f["intrinsics"], extrinsics=f["extrinsics"])
    assert camera["frame"] == "camera" and world["frame"] == "world"
    for doc, frame in ((camera, camera_frame), (world, world_frame)):
        assert len(frame.object_ids) >= 2  # the scene's objects found by segmentation
        assert len(doc["grasps"]) == 1 and doc["grasps"][0]["kind"] in ("evaluated", "refined") and not doc["reasons"]
        assert_grasps_on_their_objects(doc, frame)
        assert {"perception_s", "plan_s", "stage1_s", "stage2_s", "total_s", "compiled"} <= set(doc["timing"])
        assert doc["checkpoint"] == "sgjax/models/ernet_default"  # the E-RNet shipped for the default gripper
    # The same grasp, once in the camera's coordinates and once in the world's.
    T = np.array(json.loads((frame_dir / "extrinsics.json").read_text())["T"])
    (c,), (w,) = camera["grasps"], world["grasps"]
    assert c["object"] == w["object"]
    np.testing.assert_allclose(T @ np.array(c["pose"]), w["pose"], atol=2e-3)
    np.testing.assert_allclose(T[:3, :3] @ c["center"] + T[:3, 3], w["center"], atol=2e-3)
    assert abs(c["width"] - w["width"]) < 1e-3
    assert world["table"][2] > 0.99 and abs(world["table"][3]) < 0.005  # the simulator's table: z = 0
    # The grasp is on the object the true masks say it is on.
    with Image.open(f["masks"]) as image:
        masks = np.asarray(image)
    pixels = camera_frame.pixels[camera_frame.labels == c["object"]]
    truth = np.bincount(masks[pixels[:, 0], pixels[:, 1]]).argmax()
    assert truth > 0

    # The human summary of the same plan.
    assert main(["plan", *base, "--small-db"]) == 0
    out = capsys.readouterr().out
    assert "camera frame" in out and f"object {c['object']}:" in out and "center" in out and "timing" in out
    assert "E-RNet checkpoint: sgjax/models/ernet_default" in out

    # As its own process, as the `sgjax` command runs: the programs the plans above called load on a
    # second thread (`exported.prefetch`) and the process ends without Python's teardown (`_end_process`):
    # the same document, all of it; a bad input still ends with status 2 and one line.
    command = [sys.executable, "-m", "sgjax_cli", "plan", *base, "--small-db", "--json"]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    doc = json.loads(done.stdout)
    assert (doc["objects"], doc["grasps"], doc["table"]) == (camera["objects"], camera["grasps"], camera["table"])
    done = subprocess.run(command[:5] + [str(frame_dir / "missing.png"), *command[6:]], capture_output=True, text=True)
    assert done.returncode == 2 and done.stdout == "" and done.stderr.startswith("sgjax: error: ")
    assert len(done.stderr.strip().splitlines()) == 1 and "missing.png" in done.stderr


def test_plan_frame_tries_the_joined_hypothesis_when_the_first_finds_no_grasp(frame_dir):
    """A clustered frame whose objects came out in pieces too small to plan on (5 x 5 pixel blocks, < 50
    points each: the planner finds no object) gets its grasp from the joined hypothesis (here the true
    masks' objects): FramePlan.frame is the joined frame, the grasp lies on the object it names there."""
    import dataclasses

    from sgjax.grasping import plan_frame
    from sgjax.planner import Planner
    from sgjax.stage1.database import DBConfig, load_database

    f = files(frame_dir)
    whole = Frame.from_depth(f["depth"], f["intrinsics"], extrinsics=f["extrinsics"], masks=f["masks"])
    block = whole.pixels[:, 0] // 5 * 1000 + whole.pixels[:, 1] // 5
    pieces = np.where(whole.labels > 0, np.unique(whole.labels * 10**6 + block, return_inverse=True)[1].reshape(-1) + 1,
                      whole.labels).astype(np.int32)
    assert np.bincount(pieces[pieces > 0]).max() < 50
    frame = dataclasses.replace(whole, labels=pieces, joined_labels=whole.labels, segmentation="clusters")
    planner = Planner(db=load_database(DBConfig.small(), progress=False))
    result = plan_frame(planner, frame)
    assert result.frame.segmentation == "joined clusters" and np.array_equal(result.frame.labels, whole.labels)
    (g,) = result.grasps
    assert g.object in whole.object_ids and not result.reasons
    assert np.linalg.norm(whole.object_points(g.object) - g.center, axis=1).min() < NEAR
    # Without other hypotheses (the same labels as masks) the frame gets none, and says why.
    alone = plan_frame(planner, dataclasses.replace(frame, joined_labels=None, segmentation="masks"))
    assert not alone.grasps and alone.frame is not None and "50" in alone.reasons["scene"]


def test_plan_depth_with_masks_all_objects_alternatives_and_a_picture(frame_dir, capsys, tmp_path):
    f = files(frame_dir)
    png = tmp_path / "plan.png"
    doc = plan_json(capsys, "--depth", f["depth"], "--intrinsics", f["intrinsics"], "--extrinsics", f["extrinsics"],
                    "--masks", f["masks"], "--all-objects", "--top", "2", "--png", str(png))
    frame = Frame.from_depth(f["depth"], f["intrinsics"], extrinsics=f["extrinsics"], masks=f["masks"])
    with Image.open(f["masks"]) as image:
        mask_ids = set(np.unique(np.asarray(image)).tolist()) - {0}
    assert frame.segmentation == "masks" and set(frame.object_ids) <= mask_ids and len(frame.object_ids) >= 2
    assert_grasps_on_their_objects(doc, frame)
    chosen = [g for g in doc["grasps"] if g["kind"] != "alternative"]
    others = [g for g in doc["grasps"] if g["kind"] == "alternative"]
    objects = [g["object"] for g in chosen]
    assert len(objects) == len(set(objects)) >= 1  # at most one chosen grasp per object
    assert set(objects) | {int(k) for k in doc["reasons"]} == set(frame.object_ids)  # a grasp or a reason each
    assert others and doc["grasps"] == chosen + others  # --top 2: alternatives after the chosen grasps
    assert all(g["object"] in objects for g in others) and len({g["object"] for g in others}) == len(others)
    assert [g["score"] for g in chosen] == sorted((g["score"] for g in chosen), reverse=True)
    with Image.open(png) as image:
        assert image.format == "PNG" and image.size[0] > 1000  # the image and the two 3D views

    # No object with a grasp: exit 1, still one document, saying why (an object of 25 points is too small to plan).
    tiny = np.zeros((480, 640), np.uint8)
    tiny[400:405, 100:105] = 7
    Image.fromarray(tiny).save(tmp_path / "tiny.png")
    capsys.readouterr()
    assert main(["plan", "--depth", f["depth"], "--intrinsics", f["intrinsics"], "--masks", str(tmp_path / "tiny.png"),
                 "--small-db", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["grasps"] == [] and [o["id"] for o in doc["objects"]] == [7] and "visible points" in doc["reasons"]["scene"]


@pytest.fixture(scope="module")
def bad(tmp_path_factory, frame_dir):
    """Files that are wrong in one way each, beside the good frame's."""
    tmp_path = tmp_path_factory.mktemp("bad")
    f = files(frame_dir)
    with Image.open(f["depth"]) as image:
        depth = np.asarray(image)
    K = read_intrinsics(f["intrinsics"]).K
    Image.fromarray(np.zeros_like(depth)).save(tmp_path / "zeros.png")
    np.save(tmp_path / "nan.npy", np.full(depth.shape, np.nan, np.float32))
    np.save(tmp_path / "millimetres.npy", depth.astype(np.float32))  # a float depth must be in metres
    (tmp_path / "small.json").write_text(json.dumps({"K": K.tolist(), "width": 320, "height": 240}))
    Image.fromarray(np.zeros((240, 320), np.uint8)).save(tmp_path / "small_masks.png")
    Image.fromarray(np.zeros(depth.shape, np.uint8)).save(tmp_path / "empty.png")
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(500, 1500, depth.shape).astype(np.uint16)).save(tmp_path / "noise.png")
    Image.fromarray(np.full(depth.shape, 700, np.uint16)).save(tmp_path / "flat.png")  # a wall: a plane, nothing on it
    (tmp_path / "broken.png").write_bytes(b"not a picture at all")
    (tmp_path / "broken.json").write_text("{ not json")
    (tmp_path / "skew.json").write_text(json.dumps({"T": (2 * np.eye(4)).tolist()}))
    names = {p.name.replace(".", "_") if p.stem == "broken" else p.stem: str(p) for p in tmp_path.iterdir()}
    return {**f, **names, "cloud": str(tmp_path / "cloud.npy")}


BAD = [  # (argv with {names} of `bad`'s files, words the one line must hold)
    (["--depth", "{dir}/missing.png", "--intrinsics", "{intrinsics}"], "no such depth image"),
    (["--depth", "{depth}", "--intrinsics", "{dir}/missing.json"], "no such intrinsics"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--extrinsics", "{dir}/missing.json"], "no such extrinsics"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--masks", "{dir}/missing.png"], "no such masks"),
    (["--depth", "{zeros}", "--intrinsics", "{intrinsics}"], "no valid pixel"),
    (["--depth", "{nan}", "--intrinsics", "{intrinsics}"], "no valid pixel"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--depth-scale", "1"], "median depth"),
    (["--depth", "{millimetres}", "--intrinsics", "{intrinsics}"], "is the depth in metres"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--depth-scale", "0"], "--depth-scale"),
    (["--depth", "{depth}", "--intrinsics", "{small}"], "intrinsics are for 320x240"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--masks", "{small_masks}"], "320x240 pixels"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--workspace-mask", "{empty}"], "workspace mask holds no"),
    (["--depth", "{noise}", "--intrinsics", "{intrinsics}"], "no table plane"),
    (["--depth", "{flat}", "--intrinsics", "{intrinsics}"], "no object found above the table"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--masks", "{empty}"], "the masks hold no object"),
    (["--depth", "{broken_png}", "--intrinsics", "{intrinsics}"], "broken.png: cannot read the depth PNG"),
    (["--depth", "{depth}", "--intrinsics", "{broken_json}"], "broken.json"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--extrinsics", "{broken_json}"], "broken.json: not valid JSON"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--extrinsics", "{skew}"], "not a proper rotation"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--masks", "{broken_png}"], "cannot read the masks"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--top", "0"], "--top"),
    (["{cloud}", "--depth", "{depth}", "--intrinsics", "{intrinsics}"], "not both"),
    ([], "nothing to plan on"),
    (["{cloud}"], "needs --mask"),
    (["{cloud}", "--mask", "{cloud}", "--all-objects"], "--all-objects: only for a depth image"),
    (["--depth", "{depth}"], "--depth needs --intrinsics"),
    (["--depth", "{depth}", "--intrinsics", "{intrinsics}", "--mask", "{cloud}"], "--mask: only for a scene cloud"),
    (["--intrinsics", "{intrinsics}"], "nothing to plan on"),
]


@pytest.mark.parametrize("argv, words", BAD, ids=[w for _, w in BAD])
def test_bad_input_is_one_line_and_exit_2(bad, argv, words, capsys, tmp_path):
    names = {**bad, "dir": str(tmp_path)}
    capsys.readouterr()
    code = main(["plan", *(a.format(**names) for a in argv)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("sgjax: error: "), err
    assert words in err, err


def test_draw_grasps_with_up_and_project(tmp_path):
    up = np.array([0.0, -0.633, -0.774])
    up /= np.linalg.norm(up)
    R = up_rotation(up)
    np.testing.assert_allclose(R @ up, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.array_equal(up_rotation((0, 0, 2)), np.eye(3))
    with pytest.raises(ValueError, match="up"):
        up_rotation((0, 0, 0))
    # A camera-frame box on a table seen from above at an angle; a grasp from above, along -up.
    rng = np.random.default_rng(0)
    box = rng.uniform(-0.02, 0.02, (500, 3)) + (0.0, 0.0, 0.6)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([R[0], np.cross(-up, R[0]), -up], axis=1)
    pose[:3, 3] = box.mean(0) + 0.1 * up
    path = tmp_path / "up.png"
    draw_grasps(path, box, pose[None], np.array([0.05]), scene_points=box + 0.05 * rng.standard_normal(box.shape),
                up=up, title="camera frame, table normal up")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="up"):
        draw_grasps(tmp_path / "bad.png", box, up=(0, 0, 0))
    assert not (tmp_path / "bad.png").exists()
    # project() is back_project()'s inverse: pixel (row, column) -> point -> the same (column, row).
    K = Intrinsics(fx=500.0, fy=480.0, cx=2.5, cy=1.5, width=6, height=4)
    depth = np.zeros((4, 6))
    depth[1, 4], depth[3, 0] = 0.7, 1.3
    points, pixels = back_project(depth, K)
    np.testing.assert_allclose(project(points, K.K), pixels[:, ::-1], atol=1e-9)
    assert np.isnan(project(np.array([0.0, 0.0, -1.0]), K.K)).all()


def test_table_plane_takes_up():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.3, 0.3, (400, 3)).astype(np.float32)
    labels = np.where(rng.random(400) < 0.7, -1, 1)
    old = (0.0, 0.0, 1.0, -float(np.median(points[labels < 0, 2])))  # the formula before `up` existed
    assert table_plane(points, labels) == old and table_plane(points, labels, up=(0, 0, 5)) == old
    # A tilted table: its points at height h along n.
    n = np.array([0.0, -0.6, -0.8])
    a = np.cross(n, (1.0, 0.0, 0.0))
    b = np.cross(n, a)
    table = (rng.uniform(-0.3, 0.3, (300, 1)) * a + rng.uniform(-0.3, 0.3, (300, 1)) * b) + 0.55 * n
    plane = table_plane(table, -np.ones(300), up=2 * n)
    np.testing.assert_allclose(plane, (*n, -0.55), atol=1e-9)
    assert table_plane(table, np.ones(300), up=n) is None
    for up in ((0, 0, 0), (np.nan, 0, 1), (1, 0)):
        with pytest.raises(ValueError, match="up"):
            table_plane(table, -np.ones(300), up=up)
