"""The sample's shape behind one seam: what the fitter, the quality gate and the outputs ask of it.

A geometry turns a scene into its forward model, refuses measured profiles it cannot
read starts off, reads starting values off measured profiles, moves a candidate to a
trial tilt for the global scan, and says where its interfaces land on each profile (the
quality gate's edge regions). The layered block
(flat layers side by side along x, tilted about the vertical axis: ``_plan``/``_model``,
``_starts``, the exact tracer ``_reference``) is the one geometry today. A second shape
(concentric cylinder shells, say) implements the same five methods in its own modules and
is returned by ``geometry_of`` for its scenes; the fitter, the scene reader's generic
parts, the objective and the outputs stay as they are.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Protocol

import numpy as np

from ..model.block._model import ForwardModel
from ._parameters import FreeParameter
from ..model.block._plan import build_model
from ._quality import edge_half_width_um
from ..scene._scene import Profile, Scene
from ._starts import Estimate, estimate, narrow_profiles


class Geometry(Protocol):
    """What a sample shape provides to the fit (see the module docstring)."""

    def build_model(self, scene: Scene, accuracy: float | None, free: Collection[str],
                    tilt_range_deg: tuple[float, float] | None) -> ForwardModel:
        """The forward model of the scene, free parameters ``free`` traced."""

    def estimate(self, scene: Scene, free: tuple[FreeParameter, ...], T: list[np.ndarray],
                 model: ForwardModel) -> Estimate:
        """Starting values read off the measured profiles T (one array per profile)."""

    def check_data(self, scene: Scene, T: list[np.ndarray]) -> None:
        """Refuse, with FwdfitError, measured profiles T whose starts ``estimate`` cannot read
        (called before the model compiles)."""

    def at_tilts(self, free: tuple[FreeParameter, ...], estimate: Estimate, row: np.ndarray,
                 tilts_deg: np.ndarray) -> np.ndarray:
        """Rows (m, n_free): ``row`` (n_free,) at each trial tilt, with what the data pin
        at that tilt (e.g. projected widths) kept."""

    def interfaces(self, scene: Scene, profile: Profile) -> tuple[list[tuple[float, float, str]], float]:
        """Where each interface lands on the profile, (x_from_um, x_to_um, label) each,
        and the half width (µm) of the region its refraction spreads over."""


class LayeredBlock:
    """Flat layers side by side along x, depth along the beam, tilted about the vertical axis."""

    def build_model(self, scene, accuracy, free, tilt_range_deg):
        return build_model(scene, accuracy, free=free, tilt_range_deg=tilt_range_deg)

    def estimate(self, scene, free, T, model):
        return estimate(scene, free, T, model)

    def check_data(self, scene, T):
        """Profiles narrower than the stack need every layer's thickness (``narrow_profiles``)."""
        narrow_profiles(scene, T)

    def at_tilts(self, free, estimate, row, tilts_deg):
        """The data pin each layer's projected width t / cos(tilt): thicknesses follow the tilt."""
        names = [p.name for p in free]
        tilt = names.index("sample.tilt_deg")
        thickness = [names.index(n) for n in estimate.thickness_names]
        projected = row[thickness] / math.cos(math.radians(row[tilt]))
        rows = np.repeat(row[None], len(tilts_deg), axis=0)
        rows[:, tilt] = tilts_deg
        rows[:, thickness] = projected[None] * np.cos(np.radians(tilts_deg))[:, None]
        return rows

    def interfaces(self, scene, profile):
        """Each face from its upstream to its downstream end, projected along the beam, and the
        edge half width from the penumbra, the detector blur and the depth's sideways spread."""
        sample, instrument = scene.sample, scene.instruments[profile.instrument]
        tilt = math.radians(sample.tilt_deg)
        cumulative = np.concatenate([[0.0], np.cumsum([l.thickness_um for l in sample.layers])])
        across = (cumulative - 0.5 * cumulative[-1]) / math.cos(tilt)
        media = ["vacuum"] + [l.name for l in sample.layers] + ["vacuum"]
        centre = sample.centre_um + profile.shift_um + sample.drift_um_per_mm * profile.distance_mm
        slope_um = profile.distance_mm * 1e3 * math.tan(tilt)
        faces = [(centre + a, centre + a + slope_um, f"{media[k]} | {media[k + 1]}") for k, a in enumerate(across)]
        penumbra = profile.distance_mm * instrument.aperture_mm / instrument.aperture_distance_m
        spread = 0.5 * sample.depth_mm * 1e3 * abs(math.tan(tilt))
        return faces, edge_half_width_um(profile.distance_mm, penumbra, instrument.psf_fwhm_um, spread)


def geometry_of(scene: Scene) -> Geometry:
    """The geometry of a scene (the layered block: the one shape a scene describes today)."""
    return LayeredBlock()
