"""A cylinder scene planned into its forward model: the static ray grids, cells and
wavelength nodes (``build_model``), and the scene's values as parameters (``initial_params``).

Sizes, and why (``_nodes``, ``_sub_cells``: measured on the McStas rod): the sub-pixel
cells are a quarter pixel at the default accuracy (cloud-in-cell deposits are exact to
second order in the cell, and the rim's peak is a few µm wide); the uniform ray grid
steps a cell in the detector plane (``_ray_step_cells``); the
circles' grids are geometric (``_FINE_PER_SIDE`` rays from 1e-5 to 0.1 µm, then uniform
to the taper's outer end) because a ray's deflection near a circle changes like the square root of its
distance from it; a free radius or distance is served up to ``_FREE_MARGIN`` beyond its
planned value (the grids and kernels are static).
"""

from __future__ import annotations

import math
from collections.abc import Collection

import jax
import numpy as np

from ..._errors import FwdfitError
from ...scene import _registry as registry
from ...scene._limits import check_domain
from ...scene._scene import Scene
from ...scene._spectrum import wavelength_quadrature
from .._arrays import bragg_breaks_A, check_pixels, mu_tables, to_device
from ._model import CylinderGroup, CylinderModel, CylinderParams, taper

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_PSF_TRUNCATION_SIGMAS = 5.0
_FINE_PER_SIDE = 24  # geometric rays on each side of each circle, 1e-5 to 0.1 µm from it ...
_FINE_FROM_UM = 1e-5
_FINE_UNIFORM_UM = 0.1  # ... then uniform, 0.15 µm apart (below a quarter of a 2.4 µm pixel:
_FINE_STEP_UM = 0.15  # rays sparser than the cells deposit lumps the penumbra does not smooth)
_TAPER_STEPS = 4.0  # the fine grids reach this many steps of the uniform grid (at least _TAPER_MIN_UM):
_TAPER_MIN_UM = 2.0  # a taper narrower than the step leaves the weights' sum off (4e-3 in T at mu = 400/m)
_FREE_MARGIN = 0.3  # a free radius / distance: grids sized this fraction beyond the plan


def _nodes(accuracy: float) -> int:
    """Wavelength nodes of T: the deflection scales as lambda^2, the landings of one node
    are a sharp caustic the penumbra smooths; on the McStas rod 16 nodes differ from 48 by
    3e-6 RMS and from 12 by 1e-5 (BOA white beam, 1.1-34.4 mm)."""
    return int(min(96, max(12, round(16 * math.sqrt(1e-3 / accuracy)))))


def _att_nodes(accuracy: float) -> int:
    """Wavelength nodes of T_att, exp(-mu(lambda) chord) smooth in lambda between Bragg edges
    (the quadrature splits at them): 16 differ from 64 by 4e-6 on the McStas rod, 8 by 7e-5."""
    return 16 if accuracy >= 3e-4 else 64


def _ray_step_cells(accuracy: float) -> float:
    """The uniform ray grid's step in the detector plane, in cells: 1 (3e-5 RMS from 0.5 on
    the McStas rod at 1.1 mm, the rim's peak 0.7 % lower; 2: 6e-5, its peak 1.2 % lower and
    the loss dip 3 % deeper than McStas); steps that do not divide the pixel alias."""
    return 1.0 if accuracy >= 3e-4 else 0.5


def _sub_cells(accuracy: float) -> int:
    """Cells per pixel: 4 (2 differ by 8e-5 RMS at 1.1 mm, but lower the rim's peak there
    by 4 %: the deposit's spread of one cell widens a peak a few µm wide)."""
    return 4 if accuracy >= 3e-4 else 8


def _layer_keys() -> tuple[str, ...]:
    return tuple(key for key, q in registry.part("layers", "cylinder").items() if q.model == "params")


def initial_params(scene: Scene, dtype=None) -> CylinderParams:
    """The scene's values as the cylinder's parameters; every value must be given."""
    sample = scene.sample
    if math.isnan(sample.outer_radius_um):
        raise FwdfitError(f"{scene.path}: sample.outer_radius_um is missing (only a fit may leave out the "
                          "values it varies)")
    for layer in sample.layers:
        for key in (key for key, q in registry.part("layers", "cylinder").items() if q.from_data):
            if math.isnan(getattr(layer, key)):
                raise FwdfitError(f"{scene.path}: layer {layer.name!r}: {key} is missing (only a fit may leave "
                                  "out the values it varies)")
    arr = lambda values: to_device(values, dtype)
    return CylinderParams(
        **{key: arr([registry.layer_value(l, key) for l in sample.layers]) for key in _layer_keys()},
        outer_radius_um=arr(sample.outer_radius_um),
        centre_um=arr(sample.centre_um),
        distance_mm=arr([p.distance_mm for p in scene.profiles]),
        shift_um=arr([p.shift_um + sample.drift_um_per_mm * p.distance_mm for p in scene.profiles]),
    )


