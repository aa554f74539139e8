"""Host values to device arrays, and the plan helpers every geometry shares (pixel grids,
tabulated attenuation)."""

from __future__ import annotations

import jax
import numpy as np

from .._errors import FwdfitError

_MAX_BRAGG_BREAKS = 8  # edges the wavelength quadrature splits at, at most (the strongest)


def to_device(values, dtype=None):
    """values as a JAX array of ``dtype`` (default float, float32 without x64): a plain
    transfer, where ``jnp.asarray`` compiles a small program for every new shape (~14 ms
    each, ~0.2 s of a warm run's plan)."""
    return jax.device_put(np.asarray(values, dtype=float if dtype is None else dtype))


def check_pixels(x_um: np.ndarray, pixel_um: float, where: str) -> None:
    """Measured x_um must be pixel centres on a uniform grid of the instrument's pixel."""
    steps = np.diff(x_um)
    if np.max(np.abs(steps - pixel_um)) > 1e-3 * pixel_um:
        raise FwdfitError(f"{where}: x_um must be spaced by the instrument's pixel_um = {pixel_um} "
                          f"(found steps {steps.min():.4g} to {steps.max():.4g})")


def mu_tables(scene, lam: np.ndarray) -> np.ndarray:
    """Tabulated attenuation (n_lam, n_layer) 1/m of every layer at wavelengths lam (0 without a table)."""
    return np.stack([l.material.mu_table(lam) if l.material and l.material.mu_table else 0 * lam
                     for l in scene.sample.layers], axis=-1)


def bragg_breaks_A(scene, accuracy: float, depth_m: float) -> tuple[float, ...]:
    """Bragg edges (Å) at which the wavelength quadrature splits, for every layer's material.

    Those whose jump in exp(-mu * depth) (about depth_m, the longest path through the sample,
    x the drop in mu) exceeds ``accuracy``, the strongest ``_MAX_BRAGG_BREAKS``; none for
    scenes without tabulated materials.
    """
    edges = [(jump * depth_m, edge) for layer in scene.sample.layers if layer.material
             for edge, jump in zip(layer.material.bragg_edges_A, layer.material.bragg_jumps_per_m)]
    strongest = sorted((e for e in edges if e[0] > accuracy), reverse=True)[:_MAX_BRAGG_BREAKS]
    return tuple(sorted(edge for _, edge in strongest))
