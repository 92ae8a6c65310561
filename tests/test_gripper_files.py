"""Gripper files (sgjax.geometry.gripper_files): presets, round trips, validation, the database key, and
the simulated gripper built from each preset against Stage 1's boxes."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import mujoco
import numpy as np
import pytest

from envs import gripper_model
from sgjax.geometry.gripper import PANDA_HAND, GripperSpec, closing_box, hand_boxes
from sgjax.geometry.gripper_files import (
    FIELDS,
    GripperFileError,
    gripper_from_dict,
    gripper_to_dict,
    load_gripper,
    preset_names,
    save_gripper,
)
from sgjax.stage1.database import DBConfig, shipped_path

PRESETS = ("default", "franka-hand", "robotiq-2f85", "ag-105-145")
SHIPPED_DB = "primitive_db-v1-fefb50bbd1e8.npz"  # sgjax/models/primitive_db/, built for GripperSpec()


def test_presets_load_and_validate():
    assert set(PRESETS) <= set(preset_names()) and preset_names()[0] == "default"
    for name in PRESETS:
        spec = load_gripper(name)
        assert isinstance(spec, GripperSpec)
        assert spec.palm_size[0] >= spec.max_opening + 2 * spec.finger_thickness
        assert spec.closing_force > 0 and spec.finger_friction > 0
    assert load_gripper("default") == GripperSpec()
    assert load_gripper("franka-hand") == dataclasses.replace(PANDA_HAND, closing_force=70.0)
    robotiq, ag = load_gripper("robotiq-2f85"), load_gripper("ag-105-145")
    assert (robotiq.max_opening, robotiq.finger_width, robotiq.closing_force) == (0.085, 0.022, 20.0)
    assert (ag.max_opening, ag.closing_force) == (0.145, 35.0)


def test_default_gripper_keeps_its_database_key_and_cache_keys():
    # The shipped database is found by DBConfig.key(), which hashes dataclasses.asdict(spec): the new
    # physical values must not enter it, nor the repr that other cache keys are made of.
    key = DBConfig().key()
    assert shipped_path().name == SHIPPED_DB == f"primitive_db-v1-{key}.npz"
    assert shipped_path().is_file()
    assert DBConfig(spec=load_gripper("default")).key() == key
    assert repr(GripperSpec()) == (
        "GripperSpec(max_opening=0.08, finger_length=0.05, finger_width=0.02, finger_thickness=0.01, "
        "palm_size=(0.1, 0.03, 0.02), deepen=0.008, refine_angles_deg=(-15.0, 0.0, 15.0), contact_threshold=0.0125)"
    )
    assert hash(GripperSpec()) == hash(tuple(getattr(GripperSpec(), f.name) for f in dataclasses.fields(GripperSpec)))
    # Every other preset has its own database; a spec differing only in force or friction builds the
    # same database (its content depends on the geometry only), so it shares the key.
    keys = {name: DBConfig(spec=load_gripper(name)).key() for name in PRESETS}
    assert len(set(keys.values())) == len(PRESETS)
    assert DBConfig(spec=GripperSpec(closing_force=70.0, finger_friction=0.5)).key() == key


def test_physical_values_compare_print_and_survive_replace():
    strong = GripperSpec(closing_force=70.0)
    assert strong != GripperSpec() and hash(strong) != hash(GripperSpec())
    assert repr(strong).endswith("contact_threshold=0.0125, closing_force=70.0)")
    assert dataclasses.replace(strong, deepen=0.0).closing_force == 70.0
    assert "closing_force" not in dataclasses.asdict(strong)
    with pytest.raises(ValueError, match="closing_force"):
        GripperSpec(closing_force=0.0)


@pytest.mark.parametrize("ext", [".toml", ".json"])
def test_file_round_trip(tmp_path, ext):
    custom = GripperSpec(
        max_opening=0.1, finger_length=0.045, finger_width=0.025, finger_thickness=0.012,
        palm_size=(0.13, 0.04, 0.03), deepen=0.005, refine_angles_deg=(-10.0, 10.0), contact_threshold=0.01,
        closing_force=42.5, finger_friction=0.8,
    )
    for spec in [custom, *(load_gripper(n) for n in PRESETS)]:
        path = save_gripper(spec, tmp_path / f"gripper{ext}")
        assert load_gripper(path) == spec and load_gripper(str(path)) == spec
        assert gripper_from_dict(gripper_to_dict(spec)) == spec
    data = json.loads(json.dumps(gripper_to_dict(custom)))  # plain JSON values
    assert list(data) == list(FIELDS) and data["closing_force"] == 42.5


def test_optional_fields_take_the_defaults(tmp_path):
    path = tmp_path / "minimal.json"
    required = {k: v for k, v in gripper_to_dict(GripperSpec()).items()
                if k not in ("finger_friction", "deepen", "refine_angles_deg", "contact_threshold")}
    path.write_text(json.dumps(required))
    assert load_gripper(path) == GripperSpec()


GOOD = gripper_to_dict(GripperSpec())


def _toml(changes: dict, drop: tuple = ()) -> str:
    """A TOML gripper file: the default gripper's fields with `changes`, without `drop`."""
    data = {k: v for k, v in {**GOOD, **changes}.items() if k not in drop}
    return "".join(f"{key} = {_toml_value(value)}\n" for key, value in data.items())


