"""The fitted quantities, each declared once: its scene part and key, unit, default value
and bounds, typical step and where the model takes it.

The scene reader (allowed keys, values a fit may leave out), the free parameters
(``[fit] vary`` names, bounds, steps), the model's initial parameters, the write-back
of fitted values, the scene writer (defaults left out) and result.json (units) read
this table. A new quantity is one row here plus its field on ``Sample``, ``Layer`` or
``Profile`` (and on ``ModelParams`` when ``model`` is ``"params"``).
"""

from __future__ import annotations

import dataclasses
import math

_INF = math.inf
GEOMETRIES = ("block", "cylinder")  # [sample] geometry: the layered block (the default), concentric shells
_BLOCK = ("block",)
# A free tilt is bounded by +-DEFAULT_TILT_BOUND_DEG, widened to twice a larger start
# (at most MAX_TILT_DEG): kernel windows grow with the tilts the model must serve,
# and samples are aligned to better than a degree.
DEFAULT_TILT_BOUND_DEG = 1.0
# RMS slope of an interface's local normal (mrad): the default upper bound of a free
# roughness (rough faces' kernel windows grow with it).
MAX_ROUGHNESS_MRAD = 5.0
# In-plane rotation of an image's edge (deg): rows are cuts across the edge, so a row
# crosses the layers 1/cos(rotation) wider (1.5e-4 at 1 deg), which the fit does not undo.
DEFAULT_ROTATION_BOUND_DEG = 5.0


@dataclasses.dataclass(frozen=True)
class Quantity:
    """One fitted quantity.

    part: ``"sample"``, ``"layers"`` or ``"profiles"``: the scene part whose field ``key``
    holds it (``Sample``, ``Layer``, ``Profile``) and the first word of its ``vary`` name.
    default: its value when the scene leaves it out (None: the scene must give it, or a
    fit that varies it estimates it from the data when ``from_data``). model:
    ``"params"``, a ``ModelParams`` field of the same name, ``"assembler"``, applied
    by the assembler (profile shifts, normalisation, background), or ``"image"``, a
    quantity of an image's rows that no profile model sees (fit-image alone fits it). positive: the scene
    value must be > 0. material: a constant a layer's material gives (the reader and
    writer treat it with the material); the others, neither ``from_data`` nor
    ``material``, the reader reads as they are. uniform_from: a layer's value at its
    right-hand side (graded layers), NaN when the scene leaves it out: the layer is then
    uniform, and this key's value stands in for it. geometries: the ``[sample] geometry``
    values whose scenes take the key (``GEOMETRIES``); the others refuse it.
    """

    part: str
    key: str
    unit: str
    default: float | None
    bounds: tuple[float, float]
    step: float
    model: str = "params"
    from_data: bool = False
    positive: bool = False
    material: bool = False
    uniform_from: str | None = None
    signed_by_start: bool = False  # default bounds mirrored to (-high, -low) for a negative start value
    geometries: tuple[str, ...] = ("block", "cylinder")  # the sample shapes that take it


QUANTITIES = (
    Quantity("sample", "tilt_deg", "deg", 0.0, (-DEFAULT_TILT_BOUND_DEG, DEFAULT_TILT_BOUND_DEG), 0.01,
             geometries=_BLOCK),
    Quantity("sample", "centre_um", "um", 0.0, (-_INF, _INF), 1.0),
    Quantity("sample", "depth_mm", "mm", None, (0.0, _INF), 0.01, positive=True, geometries=_BLOCK),
    Quantity("sample", "outer_radius_um", "um", None, (0.0, _INF), 1.0, from_data=True, positive=True,
             geometries=("cylinder",)),
    Quantity("sample", "left_roughness_mrad", "mrad", 0.0, (0.0, MAX_ROUGHNESS_MRAD), 0.1, geometries=_BLOCK),
    Quantity("sample", "drift_um_per_mm", "um/mm", 0.0, (-_INF, _INF), 0.01, model="assembler"),
    Quantity("sample", "rotation_deg", "deg", 0.0, (-DEFAULT_ROTATION_BOUND_DEG, DEFAULT_ROTATION_BOUND_DEG), 0.001,
             model="image"),
    Quantity("layers", "thickness_um", "um", None, (0.0, _INF), 1.0, from_data=True),
    Quantity("layers", "sld_e6_per_A2", "1e-6/A^2", None, (0.0, _INF), 0.1, from_data=True, material=True,
             signed_by_start=True),
    Quantity("layers", "mu_per_m", "1/m", None, (0.0, _INF), 1.0, from_data=True, material=True),
    Quantity("layers", "mu_per_m_per_A", "1/(m A)", 0.0, (0.0, _INF), 0.1, material=True),
    Quantity("layers", "density_scale", "", 1.0, (0.0, _INF), 0.01, positive=True),
    Quantity("layers", "roughness_mrad", "mrad", 0.0, (0.0, MAX_ROUGHNESS_MRAD), 0.1, geometries=_BLOCK),
    Quantity("layers", "sld_end_e6_per_A2", "1e-6/A^2", math.nan, (0.0, _INF), 0.1,
             uniform_from="sld_e6_per_A2", signed_by_start=True, geometries=_BLOCK),
    Quantity("layers", "mu_end_per_m", "1/m", math.nan, (0.0, _INF), 1.0, uniform_from="mu_per_m",
             geometries=_BLOCK),
    Quantity("profiles", "distance_mm", "mm", None, (0.0, _INF), 0.1, positive=True),
    Quantity("profiles", "shift_um", "um", 0.0, (-_INF, _INF), 1.0, model="assembler"),
    Quantity("profiles", "norm", "", 1.0, (0.0, _INF), 0.01, model="assembler", positive=True),
    Quantity("profiles", "background", "", 0.0, (-_INF, _INF), 0.001, model="assembler"),
)
BY_KEY = {q.key: q for q in QUANTITIES}  # keys are unique (tests/test_scene_toml.py checks)


def part(name: str, geometry: str | None = None) -> dict[str, Quantity]:
    """The quantities of one scene part, by key (those a ``geometry`` takes, where given)."""
    return {q.key: q for q in QUANTITIES if q.part == name and (geometry is None or geometry in q.geometries)}


def defaults(name: str, geometry: str | None = None) -> dict[str, float]:
    """The defaults of one scene part's quantities that have one, by key."""
    return {key: q.default for key, q in part(name, geometry).items() if q.default is not None}


def unit(vary_name: str) -> str:
    """The unit of a parameter by its ``vary`` name (``layers.Al.thickness_um`` -> ``um``)."""
    return BY_KEY[vary_name.rsplit(".", 1)[-1]].unit


def layer_value(layer, key: str) -> float:
    """A layer's value of a registry key; a graded layer's right-hand value left out (NaN)
    is its left-hand one (``Quantity.uniform_from``)."""
    value = getattr(layer, key)
    source = BY_KEY[key].uniform_from
    return getattr(layer, source) if source and math.isnan(value) else value
