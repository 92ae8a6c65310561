"""Primitive meshes, template placement and the paper's width rule, against exact geometry."""

from __future__ import annotations

import numpy as np
import pytest

from sgjax.geometry.gripper import GripperSpec, points_in_closing_region
from sgjax.stage1.database import DBConfig, build_database, database_shapes
from sgjax.stage1.primitives import (
    FRAME_SYMMETRIES,
    Primitive,
    canonical_grasp,
    closing_widths,
    grasp_frame,
    primitive_mesh,
    surface_points,
    symmetrize,
    template_grasps,
    unique_grasps,
)

SPEC = GripperSpec()
DELTA = SPEC.contact_threshold


@pytest.mark.parametrize(
    "p",
    [
        Primitive("cuboid", (0.08, 0.04, 0.03)),
        Primitive("cylinder", (0.04, 0.04, 0.1)),
        Primitive("elliptical_cylinder", (0.05, 0.03, 0.08)),
        Primitive("frustum", (0.05, 0.03, 0.08)),
    ],
)
def test_meshes_are_watertight_and_centred(p):
    mesh = primitive_mesh(p)
    assert mesh.is_watertight
    np.testing.assert_allclose(mesh.bounds[1] - mesh.bounds[0], p.extents, atol=1e-4)
    np.testing.assert_allclose(mesh.bounds.mean(0), 0.0, atol=1e-4)


def test_frustum_radius_tapers_from_bottom_to_top():
    pts = surface_points(Primitive("frustum", (0.06, 0.02, 0.1)), 4000)
    r = np.linalg.norm(pts[:, :2], axis=1)
    bottom, top = pts[:, 2] < -0.049, pts[:, 2] > 0.049
    assert r[bottom].max() == pytest.approx(0.03, abs=1e-3)
    assert r[top].max() == pytest.approx(0.01, abs=1e-3)


def test_width_rule_on_a_box_is_extent_plus_two_delta():
    p = Primitive("cuboid", (0.2, 0.04, 0.1))
    pts = surface_points(p, 20000)
    # From the top (+z face), closing along y across the 4 cm extent, fingertips 3 cm deep.
    pose = grasp_frame(np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), np.array([0, 0, 0.05 + 0.02]))
    w = closing_widths(pts, pose[None], SPEC)[0]
    assert w == pytest.approx(0.04 + 2 * DELTA, abs=1e-3)
    # Closing along x across 20 cm exceeds the 8 cm opening: dropped (NaN).
    pose_x = grasp_frame(np.array([0, 0, -1.0]), np.array([1.0, 0, 0]), np.array([0, 0, 0.07]))
    assert np.isnan(closing_widths(pts, pose_x[None], SPEC)[0])
    # A grasp beside the box closes on nothing: dropped.
    air = grasp_frame(np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), np.array([0.3, 0, 0.07]))
    assert np.isnan(closing_widths(pts, air[None], SPEC)[0])


def test_width_rule_on_an_off_centre_chord():
    r, y0 = 0.025, 0.012
    pts = surface_points(Primitive("cylinder", (2 * r, 2 * r, 0.06)), 40000)
    # From the top, closing along x, shifted by y0 along the finger-width axis (world y).
    pose = grasp_frame(np.array([0, 0, -1.0]), np.array([1.0, 0, 0]), np.array([0, y0, 0.03 + 0.02]))
    # The fingers (width 2 cm) cover |y - y0| <= 1 cm; the widest chord there is at y = y0 - 1 cm.
    half_chord = np.sqrt(r**2 - (y0 - 0.5 * SPEC.finger_width) ** 2)
    w = closing_widths(pts, pose[None], SPEC)[0]
    assert w == pytest.approx(2 * (half_chord + DELTA), abs=1.5e-3)


@pytest.mark.parametrize("family", ["cuboid", "cylinder", "elliptical_cylinder", "frustum"])
def test_templates_hold_the_object_between_open_fingers(family):
    dims = {"cuboid": (0.1, 0.045, 0.03), "cylinder": (0.045, 0.045, 0.12),
            "elliptical_cylinder": (0.05, 0.035, 0.1), "frustum": (0.05, 0.035, 0.09)}[family]
    p = Primitive(family, dims)
    poses, widths = template_grasps(p, SPEC)
    assert 20 <= len(poses) <= 400
    assert np.all(widths <= SPEC.max_opening) and np.all(widths > 2 * DELTA)
    pts = surface_points(p, 5000, seed=1)
    between = np.asarray(points_in_closing_region(pts.astype(np.float32), poses.astype(np.float32), widths, SPEC))
    assert np.all(between.sum(1) > 0)
    # Every template is a proper rigid transform with z = approach, x = closing.
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)