def _toml_value(value) -> str:
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


@dataclasses.dataclass
class Raw:
    text: str


# (changes, dropped fields, the field the error must name (None: the file), words the message must hold)
BAD_FIELDS = [
    ({}, ("finger_width",), "finger_width", "missing required field finger_width"),
    ({}, ("palm_size", "closing_force"), "palm_size", "missing required fields palm_size, closing_force"),
    ({"finger_lenght": 0.05}, (), "finger_lenght", "did you mean 'finger_length'"),
    ({"finger_width": -0.01}, (), "finger_width", "finger_width: must be positive"),
    ({"max_opening": 0.0}, (), "max_opening", "max_opening: must be positive"),
    ({"palm_size": [0.1, 0.0, 0.02]}, (), "palm_size", "palm_size[1]: must be positive"),
    ({"palm_size": [0.1, 0.03]}, (), "palm_size", "palm_size: must be a list of 3"),
    ({"max_opening": 85.0, "palm_size": [100.0, 0.03, 0.02]}, (), "max_opening", "metres"),
    ({"finger_length": "5cm"}, (), "finger_length", "finger_length: must be a number, got '5cm'"),
    ({"closing_force": True}, (), "closing_force", "closing_force: must be a number"),
    ({"finger_thickness": Raw("nan")}, (), "finger_thickness", "finger_thickness: must be finite"),
    ({"finger_width": Raw("{ a = 1 }")}, (), "finger_width", "must be a number, got a table"),
    ({"closing_force": 0.0}, (), "closing_force", "closing_force: must be positive"),
    ({"finger_friction": -0.5}, (), "finger_friction", "finger_friction: must be positive"),
    ({"deepen": -0.001}, (), "deepen", "deepen: must be >= 0"),
    ({"refine_angles_deg": []}, (), "refine_angles_deg", "refine_angles_deg: must be a non-empty list"),
    ({"refine_angles_deg": [0.0, 200.0]}, (), "refine_angles_deg", "refine_angles_deg[1]"),
    ({"max_opening": 0.03, "finger_thickness": 0.04, "palm_size": [0.2, 0.03, 0.02]}, (), "max_opening",
     "smaller than finger_thickness"),
    ({"contact_threshold": 0.05}, (), "contact_threshold", "max_opening > 2 * contact_threshold"),
    ({"palm_size": [0.09, 0.03, 0.02]}, (), "palm_size", "palm_size[0]: the palm (0.09 m) is narrower than the open fingers' span"),
]


def _one_line_error(path, field, words) -> GripperFileError:
    with pytest.raises(GripperFileError) as info:
        load_gripper(path)
    message = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "\n" not in message and str(path) in message
    assert words in message, message
    assert info.value.field == field
    if field is not None:
        assert field in message
    return info.value


@pytest.mark.parametrize("changes, drop, field, words", BAD_FIELDS)
def test_bad_fields_give_one_line_naming_the_field(tmp_path, changes, drop, field, words):
    path = tmp_path / "bad.toml"
    path.write_text(_toml(changes, drop))
    _one_line_error(path, field, words)
    # The same data through JSON (where it can be written as JSON) gives the same error.
    if not any(isinstance(v, Raw) for v in changes.values()):
        data = {k: v for k, v in {**GOOD, **changes}.items() if k not in drop}
        json_path = tmp_path / "bad.json"
        json_path.write_text(json.dumps(data))
        _one_line_error(json_path, field, words)


