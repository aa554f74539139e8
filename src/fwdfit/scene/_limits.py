"""The validity domain: the range of every scene value and option the model is made for.

Inside it the model is meant to give finite values at the requested accuracy (a NaN
there is a bug; the writers refuse it); outside it a scene is refused at load time with
one line naming the key, the value and the limit.

docs/SCENE.md ("Validity domain") lists the same limits with their reasons. Units are
those of the keys.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from .._errors import FwdfitError

MAX_TILT_DEG = 5.0  # the model is paraxial: it loses accuracy beyond ~3°
MAX_PIXELS = 20_000  # per profile: pixels of a grid or rows of a measured table
MAX_PSF_PIXELS = 100.0  # psf_fwhm_um at most this many pixels
MAX_DIVERGENCE = 0.1  # aperture_mm seen from the sample's upstream face, rad (paraxial)
SEE = "see docs/SCENE.md"

# Closed ranges [low, high] by key name (the last part of a scene key, or an option).
DOMAIN: dict[str, tuple[float, float]] = {
    "depth_mm": (1e-3, 100.0),
    "outer_radius_um": (1.0, 5e4),  # a cylinder's radius: 1 µm to 5 cm
    "tilt_deg": (-MAX_TILT_DEG, MAX_TILT_DEG),
    "centre_um": (-1e5, 1e5),
    "drift_um_per_mm": (-100.0, 100.0),
    "rotation_deg": (-20.0, 20.0),  # an image edge's in-plane rotation; rows stay cuts across it
    "thickness_um": (0.0, 1e5),
    "density_g_cm3": (1e-4, 30.0),
    "density_scale": (0.01, 100.0),
    "sld_e6_per_A2": (-20.0, 20.0),
    "mu_per_m": (0.0, 1e6),
    "mu_per_m_per_A": (0.0, 1e5),
    "sld_end_e6_per_A2": (-20.0, 20.0),
    "mu_end_per_m": (0.0, 1e6),
    "roughness_mrad": (0.0, 20.0),  # RMS slope of a face's normal; kernel windows grow with it
    "left_roughness_mrad": (0.0, 20.0),
    "aperture_mm": (1e-3, 1e3),
    "aperture_distance_m": (0.01, 100.0),
    "pixel_um": (0.01, 1e4),
    "psf_fwhm_um": (0.0, 1e4),
    "wavelength_A": (0.1, 30.0),
    "lambda_A": (0.1, 30.0),
    "fwhm_rel": (0.0, 0.5),
    "distance_mm": (1e-3, 1e3),
    "x_min_um": (-1e6, 1e6),
    "x_max_um": (-1e6, 1e6),
    "x_um": (-1e6, 1e6),
    "T": (-10.0, 10.0),
    "T_err": (1e-12, 10.0),
    "shift_um": (-1e5, 1e5),
    "norm": (1e-3, 1e3),
    "background": (-10.0, 10.0),
    "accuracy": (1e-5, 0.1),
    "b_factor": (1e-3, 1e3),  # fwdfit paganin --b-factor (the paper needed 40)
}


def domain_problem(key: str, value) -> str | None:
    """What is wrong with ``value`` for ``key`` (not a finite number, or outside
    ``DOMAIN[key]``, naming the limit), or None when it is inside the domain."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        return f"must be a finite number, got {value!r}"
    low, high = DOMAIN[key]
    if not low <= value <= high:
        return f"{value:g} is outside the validity domain [{low:g}, {high:g}] ({SEE})"
    return None


def check_domain(key: str, value, where: str) -> float:
    """``value`` as a float if it is inside ``DOMAIN[key]``, else FwdfitError.

    ``where`` names the value for the one-line message (``"scene.toml: sample.tilt_deg"``).
    """
    problem = domain_problem(key, value)
    if problem:
        raise FwdfitError(f"{where}: {problem}")
    return float(value)


def check_domain_rows(key: str, values: np.ndarray, where: str) -> None:
    """Every value of a table column inside ``DOMAIN[key]``; the first outside is named
    by its data row (1 = the row after the header)."""
    low, high = DOMAIN[key]
    outside = np.flatnonzero(~((values >= low) & (values <= high)))
    if outside.size:
        check_domain(key, float(values[outside[0]]), f"{where} row {outside[0] + 1}")