def _fine_grid(taper_um: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Distances d (n,) µm from a circle and their weights (n,) µm, tapered off by ``taper_um``."""
    edges = np.concatenate([[0.0], np.geomspace(_FINE_FROM_UM, _FINE_UNIFORM_UM, _FINE_PER_SIDE),
                            np.arange(_FINE_UNIFORM_UM, taper_um[1], _FINE_STEP_UM)[1:], [taper_um[1]]])
    d = 0.5 * (edges[1:] + edges[:-1])
    return d, np.diff(edges) * taper(d, taper_um)


def build_model(scene: Scene, accuracy: float | None = None, free: Collection[str] = (),
                tilt_range_deg=None) -> CylinderModel:
    """The forward model for every profile of a cylinder ``scene``.

    accuracy: target RMS error in T (default the scene's ``[model] accuracy``); free:
    parameter names that may change (a free radius or distance widens the static grids);
    tilt_range_deg: unused (a cylinder has no tilt).
    """
    if not jax.config.jax_enable_x64:  # eps = pi - 2 S cancels O(1) terms (``_rays``)
        raise FwdfitError("a cylinder's model needs float64: call jax.config.update('jax_enable_x64', True) "
                          "first (the fwdfit command does)")
    accuracy = scene.accuracy if accuracy is None else check_domain("accuracy", accuracy, "accuracy")
    sample = scene.sample
    free = set(free)
    grow = 1.0 + (_FREE_MARGIN if "sample.outer_radius_um" in free else 0.0)
    b_max = sample.outer_radius_um * grow + 1.0
    wide = any(name.startswith("profiles.") and name.endswith(".distance_mm") for name in free)
    # Bragg edges split the wavelength quadrature where their jump over the longest chord, 2 R, shows
    breaks_A = bragg_breaks_A(scene, accuracy, 2e-6 * b_max)
    plans: dict[tuple, list[int]] = {}
    per_profile, pads, steps = [], {}, []
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        spectrum = scene.spectra[profile.spectrum]
        x = np.asarray(profile.x_um, float)
        check_pixels(x, instrument.pixel_um, f"profile {profile.name!r}")
        cell = instrument.pixel_um / _sub_cells(accuracy)
        L = instrument.aperture_distance_m * 1e6
        delta = 1e3 * profile.distance_mm * (1.0 + (_FREE_MARGIN if wide else 0.0))
        width = instrument.aperture_mm * 1e3 * delta / (L - delta)
        aperture_cells = math.ceil(0.5 * width / cell) + 1
        sigma = instrument.psf_fwhm_um / _FWHM_PER_SIGMA
        psf_cells = math.ceil(_PSF_TRUNCATION_SIGMAS * sigma / cell) if sigma > 0 else 0
        lam, weight = wavelength_quadrature(spectrum, _nodes(accuracy), breaks_A)
        att_lam, att_weight = wavelength_quadrature(spectrum, _att_nodes(accuracy), breaks_A)
        # profiles alike share one vmapped program (an image's rows); others run apart, since
        # a vmapped deposit is slower than separate ones (37 against 14 ms for the McStas rod)
        key = (profile.instrument, len(x), len(lam), len(att_lam), aperture_cells, psf_cells)
        plans.setdefault(key, []).append(i)
        pads[i] = (aperture_cells, psf_cells)
        first = x[0] - 0.5 * instrument.pixel_um + 0.5 * cell
        per_profile.append((first, lam, weight, mu_tables(scene, lam), att_lam, att_weight,
                            mu_tables(scene, att_lam)))
        steps.append(_ray_step_cells(accuracy) * cell * (L - 1e3 * profile.distance_mm) / L)
    groups = []
    for (name, n_pixel, *_), index in plans.items():
        instrument = scene.instruments[name]
        cell = instrument.pixel_um / _sub_cells(accuracy)
        aperture_cells = max(pads[i][0] for i in index)
        psf_cells = max(pads[i][1] for i in index)
        n_pad = aperture_cells + psf_cells
        stack = lambda k: to_device(np.stack([per_profile[i][k] for i in index]))
        groups.append(CylinderGroup(
            index=tuple(index), aperture=instrument.aperture, aperture_um=instrument.aperture_mm * 1e3,
            aperture_distance_um=instrument.aperture_distance_m * 1e6,
            psf_sigma_um=instrument.psf_fwhm_um / _FWHM_PER_SIGMA, cell_um=cell, n_pixel=n_pixel,
            n_sub=_sub_cells(accuracy), aperture_cells=aperture_cells, psf_cells=psf_cells,
            fresnel=instrument.fresnel,
            first_cell_um=to_device([per_profile[i][0] - n_pad * cell for i in index]),
            wavelength_A=stack(1), wavelength_weight=stack(2), mu_table_per_m=stack(3),
            att_wavelength_A=stack(4), att_weight=stack(5), att_mu_table_per_m=stack(6)))
    step = min(steps)
    reach = max(_TAPER_MIN_UM, _TAPER_STEPS * step)
    taper_um = (0.25 * reach, reach)
    coarse = (np.arange(math.ceil((b_max + reach) / step)) + 0.5) * step
    fine_d, fine_w = _fine_grid(taper_um)
    return CylinderModel(groups=tuple(groups), coarse_b_um=to_device(coarse), coarse_step_um=step,
                         fine_d_um=to_device(fine_d), fine_weight_um=to_device(fine_w),
                         n_profiles=len(scene.profiles), taper_um=taper_um, tube=sample.core == "vacuum")
