"""Where scenes come from: the built-in presets (``scene/presets/*.toml``) and TOML files.

``load_scene("flat-wall?distance=7.5")`` loads a preset by name with options,
``load_scene("my.toml")`` a file. The presets are the ``*.toml`` files of the
``cdma_lidar.scene.presets`` folder, found by listing it (:data:`PRESETS`, from
:mod:`cdma_lidar.scene.presetfiles`): adding a preset is adding a file.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.scene.model import Scene
from cdma_lidar.scene.presetfiles import preset_file, preset_names
from cdma_lidar.scene.scenefile import apply_options, parse_options, parse_scene, read_document

__all__ = ["PRESETS", "load_scene", "preset_names"]

log = logging.getLogger(__name__)


#: Built-in scenes, loadable by name (listed once, at import).
PRESETS = preset_names()


def load_scene(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scene:
    """Load a preset by name (``flat-wall``, optionally ``flat-wall?distance=7.5``) or a TOML file.

    Query options after ``?`` (and ``overrides``, which win) replace fields before
    validation: a preset's own shortcuts (``distance`` for ``flat-wall``) or any dotted field
    such as ``instrument.snr_db=-10`` or ``objects[0].reflectivity=0.2``.
    """
    text = str(name_or_path)
    base, _, query = text.partition("?")
    opts = parse_options(query)
    opts.update(overrides or {})
    path = Path(base)
    if base in PRESETS:
        raw = preset_file(base).read_text("utf-8")
    elif path.suffix == ".toml" or path.exists():
        try:
            raw = path.read_text("utf-8")
        except OSError as exc:
            raise ConfigError(f"scene file {base!r} cannot be read ({exc.strerror})",
                              field="scene") from exc
        except UnicodeDecodeError as exc:
            raise ConfigError(f"scene file {base!r} is not UTF-8 text (byte {exc.start}); save "
                              "it as UTF-8 TOML", field="scene") from None
    else:
        raise out_of_range("scene", "a preset (" + ", ".join(PRESETS) + ") or a .toml file", base)
    doc = read_document(raw, base)
    apply_options(doc, opts)
    return parse_scene(doc, name=base if base in PRESETS else path.stem)
