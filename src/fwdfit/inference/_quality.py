"""The quality gate: does the data accept the fitted model?

After a fit, the normalised residuals (data - model) / sigma are compared with
their noise expectation over the whole fit, per profile and per region of each
profile (the edge regions around every interface, where refraction lives, and the
plateaus between them): chi-square against its expectation n +- sqrt(2 n), and the
number of runs of equal sign (Wald-Wolfowitz) against its expectation, which
catches a systematic misfit that chi-square spreads thin. A region fails when its
excess is both significant (more than ``SIGNIFICANCE`` standard deviations) and
large (reduced chi-square above a limit), so that a model error well below the
noise of a long profile does not reject a good fit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model._geometry import edge_half_width_um as edge_half_width_um

SIGNIFICANCE = 5.0  # standard deviations of the noise expectation
_LIMIT_OVERALL = 1.5  # reduced chi-square above which the whole fit fails (when significant)
_LIMIT_PROFILE = 2.0
_LIMIT_REGION = 3.0
_MIN_BROAD_PIXELS = 30  # chi-square alone fails a region of at least this many pixels
_WINDOW_PIXELS = (16, 64)  # sliding windows inside each region: a local misfit is not diluted
_WINDOW_SIGNIFICANCE = 6.0  # ... judged at this significance (of order 100 windows per profile)


@dataclasses.dataclass(frozen=True)
class Region:
    """One stretch of one profile with its residual statistics."""

    profile: str
    what: str  # e.g. "edge Al | vacuum", "inside Al", "open beam"
    x_from_um: float
    x_to_um: float
    n: int
    chi2: float
    mean_z: float  # sum of the residuals / sqrt(n): a systematic offset
    runs_z: float  # (runs - expected) / sd; strongly negative: residuals in long runs of one sign
    window: bool = False  # a sliding window inside a region: judged on systematic misfit only

    @property
    def chi2_reduced(self) -> float:
        return self.chi2 / max(self.n, 1)

    @property
    def chi2_z(self) -> float:
        return (self.chi2 - self.n) / math.sqrt(2.0 * max(self.n, 1))

    def fails(self, limit: float) -> bool:
        """Whether the excess is large (reduced chi-square above ``limit``) and significant:
        systematic (an offset, or runs of one sign) or, over a long stretch, chi-square alone.
        A few pixels off both ways (the finest refraction fringes) is not enough."""
        significance = _WINDOW_SIGNIFICANCE if self.window else SIGNIFICANCE  # many windows are tried
        systematic = abs(self.mean_z) > significance or self.runs_z < -significance
        broad = self.chi2_z > SIGNIFICANCE and self.n >= _MIN_BROAD_PIXELS and not self.window
        return self.chi2_reduced > limit and (systematic or broad)

    def describe(self) -> str:
        return (f"profile {self.profile}, x {self.x_from_um:.0f} to {self.x_to_um:.0f} um ({self.what}): "
                f"chi2/pixel {self.chi2_reduced:.2f} over {self.n} pixels, mean residual "
                f"{self.mean_z / math.sqrt(max(self.n, 1)):+.2f} sigma")


@dataclasses.dataclass(frozen=True)
class Quality:
    """The gate's verdict: ``passed``, the regions that fail (worst first) and one line saying where."""

    passed: bool
    overall: Region
    profiles: tuple[Region, ...]
    regions: tuple[Region, ...]
    failing: tuple[Region, ...]

    def summary(self) -> str:
        if self.passed:
            return f"the data accept the fit (chi2/pixel {self.overall.chi2_reduced:.3f})"
        return "the data reject the fit: " + self.failing[0].describe()


