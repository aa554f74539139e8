"""The Paganin-type filter applied to every measured profile of a scene (``fwdfit paganin``).

The filter (``_paganin.py``) assumes one homogeneous material. Here its constants
come from one layer of the scene's sample: the thickest by default, or the layer
the caller names (the paper used Al's constants for the oxide-coated sample too).
Per profile: mu(lambda) = mu_per_m + mu_per_m_per_A * lambda (+ the material's
Bragg-edge table, if any) of that layer at the profile's spectrum, Theta = D / L of
the profile's instrument, Delta its distance.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import FwdfitError
from ._paganin import paganin_filter_1d, paganin_tau_um2
from ..scene._scene import Layer, Profile, Scene
from ..scene._spectrum import wavelength_quadrature

MODES = ("mean_wavelength", "weighted_tau")
# Quadrature nodes for mode="weighted_tau": tau(lambda) is smooth (lambda^2 / mu(lambda)
# without Bragg edges), so 64 Gauss-Legendre nodes over the spectrum are plenty.
_WEIGHTED_TAU_NODES = 64
# A measured grid may deviate from uniform by this fraction of its step (rounding in files).
_GRID_TOLERANCE = 1e-3


@dataclasses.dataclass(frozen=True)
class PaganinProfile:
    """One filtered profile: pixel centres x_um (n,), measured T (n,), T_filtered (n,), tau in um^2."""

    name: str
    x_um: np.ndarray
    T: np.ndarray
    T_filtered: np.ndarray
    tau_um2: float


def paganin_layer(scene: Scene, material: str | None = None) -> Layer:
    """The layer whose constants the filter uses: ``material`` by name, else the thickest.

    Ties go to the leftmost layer.
    """
    layers = scene.sample.layers
    if material is None:
        return max(layers, key=lambda layer: layer.thickness_um)
    for layer in layers:
        if layer.name == material:
            return layer
    names = ", ".join(layer.name for layer in layers)
    raise FwdfitError(f"material {material!r} is not a layer of the scene (layers: {names})")


def profile_tau_um2(scene: Scene, profile: Profile, layer: Layer, *, b_factor: float = 1.0,
                    mode: str = "mean_wavelength") -> float:
    """Filter parameter tau (um^2) of one profile with the constants of ``layer``.

    mode: "mean_wavelength" (the paper's choice): lambda and mu(lambda) at the spectrum's
    mean wavelength; "weighted_tau": tau(lambda), with mu(lambda), averaged over the spectrum.
    """
    spectrum = scene.spectra[profile.spectrum]
    instrument = scene.instruments[profile.instrument]
    _check_mode(mode)
    if mode == "mean_wavelength":
        lam, weight = np.array([spectrum.mean_wavelength_A]), np.array([1.0])
    else:
        lam, weight = wavelength_quadrature(spectrum, _WEIGHTED_TAU_NODES)
    tau = paganin_tau_um2(wavelength_A=lam, mu_per_m=layer.mu_per_m_at(lam),
                          sld_e6_per_A2=layer.density_scale * layer.sld_e6_per_A2, distance_mm=profile.distance_mm,
                          divergence_rad=1e-3 * instrument.aperture_mm / instrument.aperture_distance_m,
                          b_factor=b_factor)
    return float(np.average(tau, weights=weight))


def paganin_profiles(scene: Scene, *, material: str | None = None, b_factor: float = 1.0,
                     mode: str = "mean_wavelength") -> list[PaganinProfile]:
    """Filter every profile of ``scene``; all must be measured (``file =``).

    Args:
        material: name of the layer whose SLD and mu the filter uses; default the thickest.
        b_factor: multiplies the layer's SLD in tau (the paper needed 40).
        mode: how tau averages over the spectrum, one of ``MODES`` (see `profile_tau_um2`).

    Returns one `PaganinProfile` per profile, in scene order. Raises FwdfitError, naming
    the profile, for a profile without data, an uneven grid, or tau <= 0.
    """
    _check_mode(mode)
    layer = paganin_layer(scene, material)
    filtered = []
    for profile in scene.profiles:
        if profile.T is None:
            raise FwdfitError(f"profile {profile.name} has no measured T (file =): "
                              "the filter needs a measured profile")
        try:
            pixel_um = _grid_step_um(profile.x_um)
            tau = profile_tau_um2(scene, profile, layer, b_factor=b_factor, mode=mode)
            T_filtered = paganin_filter_1d(profile.T, pixel_um, tau)
        except FwdfitError as error:
            raise FwdfitError(f"profile {profile.name}: {error}") from None
        filtered.append(PaganinProfile(profile.name, profile.x_um, profile.T, T_filtered, tau))
    return filtered


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise FwdfitError(f"unknown mode {mode!r} (use {' or '.join(MODES)})")


def _grid_step_um(x_um: np.ndarray) -> float:
    """The pixel step of an evenly spaced x_um grid (the FFT's frequency spacing needs one)."""
    steps = np.diff(x_um)
    step = float(np.median(steps))
    if np.max(np.abs(steps - step)) > _GRID_TOLERANCE * step:
        raise FwdfitError(f"x_um is not evenly spaced (steps {steps.min():.4g} to {steps.max():.4g} um); "
                          "the filter needs a uniform pixel grid")
    return step