def test_too_large_primitive_has_no_templates():
    poses, widths = template_grasps(Primitive("cuboid", (0.2, 0.2, 0.2)), SPEC)
    assert len(poses) == 0 and len(widths) == 0


def test_symmetrize_closes_the_set_and_dedups_jaw_flips():
    poses, widths = template_grasps(Primitive("frustum", (0.05, 0.03, 0.08)), SPEC)
    sym, sym_w = symmetrize(poses, widths)
    assert len(sym) >= len(poses)
    for g in FRAME_SYMMETRIES:
        flip = np.eye(4)
        flip[:3, :3] = g
        again, _ = unique_grasps(np.concatenate([sym, flip @ sym]), np.concatenate([sym_w, sym_w]))
        assert len(again) == len(sym)  # flipping adds nothing: the set is closed
    turned = poses.copy()
    turned[:, :3, :2] *= -1  # the same grasps turned 180 deg about approach
    both, _ = unique_grasps(np.concatenate([poses, turned]), np.concatenate([widths, widths]))
    assert len(both) == len(unique_grasps(poses, widths)[0])
    np.testing.assert_allclose(canonical_grasp(turned), canonical_grasp(poses))


def test_db_build_is_deterministic_and_round_trips(tmp_path):
    from sgjax.stage1.database import load_database_file, save_database

    cfg = DBConfig(scales=(0.06,), cuboid_ratios=(0.5,), cylinder_aspects=(1.5,), elliptical_ratios=(0.6,),
                   elliptical_aspects=(1.0,), frustum_ratios=(0.6,), frustum_aspects=(1.2,))
    a = build_database(cfg, workers=2, progress=False)
    b = build_database(cfg, workers=1, progress=False)
    assert len(a) == 4 and set(a.family.tolist()) == {0, 1, 2, 3}
    path = tmp_path / "db.npz"
    save_database(a, path)
    c = load_database_file(path)
    for name in ("family", "dims", "sq_scale", "sq_epsilon", "sq_rotation", "grasp_offsets", "grasps", "widths"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        np.testing.assert_array_equal(getattr(a, name), getattr(c, name), err_msg=name)
    assert c.config_key == cfg.key() != DBConfig().key()


def test_bad_database_files(tmp_path):
    from sgjax.stage1.database import load_database_file

    with pytest.raises(FileNotFoundError, match="sgjax build-db"):
        load_database_file(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not a readable primitive database"):
        load_database_file(bad)
    old = tmp_path / "old.npz"
    np.savez(old, meta=np.asarray('{"version": 0}'))
    with pytest.raises(ValueError, match="format v0"):
        load_database_file(old)


def test_default_grid_has_about_1200_primitives():
    shapes = database_shapes(DBConfig())
    assert 1500 <= len(shapes) <= 1700  # ~1.2k remain after the template-count cut (README)
    assert {p.family for p in shapes} == {"cuboid", "cylinder", "frustum", "elliptical_cylinder"}


def test_small_db_fits_match_primitive_sizes(small_db):
    """EMS on full surface samples recovers box and cylinder extents (frusta taper: not compared)."""
    good, total = 0, 0
    for i in range(len(small_db)):
        p = small_db.primitive(i)
        if p.family in ("cuboid", "cylinder", "elliptical_cylinder"):
            err = np.abs(np.sort(2 * small_db.sq_scale[i]) - np.sort(p.extents))
            good += bool(np.all(err <= 0.08 * np.sort(p.extents) + 2e-3))
            total += 1
    assert good >= 0.9 * total
    counts = small_db.num_grasps
    assert counts.min() >= 20 and counts.max() <= 400


def test_the_default_database_ships_and_loads_without_a_build(tmp_path, monkeypatch):
    """The package carries the default database for the current DBConfig / BUILD_VERSION (a change to
    either needs `sgjax build-db --force --ship`), and an empty cache loads it without building."""
    from sgjax.stage1 import database

    shipped = database.shipped_path(DBConfig())
    assert shipped.is_file(), "refresh the shipped database: sgjax build-db --force --ship"
    assert sorted(p.name for p in database.SHIPPED_DIR.glob("*.npz")) == [shipped.name]  # no stale copies
    monkeypatch.setenv("SGJAX_CACHE", str(tmp_path / "empty"))
    db = database.load_database(build=False)
    assert db.config_key == DBConfig().key() and not database.default_path().exists()
    assert len(db) > 1000 and np.all(np.isfinite(db.grasps)) and db.grasp_offsets[-1] == len(db.grasps)
    spec = GripperSpec()
    assert np.all((db.widths > 0) & (db.widths <= spec.max_opening))
