"""Object assets: the tiny set, mesh preparation (clean, COM frame, hulls, cache, failures), object sets,
the seen/unseen split, procedural objects and the `sgjax objects` CLI."""

import json
import os
import warnings

import numpy as np
import pytest
import trimesh

from envs import meshprep, objects, procedural
from envs.meshprep import MeshPrepError, PrepConfig
from envs.objects import MeshSource
from sgjax_cli import main
from sgjax.geometry.gripper import GripperSpec


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SGJAX_CACHE", str(tmp_path / "cache"))


def _load(path) -> trimesh.Trimesh:
    return trimesh.load(path, force="mesh")


def _l_shape() -> trimesh.Trimesh:
    """An L-shaped prism (two 8 x 3 cm arms, 4 cm thick): non-convex, volume/hull 0.76."""
    profile = np.array([[0, 0], [8, 0], [8, 3], [3, 3], [3, 8], [0, 8]], np.float64) / 100
    profile -= 0.015  # the caps fan from the origin: put it inside the corner square
    return procedural.extrude_profile(profile, 0.04)


def _inside_l(points: np.ndarray) -> np.ndarray:
    x, y, z = (points + [0.015, 0.015, 0.0]).T
    arm = ((x <= 0.08) & (y <= 0.03)) | ((x <= 0.03) & (y <= 0.08))
    return (x >= 0) & (y >= 0) & arm & (np.abs(z) <= 0.02)


def _inside_any_hull(points: np.ndarray, hulls: list[trimesh.Trimesh]) -> np.ndarray:
    inside = np.zeros(len(points), bool)
    for hull in hulls:  # convex: inside = behind every face plane
        d = np.einsum("fk,pfk->pf", hull.face_normals, points[:, None, :] - hull.triangles[None, :, 0, :])
        inside |= np.all(d <= 1e-9, axis=1)
    return inside


def _write(mesh: trimesh.Trimesh, path) -> str:
    path = str(path)
    mesh.export(path)
    return path


# --- the tiny set -----------------------------------------------------------------------------------


def test_tiny_set_is_convex_graspable_and_centred():
    assets = objects.tiny_object_set()
    assert 4 <= len(assets) <= 6
    assert len({a.name for a in assets}) == len(assets)
    opening = GripperSpec().max_opening
    for a in assets:
        assert a.source == "tiny" and a.name.startswith("tiny/")
        visual = _load(a.visual_path)
        assert visual.is_watertight
        np.testing.assert_allclose(visual.center_mass, 0.0, atol=1e-6)
        np.testing.assert_allclose(visual.extents, a.extents, atol=1e-6)
        ext = sorted(a.extents)
        assert 0.03 <= ext[0] <= opening and 0.03 <= ext[2] <= 0.25
        assert PrepConfig().mass_range[0] <= a.mass <= PrepConfig().mass_range[1]
        assert a.mass == pytest.approx(PrepConfig().density * visual.volume)
        assert len(a.hull_paths) == 1
        hull = _load(a.hull_paths[0])
        assert len(hull.vertices) <= objects.MAX_HULL_VERTICES
        assert hull.is_convex
        assert hull.volume == pytest.approx(visual.volume, rel=1e-6)


def test_tiny_set_is_reused_from_cache():
    first = objects.tiny_object_set()
    stamp = [os.stat(a.visual_path).st_mtime_ns for a in first]
    second = objects.tiny_object_set()
    assert first == second
    assert stamp == [os.stat(a.visual_path).st_mtime_ns for a in second]  # not rewritten


# --- preparing one mesh -----------------------------------------------------------------------------


