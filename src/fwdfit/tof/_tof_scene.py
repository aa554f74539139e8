"""A scene skeleton whose profiles are the wavelength bins of a TOF stack.

Each bin ``binNNN`` gets a spectrum ``[spectra.binNNN]`` with ``lambda_min_A`` and
``lambda_max_A`` and a profile reading ``binNNN.csv``; what the stack cannot tell
(the sample, the aperture, the distance unless given) is written as commented
placeholders to fill in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scene._materials import constants_from_formula
from ..scene._scene import Instrument, Layer, Profile, Sample, Scene
from ..scene._scene_toml import dump_scene
from ..scene._spectrum import BandSpectrum

_PLACEHOLDER_DISTANCE_MM = 10.0


def bin_names(n_bins: int) -> list[str]:
    """``bin000``, ``bin001``, ...: at least three digits, more for 1000 bins or over."""
    width = max(3, len(str(n_bins - 1)))
    return [f"bin{index:0{width}d}" for index in range(n_bins)]


def skeleton_toml(wavelength_edges_A: np.ndarray, x_um: np.ndarray, pixel_um: float, folder: Path, *,
                  distance_mm: float | None, header: str) -> str:
    """The scene text for ``folder``: a placeholder sample and aperture, the instrument's
    pixel, one spectrum and one profile (``binNNN.csv`` on pixels ``x_um``) per bin
    (``wavelength_edges_A``: ``(n_bins + 1,)``, Å)."""
    names = bin_names(len(wavelength_edges_A) - 1)
    scene = Scene(
        sample=Sample(depth_mm=2.0, tilt_deg=0.0, centre_um=0.0,
                      layers=(Layer.from_material("Al", 1000.0, constants_from_formula("Al", 2.70)),)),
        instruments={"": Instrument("circular", 20.0, 10.0, pixel_um)},
        spectra={name: BandSpectrum(float(low), float(high), None)
                 for name, low, high in zip(names, wavelength_edges_A[:-1], wavelength_edges_A[1:])},
        profiles=tuple(Profile(name, distance_mm or _PLACEHOLDER_DISTANCE_MM, name, "", x_um,
                               file=Path(folder) / f"{name}.csv") for name in names))
    placeholders = {"sample", "instrument.aperture", "instrument.aperture_mm", "instrument.aperture_distance_m"}
    if distance_mm is None:
        placeholders.add("profiles.distance_mm")
    return dump_scene(scene, folder, placeholders=placeholders,
                      comment=f"{header}\nFill in the sample, the aperture (and the distance, "
                              "sample centre to detector, if commented); see docs/SCENE.md.")
