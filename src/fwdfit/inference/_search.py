"""The global stage of a fit: a cheap scan of what the edges pin only weakly.

Positions, thicknesses and attenuations come from the data (``_starts``); the tilt
and the SLDs shape only the refraction fringes, whose chi-square landscape has
several basins (a wrong-signed tilt traded against a larger SLD, say), and the
fringes must line up with the data to rank a tilt fairly: where the edges show too
little contrast to be read to a µm (a weak absorber in noisy bins), what the data pin
(positions, plateaus) first settles by a local solve at the starting tilt and SLDs.
The scan then evaluates chi-square, model and data smoothed alike, on a grid of tilts (refined
around the best few), then on a grid of SLD scales at the best tilts, all through
the compiled model; the local solver then starts from the best few points.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ._parameters import FreeParameter
from ._starts import _SLD_VALUES, Estimate  # the SLDs tried where the scene gives none ...

_TILT_SPACING_DEG = 0.1  # coarse tilt grid up to 1 degree ...
_WIDE_TILT_SPACING_DEG = 0.25  # ... and beyond
_TILT_REFINE_DEG = (-0.05, -0.025, 0.025, 0.05)  # around each of the best coarse tilts
_TILT_MINIMA = 3  # coarse minima refined
_SLD_FACTORS = tuple(np.array(_SLD_VALUES) / 2.5)  # ... else scales of the scene's value (0.2-2.4)
_SLD_SWEEPS = 2  # sweeps over the SLDs, one at a time
_UNKNOWN_SLD = 2.0  # SLD of a layer without start until its scan
_DISTINCT_TILT_DEG = 1.5 * _TILT_SPACING_DEG  # candidates closer in tilt than this share a basin
_INSIDE = 1e-3  # candidates stay this fraction of the box inside two bounds


def _tilt_grid(low: float, high: float) -> np.ndarray:
    near = np.arange(-1.0, 1.0 + 1e-9, _TILT_SPACING_DEG)
    far = np.concatenate([np.arange(-5.0, -1.0, _WIDE_TILT_SPACING_DEG),
                          np.arange(1.0 + _WIDE_TILT_SPACING_DEG, 5.0 + 1e-9, _WIDE_TILT_SPACING_DEG)])
    grid = np.concatenate([near, far])
    return np.sort(grid[(grid > low) & (grid < high)])


def _inside(free: tuple[FreeParameter, ...], values: np.ndarray) -> np.ndarray:
    """values (m, n) moved just inside their bounds."""
    out = values.copy()
    for j, p in enumerate(free):
        span = p.high - p.low
        margin = _INSIDE * span if math.isfinite(span) else 1e-6 * max(p.step, 1.0)
        out[:, j] = np.clip(out[:, j], p.low + margin, p.high - margin)
    return out


def global_search(free: tuple[FreeParameter, ...], estimate: Estimate,
                  chi2_of: Callable[[np.ndarray], np.ndarray], at_tilts, n_keep: int,
                  extra: np.ndarray | None = None, settle: Callable[[np.ndarray], np.ndarray] | None = None
                  ) -> tuple[np.ndarray, int]:
    """The n_keep best distinct starting points (n_keep, n_free) and the number of points evaluated.

    chi2_of: rows of free values (m, n_free) -> chi-square (m,). at_tilts: the geometry's
    ``at_tilts(free, estimate, row, tilts)``, a row at trial tilts. extra: further points
    (e.g. the scene's own start) that compete with the scanned ones. settle: a row
    (n_free,) -> the row with the values the data pin locally fitted, applied to the
    estimate before the scan.
    """
    chi2_of = _remembered(chi2_of)
    names = [p.name for p in free]
    tilt = names.index("sample.tilt_deg") if "sample.tilt_deg" in names else None
    slds = [j for j, p in enumerate(free) if p.target[0] == "sld_e6_per_A2"]
    unknown_sld = [j for j in slds if math.isnan(estimate.values[names[j]])]
    base = np.array([estimate.values[n] for n in names], float)
    base[unknown_sld] = _UNKNOWN_SLD
    if tilt is not None and math.isnan(base[tilt]):
        base[tilt] = 0.0
    if settle is not None and (tilt is not None or slds):
        base = settle(_inside(free, base[None])[0])
    points = _inside(free, base[None] if extra is None else np.concatenate([base[None], extra]))
    chi2 = chi2_of(points)
    if tilt is not None:
        coarse = _inside(free, at_tilts(free, estimate, base, _tilt_grid(free[tilt].low, free[tilt].high)))
        coarse_chi2 = chi2_of(coarse)
        is_min = (np.r_[True, coarse_chi2[1:] <= coarse_chi2[:-1]]
                  & np.r_[coarse_chi2[:-1] <= coarse_chi2[1:], True])
        minima = np.flatnonzero(is_min)
        minima = minima[np.argsort(coarse_chi2[minima])][:_TILT_MINIMA]
        minima = minima[np.isfinite(coarse_chi2[minima])]
        refined = _inside(free, at_tilts(free, estimate, base, np.concatenate(
            [coarse[m, tilt] + np.array(_TILT_REFINE_DEG) for m in minima] + [np.zeros(0)])))
        points = np.concatenate([points, coarse, refined])
        chi2 = np.concatenate([chi2, coarse_chi2, chi2_of(refined)])
    if slds:
        # SLD by SLD (each layer's fringes sit at its own interfaces): sweeps from the two best
        # points so far; each trial set holds the current value, so a sweep never loses.
        for row in points[np.argsort(chi2)[:2]]:
            for _ in range(_SLD_SWEEPS):
                for j in slds:
                    trials = np.repeat(row[None], 1 + len(_SLD_VALUES), axis=0)
                    trials[1:, j] = (np.array(_SLD_VALUES) if j in unknown_sld
                                     else row[j] * np.array(_SLD_FACTORS))
                    trials = _inside(free, trials)
                    trial_chi2 = chi2_of(trials)
                    points = np.concatenate([points, trials])
                    chi2 = np.concatenate([chi2, trial_chi2])
                    row = trials[np.argmin(np.where(np.isfinite(trial_chi2), trial_chi2, np.inf))]
    order = np.argsort(np.where(np.isfinite(chi2), chi2, np.inf))
    kept: list[np.ndarray] = []
    for i in order:
        if len(kept) == n_keep:
            break
        if all(not _same(points[i], k, free) for k in kept):
            kept.append(points[i])
    return np.array(kept), chi2_of.n_evaluated


def _remembered(chi2_of: Callable[[np.ndarray], np.ndarray]):
    """chi2_of that evaluates each distinct row once (a sweep's trial set holds its current
    point; a second sweep over a single SLD repeats the first)."""
    known: dict[bytes, float] = {}

    def remembered(rows: np.ndarray) -> np.ndarray:
        new = [row for row in {row.tobytes(): row for row in rows if row.tobytes() not in known}.values()]
        if new:
            known.update(zip((row.tobytes() for row in new), chi2_of(np.array(new))))
        remembered.n_evaluated = len(known)
        return np.array([known[row.tobytes()] for row in rows])

    remembered.n_evaluated = 0
    return remembered


def _same(a: np.ndarray, b: np.ndarray, free: tuple[FreeParameter, ...]) -> bool:
    """Whether two candidates lie in one basin of the scan: tilts closer than the coarse
    grid's spacing (when the tilt is free), else every value within 2 % or one typical step."""
    names = [p.name for p in free]
    if "sample.tilt_deg" in names:
        j = names.index("sample.tilt_deg")
        return abs(a[j] - b[j]) < _DISTINCT_TILT_DEG
    return all(abs(x - y) <= max(0.02 * abs(y), p.step) for x, y, p in zip(a, b, free))