def test_nonconvex_mesh_is_decomposed_into_hulls_covering_it(tmp_path):
    mesh = _l_shape()
    mesh.apply_translation([0.3, -0.2, 0.1])  # the file's frame is arbitrary
    path = _write(mesh, tmp_path / "l_shape.obj")
    asset, cached = objects.prepare_mesh(MeshSource("test/l", path, "user"))
    assert not cached and asset.name == "test/l" and asset.source == "user"
    record = objects.read_asset_record(asset)
    assert record["hull_method"] == "coacd"
    hulls = [_load(p) for p in asset.hull_paths]
    assert len(hulls) > 1
    for hull in hulls:
        assert hull.is_convex and len(hull.vertices) <= objects.MAX_HULL_VERTICES
    # Origin moved to the centre of mass; the recorded offset is where it was in the file.
    visual = _load(asset.visual_path)
    np.testing.assert_allclose(visual.center_mass, 0.0, atol=1e-6)
    np.testing.assert_allclose(record["origin_in_source"], mesh.center_mass, atol=1e-6)
    assert asset.mass == pytest.approx(PrepConfig().density * mesh.volume, rel=1e-6)
    # The union of the hulls is the L: agreement on random points of the bounding box.
    rng = np.random.default_rng(0)
    points = rng.uniform(visual.bounds[0] - 0.005, visual.bounds[1] + 0.005, size=(20000, 3))
    in_l = _inside_l(points + mesh.center_mass - [0.3, -0.2, 0.1])
    in_hulls = _inside_any_hull(points, hulls)
    iou = (in_l & in_hulls).sum() / (in_l | in_hulls).sum()
    assert iou > 0.85, iou


def test_convex_mesh_collides_as_its_hull_and_shift_does_not_matter(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)  # 642 vertices
    shifted = sphere.copy()
    shifted.apply_translation([0.1, 0.2, 0.3])
    a, _ = objects.prepare_mesh(MeshSource("s/a", _write(sphere, tmp_path / "a.ply"), "user"))
    b, _ = objects.prepare_mesh(MeshSource("s/b", _write(shifted, tmp_path / "b.ply"), "user"))
    assert objects.read_asset_record(a)["hull_method"] == "convex_hull"
    np.testing.assert_allclose(_load(a.visual_path).vertices, _load(b.visual_path).vertices, atol=1e-7)
    (hull,) = [_load(p) for p in a.hull_paths]
    assert len(hull.vertices) <= objects.MAX_HULL_VERTICES and hull.is_convex
    assert hull.volume == pytest.approx(sphere.volume, rel=1e-3)  # capped hulls keep the volume
    radius = np.linalg.norm(hull.vertices, axis=1)
    assert np.all(np.abs(radius - 0.03) < 0.003)


def test_cache_hit_returns_same_asset_without_recomputing(tmp_path):
    path = _write(_l_shape(), tmp_path / "l.stl")
    first, cached_first = objects.prepare_mesh(MeshSource("x/l", path, "user"))
    stamps = [os.stat(p).st_mtime_ns for p in (first.visual_path, *first.hull_paths)]
    second, cached_second = objects.prepare_mesh(MeshSource("x/l", path, "user"))
    assert (cached_first, cached_second) == (False, True)
    assert first == second
    assert stamps == [os.stat(p).st_mtime_ns for p in (second.visual_path, *second.hull_paths)]
    # Another name for the same bytes reuses the files; another configuration does not.
    renamed, cached = objects.prepare_mesh(MeshSource("y/other", path, "procedural"))
    assert cached and renamed.visual_path == first.visual_path and renamed.name == "y/other"
    other, cached = objects.prepare_mesh(MeshSource("x/l", path, "user"), PrepConfig(convex_ratio=0.5))
    assert not cached and other.visual_path != first.visual_path
    assert objects.read_asset_record(other)["hull_method"] == "convex_hull"  # 0.76 >= 0.5


def test_large_mesh_is_simplified(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.04)  # 20480 faces
    asset, _ = objects.prepare_mesh(MeshSource("s/big", _write(sphere, tmp_path / "big.obj"), "user"))
    visual = _load(asset.visual_path)
    assert len(visual.faces) <= PrepConfig().visual_faces
    assert visual.volume == pytest.approx(sphere.volume, rel=0.01)


