"""A scene skeleton (TOML text) whose profiles are the wavelength bins of a TOF stack.

Each bin ``binNNN`` gets a spectrum ``[spectra.binNNN]`` with ``lambda_min_A`` and
``lambda_max_A`` and a profile reading ``binNNN.csv``; what the stack cannot tell
(the sample, the aperture, the distance unless given) is left as commented lines to
fill in.
"""

from __future__ import annotations

import numpy as np


def bin_names(n_bins: int) -> list[str]:
    """``bin000``, ``bin001``, ...: at least three digits, more for 1000 bins or over."""
    width = max(3, len(str(n_bins - 1)))
    return [f"bin{index:0{width}d}" for index in range(n_bins)]


def _float(value: float) -> str:
    """A TOML float (always with a point or exponent), 9 significant digits."""
    return repr(float(f"{value:.9g}"))


def skeleton_toml(wavelength_edges_A: np.ndarray, pixel_um: float, *,
                  distance_mm: float | None, header: str) -> str:
    """The scene text: commented sample, instrument with the pixel, one spectrum and one
    profile per bin (``wavelength_edges_A``: ``(n_bins + 1,)``, Å)."""
    lines = [f"# {line}" for line in header.splitlines()]
    lines += ["# Fill in the sample and the aperture; see docs/SCENE.md.", "",
              "[sample]", "# depth_mm = 2.0", "# tilt_deg = 0.0", "# centre_um = 0.0", "",
              "# [[sample.layers]]", '# name = "Al"', "# thickness_um = 1000.0",
              '# material = "Al"', "# density_g_cm3 = 2.70", "",
              "[instrument]", f"pixel_um = {_float(pixel_um)}", '# aperture = "circular"',
              "# aperture_mm = 20.0", "# aperture_distance_m = 10.0", ""]
    distance = ("# distance_mm = 10.0  # sample centre to detector" if distance_mm is None
                else f"distance_mm = {_float(distance_mm)}")
    names = bin_names(len(wavelength_edges_A) - 1)
    for name, low, high in zip(names, wavelength_edges_A[:-1], wavelength_edges_A[1:]):
        lines += [f"[spectra.{name}]", f"lambda_min_A = {_float(low)}",
                  f"lambda_max_A = {_float(high)}", ""]
    for name in names:
        lines += ["[[profiles]]", f'name = "{name}"', f'spectrum = "{name}"',
                  f'file = "{name}.csv"', distance, ""]
    return "\n".join(lines)