def test_bad_files_give_one_line_errors(tmp_path, monkeypatch):
    (tmp_path / "g.yaml").write_text("max_opening: 0.08\n")
    _one_line_error(tmp_path / "g.yaml", None, "unknown extension '.yaml'")
    _one_line_error(tmp_path / "absent.toml", None, "no such file")
    (tmp_path / "folder.json").mkdir()
    _one_line_error(tmp_path / "folder.json", None, "not a file")
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfe\x00max")
    _one_line_error(tmp_path / "binary.toml", None, "not UTF-8 text")
    (tmp_path / "syntax.toml").write_text("max_opening = \nfinger_length = 0.05\n")
    _one_line_error(tmp_path / "syntax.toml", None, "not valid TOML")
    (tmp_path / "syntax.json").write_text('{"max_opening": 0.08,\n}')
    _one_line_error(tmp_path / "syntax.json", None, "not valid JSON")
    (tmp_path / "list.json").write_text("[0.08, 0.05]")
    _one_line_error(tmp_path / "list.json", None, "top level must be a table of fields")
    (tmp_path / "twice.json").write_text('{"max_opening": 0.08, "max_opening": 0.09}')
    _one_line_error(tmp_path / "twice.json", "max_opening", "max_opening: given twice")
    locked = tmp_path / "locked.toml"
    locked.write_text(_toml({}))
    locked.chmod(0)
    if os.geteuid() == 0:  # root reads anything: make the read fail as it would for a user
        monkeypatch.setattr(Path, "read_text", lambda *a, **k: (_ for _ in ()).throw(PermissionError(13, "Permission denied")))
    _one_line_error(locked, None, "cannot be read: Permission denied")


def test_unknown_preset_lists_the_presets(tmp_path):
    with pytest.raises(GripperFileError) as info:
        load_gripper("robotiq-2f140")
    message = str(info.value)
    assert "unknown gripper preset 'robotiq-2f140'" in message and "\n" not in message
    assert all(name in message for name in PRESETS)
    with pytest.raises(GripperFileError, match="unknown extension"):
        save_gripper(GripperSpec(), tmp_path / "g.yml")
    # A spec that would not load back is not written.
    with pytest.raises(GripperFileError, match="max_opening: the stroke"):
        save_gripper(GripperSpec(max_opening=0.03, finger_thickness=0.04, palm_size=(0.2, 0.03, 0.02)), tmp_path / "g.toml")
    assert not (tmp_path / "g.toml").exists()


# ---------------------------------------------------------------------------------------------
# The simulated gripper against Stage 1's geometry.


def _gripper_model(spec: GripperSpec, physics: gripper_model.GripperPhysics | None = None):
    mj = mujoco.MjSpec()
    gripper_model.add_gripper(mj, spec, physics or gripper_model.GripperPhysics())
    model = mj.compile()
    return model, mujoco.MjData(model)


def _ids(model, kind, names):
    return [mujoco.mj_name2id(model, kind, n) for n in names]


