"""The studies ``cdma-lidar study list`` shows and ``study run NAME`` finds.

Built-in studies are listed in :data:`BUILTIN` (one import and one entry per study
module; the paper's studies come from :data:`cdma_lidar.study.paper.PARTS`, which imports
them: the catalogue imports the paper, never the other way round).
:func:`register_study` adds more at run time (plug-ins, tests). Names are unique:
registering a second study under a taken name is an error unless ``replace=True``.
"""

from __future__ import annotations

from cdma_lidar.errors import ConfigError
from cdma_lidar.study import detection, extremes, massive, paper, tradeoff
from cdma_lidar.study.engine import Study

__all__ = ["BUILTIN", "get_study", "register_study", "studies"]

#: The studies shipped with the toolkit, in the order ``study list`` shows them.
BUILTIN: tuple[Study, ...] = (tradeoff.STUDY, extremes.STUDY, detection.STUDY, massive.STUDY,
                              # the paper's results (docs/paper.md); `paper` runs them all
                              *paper.PARTS.values(), paper.STUDY)

_REGISTRY: dict[str, Study] = {}


def register_study(study: Study, *, replace: bool = False) -> Study:
    """Make ``study`` runnable by name; returns it (usable as ``STUDY = register_study(...)``)."""
    if not study.name or not all(c.isalnum() or c in "-_" for c in study.name):
        raise ConfigError(f"study name {study.name!r}: letters, digits, '-' and '_' only",
                          "name")
    if study.name in _REGISTRY and _REGISTRY[study.name] is not study and not replace:
        raise ConfigError(f"study {study.name!r} is already registered", "name")
    _REGISTRY[study.name] = study
    return study


def studies() -> list[Study]:
    """Every registered study, built-ins first."""
    return list(_REGISTRY.values())


def get_study(name: str) -> Study:
    """The study called ``name``; ConfigError listing the known names otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown study {name!r}; known: {', '.join(_REGISTRY)}",
                          "study") from None


for _study in BUILTIN:
    register_study(_study)
