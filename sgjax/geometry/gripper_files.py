"""A gripper is a file: `GripperSpec` as TOML or JSON, and the presets shipped with the package.

    spec = load_gripper("robotiq-2f85")        # a preset (sgjax/grippers/robotiq-2f85.toml)
    spec = load_gripper("my_gripper.toml")     # a file: .toml or .json
    save_gripper(spec, "copy.json")            # gripper_to_dict(spec) as TOML or JSON

A gripper file is one flat table of fields (units: metres, newtons, degrees):

    max_opening = 0.085              # required: the stroke, largest distance between the inner faces
    finger_length = 0.0375           # required: fingertip length along the approach (paper "L")
    finger_width = 0.022             # required: finger extent across the closing direction
    finger_thickness = 0.02          # required: finger extent along the closing direction
    palm_size = [0.145, 0.065, 0.12] # required: the palm box behind the fingers (x closing, y, z approach)
    closing_force = 20.0             # required: N each finger presses with (the datasheet's grip force)
    finger_friction = 1.0            # optional (1.0): sliding friction of the pads in the simulation
    deepen = 0.008                   # optional (0.008): refinement step along the approach
    refine_angles_deg = [-15.0, 0.0, 15.0]  # optional: refinement turns about the approach
    contact_threshold = 0.0125       # optional (0.0125): paper "delta" of the width rule

A preset and a user's file go through the same reader and the same checks; every problem is a
`GripperFileError` (a ValueError) with a one-line message that names the file and the field:
  * the file: an extension other than .toml / .json, a missing or unreadable file, a syntax error, a
    top level that is not a table of fields, a field given twice (JSON);
  * the fields: a missing required field, an unknown field (with the nearest known name), a value that
    is not a number (or, for palm_size / refine_angles_deg, not a list of numbers: 3 for the palm, at
    least one angle), not finite, a size <= 0 or >= 1 m (sizes are metres: a size of a metre or more is
    almost surely millimetres), a closing_force or finger_friction <= 0, a negative deepen or
    contact_threshold, an angle outside [-180, 180];
  * between fields: max_opening below finger_thickness (see `check_fields`), max_opening not above
    2 * contact_threshold (the width rule opens the fingers contact_threshold beyond each side of what
    they grasp, so no object would fit), palm_size[0] narrower than the open fingers' span
    max_opening + 2 * finger_thickness (the palm carries both fingers at full opening, as GripperSpec
    itself checks).
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sgjax.geometry.gripper import PHYSICAL_VALUES, GripperSpec
from sgjax.utils.files import atomic_write_text

# The presets: sgjax/grippers/<name>.toml, data of the sgjax package (pyproject.toml's package-data).
PRESET_DIR = Path(__file__).resolve().parent.parent / "grippers"
EXTENSIONS = (".toml", ".json")

# Fields of a gripper file, in file order. Required: what a gripper's datasheet (or a ruler) gives.
# Optional: the pad friction (no datasheet gives it) and the paper's algorithm parameters, with
# GripperSpec's defaults.
REQUIRED = ("max_opening", "finger_length", "finger_width", "finger_thickness", "palm_size", "closing_force")
_DEFAULTS = GripperSpec()
OPTIONAL = {
    "finger_friction": PHYSICAL_VALUES["finger_friction"],
    "deepen": _DEFAULTS.deepen,
    "refine_angles_deg": _DEFAULTS.refine_angles_deg,
    "contact_threshold": _DEFAULTS.contact_threshold,
}
FIELDS = REQUIRED + tuple(OPTIONAL)
# Every value of a GripperSpec, no more: its dataclass fields and its physical values.
assert set(FIELDS) == {f.name for f in dataclasses.fields(GripperSpec)} | set(PHYSICAL_VALUES)

_SIZES = ("max_opening", "finger_length", "finger_width", "finger_thickness")
MAX_SIZE = 1.0  # metres: no gripper size reaches it; a value that does was written in millimetres


class GripperFileError(ValueError):
    """A gripper file or preset that cannot be used; the message is one line naming the source and,
    where one is at fault, the field (also in `.field`, None for a problem with the file itself)."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(" ".join(str(message).split()))  # one line, whatever a parser's message held
        self.field = field


# ---------------------------------------------------------------------------------------------
# Presets.


def preset_names() -> tuple[str, ...]:
    """The shipped presets, "default" first, the others alphabetically."""
    names = sorted(p.stem for p in PRESET_DIR.glob("*.toml"))
    return tuple(sorted(names, key=lambda n: (n != "default", n)))


def preset_path(name: str) -> Path:
    """The file of preset `name`; GripperFileError listing the presets for an unknown name."""
    path = PRESET_DIR / f"{name}.toml"
    if not name or "/" in name or os.sep in name or not path.is_file():
        raise GripperFileError(
            f"unknown gripper preset {name!r}: the presets are {', '.join(preset_names())} "
            f"(or give the path of a {' or '.join(EXTENSIONS)} gripper file)"
        )
    return path


