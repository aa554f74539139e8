"""Neutron spectra (tables, Gaussian lines, wavelength bands) and their wavelength quadrature."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .._errors import FwdfitError

_GAUSS_POINTS_PER_SEGMENT = 4
_GAUSSIAN_HALF_WIDTH_SIGMAS = 4.0
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


@dataclasses.dataclass(frozen=True)
class TabulatedSpectrum:
    """Spectral density at ``lambda_A`` (Å, increasing), linear between rows, zero outside.

    ``path``: the table's file, if it came from one (kept for writing scenes back).
    """

    lambda_A: np.ndarray
    weight: np.ndarray
    path: Path | None = None

    def __post_init__(self):
        lam, w = np.asarray(self.lambda_A, float), np.asarray(self.weight, float)
        if lam.ndim != 1 or lam.shape != w.shape or lam.size < 2:
            raise FwdfitError("a spectrum table needs at least two rows of lambda_A, weight")
        if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(w))):
            raise FwdfitError("a spectrum table holds NaN or infinite values")
        if np.any(np.diff(lam) <= 0) or lam[0] <= 0:
            raise FwdfitError("spectrum lambda_A must be positive and increasing")
        if np.any(w < 0) or not np.any(w > 0):
            raise FwdfitError("spectrum weights must be >= 0 and not all zero")

    def density(self, lambda_A: np.ndarray) -> np.ndarray:
        """Spectral density at ``lambda_A`` (any scale)."""
        return np.interp(lambda_A, self.lambda_A, self.weight, left=0.0, right=0.0)

    @property
    def support_A(self) -> tuple[float, float]:
        nonzero = np.flatnonzero(np.asarray(self.weight) > 0)
        lo, hi = max(nonzero[0] - 1, 0), min(nonzero[-1] + 1, len(self.weight) - 1)
        return float(self.lambda_A[lo]), float(self.lambda_A[hi])

    @property
    def mean_wavelength_A(self) -> float:
        lam = np.linspace(*self.support_A, 4001)
        density = self.density(lam)
        return float(np.sum(lam * density) / np.sum(density))


@dataclasses.dataclass(frozen=True)
class GaussianLine:
    """A Gaussian wavelength band with FWHM ``fwhm_rel * wavelength_A`` (velocity selector)."""

    wavelength_A: float
    fwhm_rel: float

    def __post_init__(self):
        if not self.wavelength_A > 0:
            raise FwdfitError("wavelength_A must be positive")
        if not 0 <= self.fwhm_rel < 1:
            raise FwdfitError("fwhm_rel must be in [0, 1)")

    @property
    def sigma_A(self) -> float:
        return self.fwhm_rel * self.wavelength_A / _FWHM_PER_SIGMA

    def density(self, lambda_A: np.ndarray) -> np.ndarray:
        sigma = max(self.sigma_A, 1e-300)
        return np.exp(-0.5 * ((np.asarray(lambda_A) - self.wavelength_A) / sigma) ** 2)

    @property
    def support_A(self) -> tuple[float, float]:
        half = _GAUSSIAN_HALF_WIDTH_SIGMAS * self.sigma_A
        return max(self.wavelength_A - half, 1e-3), self.wavelength_A + half

    @property
    def mean_wavelength_A(self) -> float:
        return float(self.wavelength_A)


@dataclasses.dataclass(frozen=True)
class BandSpectrum:
    """A wavelength bin [lambda_min_A, lambda_max_A] (Å): uniform density, or ``table``'s, inside; zero outside.

    A time-of-flight bin. ``table``: an optional spectrum weighting the band (its file is kept
    for writing scenes back).
    """

    lambda_min_A: float
    lambda_max_A: float
    table: TabulatedSpectrum | None = None

    def __post_init__(self):
        if not 0 < self.lambda_min_A < self.lambda_max_A:
            raise FwdfitError("a band needs 0 < lambda_min_A < lambda_max_A, got "
                              f"{self.lambda_min_A:g} and {self.lambda_max_A:g}")
        if self.table is not None and not np.any(self.table.density(
                np.linspace(self.lambda_min_A, self.lambda_max_A, 1001)) > 0):
            raise FwdfitError(f"the spectrum table is zero across the band {self.lambda_min_A:g} "
                              f"to {self.lambda_max_A:g} Å")

    def density(self, lambda_A: np.ndarray) -> np.ndarray:
        lambda_A = np.asarray(lambda_A, dtype=float)
        inside = (lambda_A >= self.lambda_min_A) & (lambda_A <= self.lambda_max_A)
        weight = 1.0 if self.table is None else self.table.density(lambda_A)
        return np.where(inside, weight, 0.0)

    @property
    def support_A(self) -> tuple[float, float]:
        return float(self.lambda_min_A), float(self.lambda_max_A)

    @property
    def mean_wavelength_A(self) -> float:
        lam = np.linspace(*self.support_A, 4001)
        density = self.density(lam)
        return float(np.sum(lam * density) / np.sum(density))


Spectrum = TabulatedSpectrum | GaussianLine | BandSpectrum


def segment_edges(lo: float, hi: float, n_segments: int, breaks_A=()) -> np.ndarray:
    """Edges (n,) of ``max(n_segments, k + 1)`` segments of [lo, hi] with every one of the k
    ``breaks_A`` inside (lo, hi) an edge; the pieces between breaks are cut into equal
    segments, each extra segment going to the piece whose segments are longest."""
    cuts = np.concatenate([[lo], np.unique([b for b in breaks_A if lo < b < hi]), [hi]])
    lengths = np.diff(cuts)
    counts = np.ones(lengths.size, dtype=int)
    for _ in range(n_segments - counts.sum()):
        counts[np.argmax(lengths / counts)] += 1
    return np.concatenate([np.linspace(a, b, n + 1)[:-1] for a, b, n in zip(cuts[:-1], cuts[1:], counts)]
                          + [[hi]])


def wavelength_quadrature(spectrum: Spectrum, n_nodes: int, breaks_A=()) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (Å) and normalised weights that integrate smooth functions against the spectrum.

    Composite Gauss-Legendre with 4 points per segment of the spectrum's support,
    segments equal between the ``breaks_A`` (Å: wavelengths where the integrand jumps,
    such as Bragg edges) inside the support, which are always segment edges; a line
    narrower than 1e-6 of its wavelength is a single node. Returns two arrays of shape
    ``(n,)``, ``n`` the multiple of 4 at or above ``n_nodes`` (above it, 4 per piece
    between breaks, when there are more pieces than segments).
    """
    if isinstance(spectrum, GaussianLine) and spectrum.fwhm_rel < 1e-6:
        return np.array([spectrum.wavelength_A]), np.array([1.0])
    n_segments = max(1, -(-n_nodes // _GAUSS_POINTS_PER_SEGMENT))
    edges = segment_edges(*spectrum.support_A, n_segments, breaks_A)
    t, w = np.polynomial.legendre.leggauss(_GAUSS_POINTS_PER_SEGMENT)
    half = 0.5 * np.diff(edges)[:, None]
    nodes = (0.5 * (edges[:-1] + edges[1:]))[:, None] + half * t
    weights = half * w * spectrum.density(nodes)
    nodes, weights = nodes.ravel(), weights.ravel()
    return nodes, weights / weights.sum()