def runs_z(signs: np.ndarray) -> float:
    """Wald-Wolfowitz runs statistic of a sign sequence (0 if one sign only)."""
    positive = int(np.sum(signs > 0))
    negative = len(signs) - positive
    n = positive + negative
    if positive == 0 or negative == 0 or n < 3:
        return 0.0
    runs = 1 + int(np.sum(signs[1:] != signs[:-1]))
    expected = 2.0 * positive * negative / n + 1.0
    variance = (expected - 1.0) * (expected - 2.0) / (n - 1.0)
    return (runs - expected) / math.sqrt(max(variance, 1e-12))


def _region(profile: str, what: str, x, z) -> Region:
    return Region(profile, what, float(x[0]), float(x[-1]), len(z), float(np.sum(z * z)),
                  float(np.sum(z) / math.sqrt(max(len(z), 1))), runs_z(np.sign(z)))


def assess(names: list[str], x_um: list[np.ndarray], z: list[np.ndarray],
           interfaces: list[list[tuple[float, str]]], half_width_um: list[float], n_free: int) -> Quality:
    """Judge normalised residuals z (one array per profile, on pixels x_um).

    interfaces: per profile, (x_from, x_to µm on the detector, label) of every interface:
    where its attenuation edge and its refraction fringes land;
    half_width_um: per profile, the margin added on both sides of that stretch.
    """
    every = np.concatenate(z)
    overall = dataclasses.replace(_region("all", "all profiles", np.array([0.0]), every),
                                  n=max(len(every) - n_free, 1))
    per_profile, regions, windows = [], [], []
    for name, x, r, faces, half in zip(names, x_um, z, interfaces, half_width_um):
        per_profile.append(_region(name, "whole profile", x, r))
        label = np.full(len(x), "", dtype=object)
        for lo, hi, what in faces:
            near = (x >= min(lo, hi) - half) & (x <= max(lo, hi) + half)
            label[near & (label == "")] = f"edge {what}"
        plateaus = sorted(0.5 * (lo + hi) for lo, hi, _ in faces)
        rest = np.flatnonzero(label == "")
        label[rest] = [f"plateau {k}" for k in np.searchsorted(plateaus, x[rest])]
        for what in dict.fromkeys(label):
            where = label == what
            if where.sum() >= 5:
                named = _plateau_name(what, faces)
                regions.append(_region(name, named, x[where], r[where]))
                windows.extend(_windows(name, named, x[where], r[where], _LIMIT_REGION))
    failing = ([r for r in regions + windows if r.fails(_LIMIT_REGION)]
               + [r for r in per_profile if r.fails(_LIMIT_PROFILE)])
    if overall.fails(_LIMIT_OVERALL):
        failing.append(overall)
    failing.sort(key=lambda r: -r.chi2_z)
    return Quality(not failing, overall, tuple(per_profile), tuple(regions), tuple(failing))


def _windows(profile: str, what: str, x, z, limit: float) -> list[Region]:
    """The stretches of _WINDOW_PIXELS pixels, sliding by half their width over one region,
    whose reduced chi-square exceeds ``limit`` (only those can fail; every window's
    chi-square comes from one cumulative sum). They fail only on a systematic misfit (``Region.fails``),
    which noise rarely mimics."""
    squares = np.concatenate([[0.0], np.cumsum(z * z)])
    out = []
    for width in _WINDOW_PIXELS:
        starts = np.arange(0, len(z) - width + 1, width // 2)
        chi2 = squares[starts + width] - squares[starts]
        for start in starts[chi2 > limit * width]:
            window = slice(start, start + width)
            out.append(dataclasses.replace(_region(profile, what, x[window], z[window]), window=True))
    return out


def _plateau_name(label: str, faces) -> str:
    """'plateau k' -> what lies there (open beam or a layer), from the interface labels."""
    if not label.startswith("plateau"):
        return label
    k = int(label.split()[1])
    ordered = [what for _, _, what in sorted(faces)]
    if not ordered:
        return "whole profile"
    if k == 0:
        return "open beam, left"
    if k == len(ordered):
        return "open beam, right"
    return "inside " + ordered[k - 1].split(" | ")[-1]
