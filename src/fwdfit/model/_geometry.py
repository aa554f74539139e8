"""The seam between the fit and the sample's shape: what a geometry provides, and the
starting values it reads off the data.

A geometry (one folder of ``model/`` each: ``block/``, ...) turns a scene into its
parameters and forward model, fills in what a fit leaves out before the model is
planned, refuses measured profiles it cannot read starts off, reads starting values off
them, moves a candidate to trial tilts for the global scan, and says where its faces
land on each profile (the quality gate's edge regions; an image's faces, row by row,
``images._edges``), sizes an image's face templates and says which free parameters the
faces in an image's view leave undetermined. The fitter, the search, the
objective and the outputs call only this; ``inference.geometry_of`` picks the geometry
of a scene. It lives here, below ``inference/``, so that a geometry's folder implements
it without importing what sits above it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection
from typing import Any, Protocol

import numpy as np

from ..scene._scene import Profile, Scene

_MIN_EDGE_HALF_WIDTH_UM = 15.0
_FRINGE_ANGLE_RAD = 3e-3  # reach of the refraction fringes: this angle times the distance


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Starting values from the data, free name -> value (a block's thicknesses at tilt 0:
    the projected widths; a trial tilt multiplies them by cos(tilt))."""

    values: dict[str, float]
    thickness_names: tuple[str, ...]  # the free thicknesses among them
    held_names: tuple[str, ...] = ()  # free thicknesses read off interior steps (not the thickest layer's)
    pinned_names: tuple[str, ...] = ()  # free positions and plateau levels, which the data pin directly


def edge_half_width_um(distance_mm: float, penumbra_um: float, psf_fwhm_um: float, tilt_spread_um: float) -> float:
    """Half-width (µm) of the region around an interface where its refraction fringes lie."""
    return max(_MIN_EDGE_HALF_WIDTH_UM,
               0.5 * penumbra_um + _FRINGE_ANGLE_RAD * distance_mm * 1e3 + psf_fwhm_um + tilt_spread_um)


class Geometry(Protocol):
    """What a sample shape provides to the fit (see the module docstring). ``free`` is the
    fit's tuple of ``inference.FreeParameter``; a model is the geometry's own forward model
    (``groups``, ``flat``, ``grouped``, ``stacked``, ``scene_order``)."""

    def initial_params(self, scene: Scene, dtype=None) -> Any:
        """The scene's values as the model's parameters (every value given)."""

    def plan_scene(self, scene: Scene, free: tuple) -> Scene:
        """The scene the model's static plan is built from: the start values a fit leaves
        out (NaN) filled with values the plan can be sized for."""

    def build_model(self, scene: Scene, accuracy: float | None, free: Collection[str],
                    tilt_range_deg: tuple[float, float] | None) -> Any:
        """The forward model of the scene, free parameters ``free`` traced."""

    def estimate(self, scene: Scene, free: tuple, T: list[np.ndarray], model) -> Estimate:
        """Starting values read off the measured profiles T (one array per profile)."""

    def check_data(self, scene: Scene, T: list[np.ndarray]) -> None:
        """Refuse, with FwdfitError, measured profiles T whose starts ``estimate`` cannot read
        (called before the model compiles)."""

    def at_tilts(self, free: tuple, estimate: Estimate, row: np.ndarray, tilts_deg: np.ndarray) -> np.ndarray:
        """Rows (m, n_free): ``row`` (n_free,) at each trial tilt, with what the data pin
        at that tilt (e.g. projected widths) kept."""

    def plateau(self, scene: Scene, profile: Profile) -> np.ndarray:
        """Pixels (bool, (n,)) of the profile where T_att is read for a spectrum (time-of-flight
        bins): inside the sample, farther from every face than refraction moves intensity."""

    def interfaces(self, scene: Scene, profile: Profile) -> tuple[list[tuple[float, float, str]], float]:
        """Where each interface lands on the profile, (x_from_um, x_to_um, label) each,
        left to right, and the half width (µm) of the region its refraction spreads over."""

    def sized_for(self, scene: Scene, width_um: float) -> Scene:
        """The scene with every size a fit leaves out (NaN) filled so that its faces land
        inside a window ``width_um`` wide (an image's face templates, ``images._edges``)."""

    def undetermined(self, scene: Scene, names: Collection[str], in_view: np.ndarray) -> list[str]:
        """The free parameters among ``names`` that an image cannot determine when only the
        faces ``in_view`` (bool per face of ``interfaces``, left to right) show and the
        centre is fitted per row."""
