"""The ``[design]`` table: what ``fwdfit design`` may choose between, and for what.

``target``: the parameters (``[fit] vary`` names) whose errors the plan minimises
(default: every shared free parameter); ``distances_mm``: candidate sample-detector
distances (default: the profiles' distances); ``spectra``: candidate spectra, names of
``[spectra]`` (default: those the profiles use); ``exposure``: the total exposure, in
units of one profile's exposure as measured (default: the number of profiles);
``noise``: the relative error of one open-beam pixel in one unit of exposure (default:
from the profiles' errors, ``T_err / sqrt(T)``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from .._errors import FwdfitError

DESIGN_KEYS = ("target", "distances_mm", "spectra", "exposure", "noise")


@dataclasses.dataclass(frozen=True)
class DesignSpec:
    target: tuple[str, ...] = ()
    distances_mm: tuple[float, ...] = ()
    spectra: tuple[str, ...] = ()
    exposure: float = math.nan
    noise: float = math.nan


def read_design(path: Path, table: Any, spectra: dict) -> DesignSpec:
    """The ``[design]`` table of the scene file ``path`` (``spectra``: the scene's, by name)."""
    def fail(key: str, message: str):
        raise FwdfitError(f"{path}: design.{key}: {message}")

    if not isinstance(table, dict):
        raise FwdfitError(f"{path}: design: must be a table")
    unknown = sorted(set(table) - set(DESIGN_KEYS))
    if unknown:
        fail(unknown[0], f"unknown key (design keys: {', '.join(DESIGN_KEYS)})")
    target = table.get("target", [])
    if not isinstance(target, list) or not all(isinstance(v, str) and v for v in target):
        fail("target", "must be a list of parameter names")
    distances = table.get("distances_mm", [])
    if not isinstance(distances, list) or not all(_number(d) and d > 0 for d in distances):
        fail("distances_mm", f"must be a list of positive distances in mm, got {distances!r}")
    names = table.get("spectra", [])
    if not isinstance(names, list) or not all(isinstance(v, str) for v in names):
        fail("spectra", "must be a list of spectrum names")
    missing = [name for name in names if name not in spectra]
    if missing:
        fail("spectra", f"no spectrum {missing[0]!r} in [spectra]")
    values = {}
    for key in ("exposure", "noise"):
        if key in table:
            if not (_number(table[key]) and table[key] > 0):
                fail(key, f"must be a positive number, got {table[key]!r}")
            values[key] = float(table[key])
    return DesignSpec(tuple(target), tuple(float(d) for d in distances), tuple(names), **values)


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
