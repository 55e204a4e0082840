"""Presets are the files of scene/presets (found by listing the folder, named nowhere else),
and every default of the scene model is declared once, in its dataclass."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cdma_lidar.scene import PRESETS, load_scene, loader, presetfiles
from cdma_lidar.scene.model import (
    Calibration,
    Ghost,
    InstrumentSpec,
    ObjectSpec,
    OtherUser,
    Scene,
    field_default,
)
from cdma_lidar.scene.scenefile import (
    DEFAULT_COLUMNS,
    DEFAULT_LASER_POWER_W,
    DEFAULT_WAVELENGTHS,
    parse_scene,
)

SCENE_DIR = Path(__file__).resolve().parents[2] / "scene"
PRESET_FILES = sorted(SCENE_DIR.glob("presets/*.toml"))


def test_the_preset_listing_is_the_folder():
    assert PRESET_FILES, "no presets found"
    assert PRESETS == tuple(p.stem for p in PRESET_FILES)
    assert loader.preset_names() == PRESETS


@pytest.mark.parametrize("path", PRESET_FILES, ids=[p.stem for p in PRESET_FILES])
def test_every_preset_file_loads_by_name_and_by_path(path):
    by_name = load_scene(path.stem)
    assert by_name.name == path.stem and by_name.description
    by_path = load_scene(path)
    assert by_path.name == path.stem
    np.testing.assert_array_equal(by_path.instrument.rotations_deg,
                                  by_name.instrument.rotations_deg)


def test_a_new_file_in_the_folder_is_a_preset(tmp_path, monkeypatch):
    (tmp_path / "b-scene.toml").write_text('description = "b"\n')
    (tmp_path / "a-scene.toml").write_text('description = "a"\n')
    (tmp_path / "notes.txt").write_text("not a scene\n")
    monkeypatch.setattr(presetfiles, "_presets_folder", lambda: tmp_path)
    assert presetfiles.preset_names() == ("a-scene", "b-scene")


def test_no_module_lists_the_presets_again():
    """No tuple, list or set of preset names in the scene code: a second list to keep."""
    names = set(PRESETS)
    found = []
    for path in sorted(SCENE_DIR.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text("utf-8"))):
            if isinstance(node, ast.Tuple | ast.List | ast.Set):
                listed = [e.value for e in node.elts
                          if isinstance(e, ast.Constant) and e.value in names]
                if len(listed) > 1:
                    found.append(f"{path.name}:{node.lineno} {listed}")
    assert not found


# ---------------------------------------------------------------------------------------
# defaults, declared once

def _with_default(cls: type) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)
            if f.default is not dataclasses.MISSING
            or f.default_factory is not dataclasses.MISSING]


def _assert_defaults(obj: object, skip: set[str] = frozenset()) -> None:
    for name in _with_default(type(obj)):
        if name in skip:
            continue
        got, want = getattr(obj, name), field_default(type(obj), name)
        if isinstance(want, np.ndarray):
            np.testing.assert_array_equal(got, want, err_msg=name)
        else:
            assert got == want and type(got) is type(want), (type(obj).__name__, name, got)


def test_an_empty_scene_file_has_the_dataclass_defaults():
    scene = parse_scene({"instrument": {
        "ghosts": [{"distance_m": 40.0, "amplitude_v": 1e-3}],
        "other_users": [{"uid": 1, "distance_m": 15.0, "amplitude_v": 1e-3}]}})
    _assert_defaults(scene, skip={"calibration"})
    _assert_defaults(scene.calibration)
    spec = scene.instrument
    _assert_defaults(spec, skip={"ghosts", "other_users"})
    _assert_defaults(spec.ghosts[0])
    _assert_defaults(spec.other_users[0])
    # the nominal grating defaults to the true one
    assert spec.nominal_grooves_per_mm == spec.grooves_per_mm
    assert spec.nominal_incidence_deg == spec.incidence_deg
    # the shorthands that expand to the arrays
    d = DEFAULT_WAVELENGTHS
    np.testing.assert_array_equal(
        spec.wavelengths_m, d["start_m"] + d["spacing_m"] * np.arange(d["count"]))
    np.testing.assert_array_equal(spec.laser_power_w, np.full(d["count"], DEFAULT_LASER_POWER_W))
    assert spec.columns == DEFAULT_COLUMNS


def test_objects_have_the_dataclass_defaults():
    scene = parse_scene({"objects": [
        {"kind": "plane", "position_m": [5.0, 0.0, 0.0]},
        {"kind": "text", "position_m": [5.0, 0.0, 0.0], "text": "A", "height_m": 0.1}]})
    plane, text = scene.objects
    _assert_defaults(plane)
    _assert_defaults(text, skip={"text", "height_m"})
    assert (plane.name, text.name) == ("plane0", "text1")


#: Reader methods and the position of their default among the positional arguments.
_DEFAULT_ARG = {"num": 3, "int": 3, "vec": 4, "str": 2, "ints": 3}


def test_the_parser_writes_no_default_value_of_its_own():
    """Every default the scene-file reader passes is a name or an expression (a dataclass
    field's default, a DEFAULT_* shorthand, a value read earlier), never a literal."""
    tree = ast.parse((SCENE_DIR / "scenefile.py").read_text("utf-8"))
    literals = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in _DEFAULT_ARG):
            continue
        args = [kw.value for kw in node.keywords if kw.arg == "default"]
        pos = _DEFAULT_ARG[node.func.attr]
        args += node.args[pos:pos + 1]
        literals += [f"line {a.lineno}: {ast.unparse(node)}" for a in args
                     if isinstance(a, ast.Constant | ast.List | ast.Tuple)]
    assert not literals


@pytest.mark.parametrize("cls", [Calibration, Ghost, InstrumentSpec, ObjectSpec, OtherUser,
                                 Scene])
def test_field_default_reads_the_declaration(cls):
    for name in _with_default(cls):
        field_default(cls, name)  # no KeyError
    required = [f.name for f in dataclasses.fields(cls) if f.name not in _with_default(cls)]
    for name in required:
        with pytest.raises(KeyError):
            field_default(cls, name)