def test_decimation_never_opens_a_closed_mesh():
    """The YCB knife's blade is a thin closed sheet: quadric decimation to 3000 faces pinches it (edges
    shared by more than two faces), so the preparation keeps the closed full mesh instead."""
    knife = next(s for s in objects.ycb_meshes() if s.name == "ycb/032_knife")
    mesh = meshprep.clean_mesh(meshprep.load_mesh(knife.path))
    assert mesh.is_watertight and len(mesh.faces) > 3000
    raw = mesh.simplify_quadric_decimation(face_count=3000)
    assert not trimesh.Trimesh(raw.vertices, raw.faces, process=True).is_watertight
    out = meshprep.simplify_mesh(mesh, 3000)
    assert out.is_watertight and len(out.faces) == len(mesh.faces)


@pytest.mark.parametrize(
    "content, reason",
    [
        (b"solid nothing\nthis is not an stl file", "cannot read mesh|no triangles"),
        (b"", "cannot read mesh|no triangles"),
    ],
)
def test_corrupt_file_raises_named_error(tmp_path, content, reason):
    path = tmp_path / "bad.stl"
    path.write_bytes(content)
    with pytest.raises(MeshPrepError, match=reason):
        objects.prepare_mesh(MeshSource("b/bad", str(path), "user"))


def test_mesh_in_millimetres_is_rejected(tmp_path):
    box = trimesh.creation.box((40.0, 50.0, 120.0))  # a 4 x 5 x 12 cm box written in mm
    with pytest.raises(MeshPrepError, match="metres"):
        objects.prepare_mesh(MeshSource("b/mm", _write(box, tmp_path / "mm.obj"), "user"))


def test_mass_properties_use_the_first_closed_solid_else_the_pieces():
    config = PrepConfig()
    box = trimesh.creation.box((0.04, 0.06, 0.1))
    box.apply_translation([0.01, 0.0, 0.0])
    open_box = box.copy()
    open_box.update_faces(np.arange(len(open_box.faces)) > 1)  # one side missing
    assert not open_box.is_watertight
    mass, volume, com = meshprep.mass_properties([open_box, box], [], config)
    assert volume == pytest.approx(0.04 * 0.06 * 0.1) and mass == pytest.approx(config.density * volume)
    np.testing.assert_allclose(com, [0.01, 0.0, 0.0], atol=1e-9)
    # No closed solid: volume-weighted centroid of the pieces (1 : 3 volumes at x = 0 and x = 0.1).
    small, big = trimesh.creation.box((0.02, 0.02, 0.02)), trimesh.creation.box((0.06, 0.02, 0.02))
    big.apply_translation([0.1, 0.0, 0.0])
    mass, volume, com = meshprep.mass_properties([open_box], [small, big], config)
    assert volume == pytest.approx(small.volume + big.volume)
    np.testing.assert_allclose(com, [0.075, 0.0, 0.0], atol=1e-9)
    assert mass == config.mass_range[0]  # 16 cm^3 at 500 kg/m^3 = 8 g, clamped up


def test_cap_hull_vertices_keeps_convexity_and_volume():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    for cap in (16, 32, 64):
        capped = meshprep.cap_hull_vertices(sphere, cap)
        assert len(capped.vertices) <= cap and capped.is_convex
        assert capped.volume == pytest.approx(sphere.volume, rel=1e-6)
    small = trimesh.creation.box((1, 2, 3))
    assert meshprep.cap_hull_vertices(small, 64) is small


# --- object sets ------------------------------------------------------------------------------------


def _user_folder(tmp_path):
    folder = tmp_path / "my_meshes"
    (folder / "sub").mkdir(parents=True)
    _write(trimesh.creation.box((0.04, 0.05, 0.10)), folder / "box.stl")
    _write(trimesh.creation.icosphere(subdivisions=2, radius=0.03), folder / "sub" / "ball.ply")
    _write(trimesh.creation.cylinder(radius=0.02, height=0.08, sections=16), folder / "can.obj")
    (folder / "broken.obj").write_text("v 0 0 0\nf 1 2 3\nthis is garbage\n")
    (folder / "notes.txt").write_text("not a mesh")
    return folder