def _is_path(name_or_path: str | os.PathLike) -> bool:
    """A path (a PathLike, or text with a folder separator or an extension), not a preset name."""
    if not isinstance(name_or_path, str):
        return True
    text = name_or_path
    return "/" in text or os.sep in text or bool(Path(text).suffix) or text.startswith(".")


# ---------------------------------------------------------------------------------------------
# Reading.


def load_gripper(name_or_path: str | os.PathLike | GripperSpec) -> GripperSpec:
    """The GripperSpec of a preset name (`preset_names()`) or of a .toml / .json gripper file (a
    GripperSpec is returned as it is). Text with a folder separator or an extension is a path, other
    text a preset name.

    Raises GripperFileError (a ValueError) with a one-line message naming the file and field."""
    if isinstance(name_or_path, GripperSpec):
        return name_or_path
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise GripperFileError(f"a gripper is a preset name or a file path, got {type(name_or_path).__name__}")
    if _is_path(name_or_path):
        path = Path(name_or_path)
        return gripper_from_dict(read_gripper_file(path), f"gripper file {str(path)!r}")
    path = preset_path(name_or_path)
    return gripper_from_dict(read_gripper_file(path), f"gripper preset {name_or_path!r}")


def read_gripper_file(path: str | os.PathLike) -> dict[str, Any]:
    """The raw table of fields of a .toml / .json file (not yet checked: see `gripper_from_dict`)."""
    path = Path(path)
    source = f"gripper file {str(path)!r}"
    if path.suffix.lower() not in EXTENSIONS:
        raise GripperFileError(
            f"{source}: unknown extension {path.suffix or '(none)'!r}: a gripper file is {' or '.join(EXTENSIONS)}"
        )
    if not path.exists():
        raise GripperFileError(f"{source}: no such file")
    if not path.is_file():
        raise GripperFileError(f"{source}: not a file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise GripperFileError(f"{source}: not UTF-8 text") from None
    except OSError as exc:
        raise GripperFileError(f"{source}: cannot be read: {exc.strerror or exc}") from None
    try:
        if path.suffix.lower() == ".toml":
            data = tomllib.loads(text)
        else:
            data = json.loads(text, object_pairs_hook=_no_duplicates)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise GripperFileError(f"{source}: not valid {path.suffix.lower()[1:].upper()}: {exc}") from None
    except _Duplicate as exc:
        raise GripperFileError(f"{source}: {exc.args[0]}: given twice", field=exc.args[0]) from None
    if not isinstance(data, dict):
        raise GripperFileError(f"{source}: the top level must be a table of fields, got {type(data).__name__}")
    return data


class _Duplicate(Exception):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Duplicate(key)
        out[key] = value
    return out


def gripper_from_dict(data: Mapping[str, Any], source: str = "gripper") -> GripperSpec:
    """The GripperSpec of a table of fields (as a gripper file holds them; `gripper_to_dict` is the
    inverse), after every check of the module docstring. `source` starts each error message."""
    if not isinstance(data, Mapping):
        raise GripperFileError(f"{source}: expected a table of fields, got {type(data).__name__}")
    unknown = [k for k in data if k not in FIELDS]
    if unknown:
        key = unknown[0]
        near = difflib.get_close_matches(str(key), FIELDS, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise GripperFileError(
            f"{source}: unknown field {key!r}{hint}; the fields are {', '.join(FIELDS)}", field=str(key)
        )
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise GripperFileError(
            f"{source}: missing required field{'s' if len(missing) > 1 else ''} {', '.join(missing)}", field=missing[0]
        )
    values = {**OPTIONAL, **data}
    fields = {name: _check_value(name, values[name], source) for name in FIELDS}
    check_fields(fields, source)
    try:
        return GripperSpec(**fields)
    except (TypeError, ValueError) as exc:  # GripperSpec's own checks (all covered above)
        raise GripperFileError(f"{source}: {exc}") from None


def _number(name: str, value: Any, source: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        shown = repr(value) if not isinstance(value, (dict, list)) else f"a {'table' if isinstance(value, dict) else 'list'}"
        raise GripperFileError(f"{source}: {name}: must be a number, got {shown}", field=name.split("[")[0])
    if not math.isfinite(value):
        raise GripperFileError(f"{source}: {name}: must be finite, got {value}", field=name.split("[")[0])
    return float(value)


def _size(name: str, value: Any, source: str) -> float:
    value = _number(name, value, source)
    field = name.split("[")[0]
    if not value > 0:
        raise GripperFileError(f"{source}: {name}: must be positive (metres), got {value}", field=field)
    if value >= MAX_SIZE:
        raise GripperFileError(
            f"{source}: {name}: {value} m is not a gripper size: sizes are in metres (millimetres written?)", field=field
        )
    return value


def _check_value(name: str, value: Any, source: str) -> Any:
    """One field's value, converted (floats, tuples) and checked on its own."""
    if name in _SIZES:
        return _size(name, value, source)
    if name == "palm_size":
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise GripperFileError(
                f"{source}: palm_size: must be a list of 3 sizes [x, y, z] in metres, got {value!r}", field=name
            )
        return tuple(_size(f"palm_size[{i}]", v, source) for i, v in enumerate(value))
    if name == "refine_angles_deg":
        if not isinstance(value, (list, tuple)) or not value:
            raise GripperFileError(
                f"{source}: refine_angles_deg: must be a non-empty list of angles in degrees, got {value!r}", field=name
            )
        angles = tuple(_number(f"refine_angles_deg[{i}]", v, source) for i, v in enumerate(value))
        for i, angle in enumerate(angles):
            if abs(angle) > 180.0:
                raise GripperFileError(
                    f"{source}: refine_angles_deg[{i}]: must be within [-180, 180] degrees, got {angle}", field=name
                )
        return angles
    value = _number(name, value, source)
    if name in ("closing_force", "finger_friction") and not value > 0:
        unit = " (N)" if name == "closing_force" else ""
        raise GripperFileError(f"{source}: {name}: must be positive{unit}, got {value}", field=name)
    if name in ("deepen", "contact_threshold") and value < 0:
        raise GripperFileError(f"{source}: {name}: must be >= 0 (metres), got {value}", field=name)
    return value


def check_fields(fields: Mapping[str, Any], source: str = "gripper") -> None:
    """The rules between fields (each field already checked on its own):

    * max_opening >= finger_thickness. The stroke and the fingers' thickness are not tied by the
      mechanism (short-stroke grippers with jaws thicker than half their stroke exist, so "twice the
      thickness" would refuse real grippers); a stroke below one finger's thickness is not a gripper
      for this project's objects (3-25 cm) but the sign of two fields swapped or mistyped.
    * max_opening > 2 * contact_threshold: the width rule opens the fingers contact_threshold beyond
      each side of what they grasp, so with less no template grasp fits in the stroke.
    * palm_size[0] >= max_opening + 2 * finger_thickness: the palm carries both fingers at full opening
      (GripperSpec's own rule).
    """
    opening, thickness = fields["max_opening"], fields["finger_thickness"]
    if opening < thickness:
        raise GripperFileError(
            f"{source}: max_opening: the stroke {opening} m is smaller than finger_thickness {thickness} m "
            "(swapped fields?)", field="max_opening"
        )
    delta = fields["contact_threshold"]
    if not opening > 2 * delta:
        raise GripperFileError(
            f"{source}: contact_threshold: {delta} m leaves no room in the stroke: the width rule needs "
            f"max_opening > 2 * contact_threshold, got max_opening {opening} m", field="contact_threshold"
        )
    span = opening + 2 * thickness
    palm_x = fields["palm_size"][0]
    if palm_x < span - 1e-9:
        raise GripperFileError(
            f"{source}: palm_size[0]: the palm ({palm_x} m) is narrower than the open fingers' span "
            f"max_opening + 2 * finger_thickness = {span:.6g} m", field="palm_size"
        )


# ---------------------------------------------------------------------------------------------
# Writing.


def gripper_to_dict(spec: GripperSpec) -> dict[str, Any]:
    """Every field of a gripper file for `spec` (floats and lists, in file order): JSON- and TOML-ready,
    and `gripper_from_dict(gripper_to_dict(spec)) == spec`. Unlike `dataclasses.asdict` it carries the
    physical values (closing_force, finger_friction)."""
    out: dict[str, Any] = {}
    for name in FIELDS:
        value = getattr(spec, name)
        out[name] = [float(v) for v in value] if isinstance(value, tuple) else float(value)
    return out


def gripper_to_toml(spec: GripperSpec) -> str:
    """`spec` as the text of a TOML gripper file."""
    lines = ["# A gripper (sgjax.geometry.gripper_files): metres, newtons, degrees."]
    for name, value in gripper_to_dict(spec).items():
        text = f"[{', '.join(repr(v) for v in value)}]" if isinstance(value, list) else repr(value)
        lines.append(f"{name} = {text}")
    return "\n".join(lines) + "\n"


def save_gripper(spec: GripperSpec, path: str | os.PathLike) -> Path:
    """Write `spec` as a .toml or .json gripper file (atomically), after the checks `load_gripper`
    makes, so that what is written loads back equal; returns the path."""
    path = Path(path)
    source = f"gripper file {str(path)!r}"
    if path.suffix.lower() not in EXTENSIONS:
        raise GripperFileError(
            f"{source}: unknown extension {path.suffix or '(none)'!r}: a gripper file is {' or '.join(EXTENSIONS)}"
        )
    gripper_from_dict(gripper_to_dict(spec), source)
    if path.suffix.lower() == ".toml":
        text = gripper_to_toml(spec)
    else:
        text = json.dumps(gripper_to_dict(spec), indent=2) + "\n"
    atomic_write_text(path, text)
    return path