def _local_box(model, data, geom: int, body: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of a box geom in the gripper body's frame (the gripper frame)."""
    rotation = data.xmat[body].reshape(3, 3)
    centre = rotation.T @ (data.geom_xpos[geom] - data.xpos[body])
    axes = rotation.T @ data.geom_xmat[geom].reshape(3, 3)
    np.testing.assert_allclose(np.abs(axes), np.eye(3), atol=1e-9)  # axis-aligned in the gripper frame
    half = model.geom_size[geom]
    return centre - half, centre + half


@pytest.mark.parametrize("name", PRESETS)
def test_simulated_gripper_matches_stage1_boxes(name):
    spec = load_gripper(name)
    model, data = _gripper_model(spec)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, gripper_model.GRIPPER_BODY)
    joints = _ids(model, mujoco.mjtObj.mjOBJ_JOINT, gripper_model.FINGER_JOINTS)
    pads = _ids(model, mujoco.mjtObj.mjOBJ_GEOM, gripper_model.FINGER_GEOMS)  # left (-x), right (+x)
    palm = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, gripper_model.PALM_GEOM)
    actuators = _ids(model, mujoco.mjtObj.mjOBJ_ACTUATOR, gripper_model.FINGER_ACTUATORS)

    # The stroke: each finger travels max_opening / 2, and its servo cannot ask for more.
    opening = sum(model.jnt_range[j][1] for j in joints)
    assert opening == pytest.approx(spec.max_opening, abs=1e-12)
    assert all(model.jnt_range[j][0] == 0.0 for j in joints)
    assert all(model.actuator_ctrlrange[a][1] == pytest.approx(0.5 * spec.max_opening) for a in actuators)
    # The physical values come from the spec.
    for a in actuators:
        np.testing.assert_allclose(model.actuator_forcerange[a], [-spec.closing_force, spec.closing_force])
    for g in pads:
        assert model.geom_friction[g][0] == spec.finger_friction

    for width in (spec.max_opening, 0.5 * spec.max_opening, 0.0):
        data.qpos[[model.jnt_qposadr[j] for j in joints]] = 0.5 * width
        mujoco.mj_forward(model, data)
        right, left, palm_box = hand_boxes(spec, width)
        for geom, box in ((pads[0], left), (pads[1], right), (palm, palm_box)):
            lo, hi = _local_box(model, data, geom, body)
            np.testing.assert_allclose(lo, np.asarray(box[0], float), atol=1e-9)
            np.testing.assert_allclose(hi, np.asarray(box[1], float), atol=1e-9)
        # The inner faces bound the closing region, over its y and z extents.
        closing_lo, closing_hi = (np.asarray(v, float) for v in closing_box(spec, width))
        left_lo, left_hi = _local_box(model, data, pads[0], body)
        right_lo, right_hi = _local_box(model, data, pads[1], body)
        assert left_hi[0] == pytest.approx(closing_lo[0], abs=1e-9)
        assert right_lo[0] == pytest.approx(closing_hi[0], abs=1e-9)
        np.testing.assert_allclose([left_lo[1:], right_lo[1:]], [closing_lo[1:]] * 2, atol=1e-9)
        np.testing.assert_allclose([left_hi[1:], right_hi[1:]], [closing_hi[1:]] * 2, atol=1e-9)

    # Driven open from closed, the fingers stop at the spec's max_opening.
    mujoco.mj_resetData(model, data)
    data.ctrl[actuators] = model.actuator_ctrlrange[actuators, 1]
    mujoco.mj_step(model, data, nstep=int(0.5 / model.opt.timestep))
    reached = sum(data.qpos[model.jnt_qposadr[j]] for j in joints)
    assert reached == pytest.approx(spec.max_opening, abs=1e-3)


def test_default_simulated_gripper_is_unchanged_and_physics_overrides_still_apply():
    # The values the simulation used before the spec carried them (GripperPhysics' constants).
    model, _ = _gripper_model(GripperSpec())
    pads = _ids(model, mujoco.mjtObj.mjOBJ_GEOM, gripper_model.FINGER_GEOMS)
    palm = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, gripper_model.PALM_GEOM)
    for a in range(model.nu):
        np.testing.assert_array_equal(model.actuator_forcerange[a], [-25.0, 25.0])
        assert model.actuator_gainprm[a][0] == 2000.0 and model.actuator_biasprm[a][1:3].tolist() == [-2000.0, -20.0]
    for g in [*pads, palm]:
        np.testing.assert_array_equal(model.geom_friction[g], [1.0, 0.005, 0.0001])
    # A GripperPhysics changed from its defaults (an experiment, e.g. a weak grip) still wins over the spec.
    weak = gripper_model.GripperPhysics(grip_force=0.6, friction=(0.3, 0.005, 0.0001))
    model, _ = _gripper_model(load_gripper("franka-hand"), weak)
    np.testing.assert_array_equal(model.actuator_forcerange[0], [-0.6, 0.6])
    assert model.geom_friction[pads[0]][0] == 0.3
    # A stronger gripper gets stiffer servos, so its force still saturates 1.25 cm from the goal.
    model, _ = _gripper_model(load_gripper("franka-hand"))
    assert model.actuator_gainprm[0][0] == pytest.approx(70.0 / 0.0125)
    assert model.geom_friction[palm].tolist() == pytest.approx([1.0, 0.005, 0.0001])