def test_user_folder_is_an_object_set_and_bad_meshes_are_skipped_and_recorded(tmp_path):
    folder = _user_folder(tmp_path)
    with pytest.warns(UserWarning, match="broken"):
        assets = objects.load_object_set(str(folder))
    assert [a.name for a in assets] == ["my_meshes/box", "my_meshes/can", "my_meshes/sub/ball"]
    assert {a.source for a in assets} == {"user"}
    np.testing.assert_allclose(sorted(assets[0].extents), [0.04, 0.05, 0.10], atol=1e-6)
    report = objects.prepare_object_set(str(folder))
    assert report.cached == [a.name for a in assets] and not report.prepared
    (failure,) = report.failures
    assert failure.name == "my_meshes/broken" and failure.cached  # recorded by the first run
    with open(report.report_path) as f:
        recorded = json.load(f)["failures"]
    assert [f["name"] for f in recorded] == ["my_meshes/broken"] and recorded[0]["reason"]


def test_a_default_set_that_loses_a_member_is_an_error_naming_it():
    objects.tiny_object_set()  # generates the tiny meshes into this test's cache
    broken = next(s for s in objects.tiny_sources() if s.name == "tiny/box_b")
    with open(broken.path, "w") as f:  # a member's file goes bad
        f.write("this is not a mesh")
    with pytest.raises(objects.ObjectSetError, match=r"'tiny': 1 of 5 member.*tiny/box_b.*no triangles|cannot read"):
        objects.load_object_set("tiny")
    # Asked for explicitly, the loss is allowed, but said.
    with pytest.warns(UserWarning, match="tiny/box_b"):
        assert len(objects.load_object_set("tiny", strict=False)) == 4


def test_a_user_folder_may_skip_meshes_when_strict_is_off_only(tmp_path):
    folder = _user_folder(tmp_path)
    with pytest.raises(objects.ObjectSetError, match="my_meshes/broken"):
        objects.load_object_set(str(folder), strict=True)


def test_object_set_identity_is_the_hash_of_the_names():
    assets = objects.tiny_object_set()
    identity = objects.object_set_identity("tiny", assets)
    assert identity["size"] == 5 and identity["name"] == "tiny" and identity["skipped"] == []
    assert identity == objects.object_set_identity("tiny", assets[::-1])  # order does not matter
    assert objects.object_set_identity("tiny", assets[:4])["hash"] != identity["hash"]


def test_an_environment_failure_is_not_recorded_and_goes_with_its_fix(tmp_path):
    """A Python where fast-simplification cannot be imported (as open3d without libusb once was): the big
    mesh fails naming the environment, nothing is recorded, and the next run in a working environment
    prepares it."""
    import subprocess
    import sys

    (tmp_path / "meshes").mkdir()
    path = _write(trimesh.creation.icosphere(subdivisions=5, radius=0.04), tmp_path / "meshes" / "big.obj")
    script = (
        "import sys; sys.modules['fast_simplification'] = None\n"  # import fails as for a missing package
        "from envs import objects\n"
        "report = objects.prepare_meshes([objects.MeshSource('s/big', sys.argv[1], 'user')])\n"
        "(f,) = report.failures\n"
        "assert f.environment and not f.cached and 'fast-simplification' in f.reason, f\n"
        "try:\n"
        "    objects.load_object_set_report(sys.argv[2], strict=True)\n"
        "except objects.ObjectSetError as exc:\n"
        "    assert 'fix the environment' in str(exc), exc\n"
        "else:\n"
        "    raise AssertionError('no error')\n"
    )
    run = subprocess.run([sys.executable, "-c", script, path, str(tmp_path / "meshes")], capture_output=True,
                         text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    assert not list(objects.prepared_root().glob("*.failed.json"))
    asset, cached = objects.prepare_mesh(MeshSource("s/big", path, "user"))
    assert not cached and len(_load(asset.visual_path).faces) <= PrepConfig().visual_faces


def test_a_recorded_failure_is_retried_when_the_environment_changed(tmp_path):
    path = tmp_path / "bad.stl"
    path.write_bytes(b"solid nothing\nthis is not an stl file")
    source = MeshSource("x/bad", str(path), "user")
    with pytest.raises(MeshPrepError) as first:
        objects.prepare_mesh(source)
    assert not isinstance(first.value, objects.RecordedFailure)
    (record_path,) = objects.prepared_root().glob("*.failed.json")
    record = json.loads(record_path.read_text())
    assert record["environment"] == objects.prep_environment()
    with pytest.raises(objects.RecordedFailure):  # same environment: the recorded failure is used
        objects.prepare_mesh(source)
    record["environment"] = {**record["environment"], "trimesh": "0.0.1"}  # recorded under another trimesh
    record_path.write_text(json.dumps(record))
    with pytest.raises(MeshPrepError) as again:  # tried again (and fails again, for the mesh's own reason)
        objects.prepare_mesh(source)
    assert not isinstance(again.value, objects.RecordedFailure)


def test_parallel_workers_give_the_same_assets(tmp_path):
    folder = _user_folder(tmp_path)
    parallel = objects.prepare_object_set(str(folder), workers=2)
    assert len(parallel.prepared) == 3 and len(parallel.failures) == 1
    serial = objects.prepare_object_set(str(folder), workers=1)
    assert serial.assets == parallel.assets and len(serial.cached) == 3


def test_unknown_set_and_bad_folders_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown object set"):
        objects.load_object_set("ycb-typo")
    with pytest.raises(ValueError, match="does not exist"):
        objects.load_object_set(str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no"):
        objects.load_object_set(str(tmp_path / "empty"))


def test_rest_width_is_the_width_an_object_lies_at():
    # A box lies on its largest face: a gripper closing horizontally must span its middle side.
    assert meshprep.rest_width(trimesh.creation.box((0.03, 0.08, 0.12))) == pytest.approx(0.08, abs=1e-6)
    # A flat can lies on its base (its diameter), a long one on its side (its diameter again).
    assert meshprep.rest_width(trimesh.creation.cylinder(0.04, 0.03, sections=64)) == pytest.approx(0.08, abs=1e-3)
    assert meshprep.rest_width(trimesh.creation.cylinder(0.02, 0.12, sections=64)) == pytest.approx(0.04, abs=1e-3)
    # A cube of side s: s in every resting pose.
    assert meshprep.rest_width(trimesh.creation.box((0.05, 0.05, 0.05))) == pytest.approx(0.05, abs=1e-6)


@pytest.fixture(scope="module")
def _ycb_cache(tmp_path_factory):
    """One cache for the tests that apply the size rule to the 78 YCB meshes: their rest widths (~1 s a
    mesh) are computed once, then read back as every user's second run does."""
    return str(tmp_path_factory.mktemp("ycb_cache"))


@pytest.fixture
def ycb_cache(_ycb_cache, monkeypatch):
    monkeypatch.setenv("SGJAX_CACHE", _ycb_cache)  # after the autouse per-test cache: this one wins


def test_ycb_filter_on_the_real_meshes(ycb_cache):
    every = objects.ycb_meshes()
    assert len(every) == 78
    graspable = objects.object_sources("ycb")
    names = {s.name for s in graspable}
    spec = GripperSpec()
    limit = spec.max_opening - 2 * spec.contact_threshold
    sized = set()
    for source in every:  # the bounding-box part of the rule, checked on independently loaded meshes
        extents = np.sort(_load(source.path).extents)
        if extents[0] <= limit and 0.03 <= extents[2] <= 0.25:
            sized.add(source.name)
    assert names <= sized
    # The resting part, on a few meshes: a tuna can or a sugar box lying flat is too wide to take.
    for name, expected in [("ycb/007_tuna_fish_can", False), ("ycb/004_sugar_box", False),
                           ("ycb/058_golf_ball", True), ("ycb/032_knife", True)]:
        path = next(s.path for s in every if s.name == name)
        assert (meshprep.rest_width(_load(path)) <= limit) == expected, name
        assert (name in names) == expected, name
    assert not names & {"ycb/029_plate", "ycb/062_dice", "ycb/019_pitcher_base", "ycb/048_hammer"}
    # A smaller gripper admits fewer objects.
    small = objects.ycb_graspable(GripperSpec(max_opening=0.05, palm_size=(0.08, 0.03, 0.02)))
    assert {s.name for s in small} < names


def test_seen_unseen_split_is_deterministic_and_disjoint(ycb_cache):
    seen, unseen = objects.object_sources("ycb-seen"), objects.object_sources("ycb-unseen")
    assert seen == objects.object_sources("ycb-seen") and unseen == objects.object_sources("ycb-unseen")
    seen_names, unseen_names = {s.name for s in seen}, {s.name for s in unseen}
    assert not seen_names & unseen_names
    assert seen_names | unseen_names == {s.name for s in objects.object_sources("ycb")}
    assert unseen_names <= {f"ycb/{n}" for n in objects.YCB_UNSEEN} and len(unseen) >= 5
    everything_seen = objects.object_sources("seen")
    assert everything_seen == seen + objects.object_sources("procedural")
    everything_unseen = objects.object_sources("unseen")
    assert everything_unseen == unseen + objects.object_sources("procedural-unseen")
    assert len(everything_seen) >= 20 and len(everything_unseen) >= 10
    # The unseen procedural family shares no mesh with the seen one.
    assert not {s.path for s in everything_seen} & {s.path for s in everything_unseen}


# --- procedural objects -------------------------------------------------------------------------------


def test_procedural_objects_are_deterministic_graspable_solids():
    spec = GripperSpec()
    kinds = set()
    for index in range(len(procedural.KINDS)):  # one object of each kind (kinds cycle with the index)
        name, mesh = procedural.procedural_object(index, seed=0)
        again = procedural.procedural_object(index, seed=0)[1]
        np.testing.assert_array_equal(mesh.vertices, again.vertices)
        assert not np.allclose(procedural.procedural_object(index, seed=1)[1].extents, mesh.extents)
        assert mesh.is_watertight and mesh.volume > 0
        assert objects.fits_gripper(mesh.extents, spec, rest=meshprep.rest_width(mesh)), (name, mesh.extents)
        kinds.add(name.split("_")[0])
    assert kinds == set(procedural.KINDS)


# --- CLI ----------------------------------------------------------------------------------------------


def test_cli_prepare_and_list(tmp_path, capsys):
    folder = _user_folder(tmp_path)
    assert main(["objects", "list", "--objects", str(folder)]) == 0  # lists only; prepares nothing
    assert "not prepared yet" in capsys.readouterr().err
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["objects", "prepare", "--objects", str(folder), "--quiet"]) == 1  # one skipped
    out = capsys.readouterr().out
    assert "3 ready (3 prepared now, 0 cached), 1 skipped" in out and "my_meshes/broken" in out
    assert main(["objects", "list", "--objects", str(folder), "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["name"] for r in rows] == ["my_meshes/box", "my_meshes/can", "my_meshes/sub/ball"]
    assert all(len(r["extents"]) == 3 and r["mass"] > 0 and r["hull_paths"] for r in rows)
    assert main(["objects", "prepare", "--set", "tiny", "--quiet"]) == 0
    assert "5 ready" in capsys.readouterr().out
    assert main(["objects", "list", "--set", "nope"]) == 2
