"""Experiment design: which measurements determine the quantities a user wants best.

A candidate measurement is a spectrum (with the instrument of the profiles that use it)
at a sample-detector distance, on the pixels of the widest profile of that instrument.
Its Fisher information per unit of exposure, for the scene's shared free parameters, is
F_c = J_c^T J_c / sigma_c^2 at the scene's values, with J_c the model's derivatives
(central differences of the compiled model, ``Predictor``) and sigma_c = noise sqrt(T)
the Poisson error of a pixel in one unit of exposure. A candidate's own nuisances (the
scene's per-profile free parameters: shift, norm, background) are marginalised (Schur
complement), so its information scales with its exposure. A plan t (exposure per
candidate, sum = the budget) has F(t) = sum_c t_c F_c and predicted covariance F(t)^-1.

The plan minimises sum_j Var(theta_j) / theta_j^2 over the targets j (relative variances;
an absolute one for a target whose value is 0) on the simplex of exposures: a convex
problem (L-optimal design), solved by the multiplicative algorithm
t_c <- t_c (g_c / mean_t g)^(1/2), g_c = -d phi / d t_c, to the equivalence theorem's
bound (max_c g_c <= (1 + tol) sum_c t_c g_c / budget).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._geometry import geometry_of
from ._parameters import FreeParameter, assembler, free_parameters
from ._predict import Predictor
from .._errors import FwdfitError
from .._progress import Progress, as_progress
from ..scene import _registry as registry
from ..scene._scene import Profile, Scene, load_scene

_DIFFERENCE_STEP = 0.1  # central-difference step, in the registry's typical steps
_RIDGE = 1e-10  # times the information's diagonal: keeps an undetermined plan invertible
_TOLERANCE = 1e-4  # the equivalence theorem's bound, relative
_MAX_ITERATIONS = 20_000
_NEGLIGIBLE = 1e-3  # a candidate with less than this share of the budget is left out of the plan


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One possible measurement: a spectrum (and its instrument) at a distance (mm)."""

    spectrum: str
    instrument: str
    distance_mm: float

    @property
    def label(self) -> str:
        return f"{self.spectrum}@{self.distance_mm:g}mm"


@dataclasses.dataclass(frozen=True)
class Design:
    """The candidates' information and the plans compared.

    parameters: the shared free parameters (n,); values (n,): the scene's values there;
    targets: indices into parameters; candidates (C,); information (C, n, n) per unit
    exposure, nuisances marginalised; budget: total exposure; plans: name -> exposures
    (C,) ("optimal", "even": the budget spread over every candidate, "scene": the
    scene's own measurements, one unit each scaled to the budget).
    """

    parameters: tuple[str, ...]
    values: np.ndarray
    targets: tuple[int, ...]
    candidates: tuple[Candidate, ...]
    information: np.ndarray
    budget: float
    noise: float
    plans: dict[str, np.ndarray]

    def errors(self, exposures: np.ndarray) -> np.ndarray:
        """Predicted standard errors (n,) of the parameters for exposures (C,); inf where the
        plan cannot determine a parameter."""
        F = np.tensordot(np.asarray(exposures, float), self.information, axes=1)
        return _standard_errors(F)

    def single_errors(self) -> np.ndarray:
        """(C, n): the standard errors if the whole budget went to each candidate alone."""
        return np.stack([_standard_errors(self.budget * F) for F in self.information])


def design(scene: Scene | str, *, target=None, distances_mm=None, spectra=None, exposure: float | None = None,
           noise: float | None = None, accuracy: float | None = None,
           progress: bool | Progress = False) -> Design:
    """The measurement plan that minimises the targets' predicted errors (``Design``).

    Arguments default to the scene's ``[design]`` table (``DesignSpec``): target (``vary``
    names), distances_mm, spectra (names), exposure (total, in profile exposures), noise
    (relative error of an open-beam pixel in one unit of exposure). The design is made at
    the scene's values: each free parameter needs one.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    say = as_progress(progress)
    spec = scene.design
    target = tuple(spec.target if target is None else target)
    distances = tuple(spec.distances_mm if distances_mm is None else distances_mm) or tuple(
        dict.fromkeys(p.distance_mm for p in scene.profiles))
    names = tuple(spec.spectra if spectra is None else spectra) or tuple(dict.fromkeys(p.spectrum for p in scene.profiles))
    budget = _first(exposure, spec.exposure, float(len(scene.profiles)))
    noise = _first(noise, spec.noise) if noise is not None or not math.isnan(spec.noise) else math.nan
    if not scene.profiles:
        raise FwdfitError(f"{scene.path}: design: the scene has no profile to take the pixels and instruments from")
    if not (budget > 0 and math.isfinite(budget)):
        raise FwdfitError(f"{scene.path}: design.exposure: must be a positive number, got {budget}")
    if math.isnan(noise):
        noise = _noise_of(scene)
    shared = [p for p in free_parameters(scene) if not p.name.startswith("profiles.")]
    if not shared:
        raise FwdfitError(f"{scene.path}: fit.vary: design needs a shared free parameter (sample or layer)")
    unknown = [p.name for p in shared if not math.isfinite(p.value)]
    if unknown:
        raise FwdfitError(f"{scene.path}: {unknown[0]}: design needs a value (it plans for the scene's values)")
    names_shared = tuple(p.name for p in shared)
    target = target or names_shared
    missing = [t for t in target if t not in names_shared]
    if missing:
        raise FwdfitError(f"{scene.path}: design.target: {missing[0]!r} is not a shared free parameter "
                          f"(fit.vary: {', '.join(names_shared)})")
    candidates = _candidates(scene, names, distances)
    nuisances = tuple(dict.fromkeys(p.name.rsplit(".", 1)[-1] for p in free_parameters(scene)
                                    if p.name.startswith("profiles.")))
    say(f"design: {len(candidates)} candidate measurements, {len(shared)} shared parameters"
        + (f", nuisances {', '.join(nuisances)} per measurement" if nuisances else ""))
    information = _information(scene, shared, nuisances, candidates, noise, accuracy, say)
    values = np.array([p.value for p in shared])
    targets = tuple(names_shared.index(t) for t in target)
    weights = np.zeros(len(shared))
    weights[list(targets)] = [1.0 / values[i] ** 2 if values[i] != 0 else 1.0 / shared[i].step ** 2 for i in targets]
    even = np.full(len(candidates), budget / len(candidates))
    own = np.array([sum(1.0 for p in scene.profiles if (p.spectrum, p.distance_mm) == (c.spectrum, c.distance_mm))
                    for c in candidates])
    undetermined = [names_shared[i] for i in targets if not math.isfinite(
        _standard_errors(np.tensordot(even, information, axes=1))[i])]
    if undetermined:
        raise FwdfitError(f"{scene.path}: design: no plan of these candidates determines {undetermined[0]}")
    plans = {"optimal": optimal_plan(information, weights, even), "even": even}
    if own.sum() > 0:
        plans["scene"] = own * budget / own.sum()
    return Design(names_shared, values, targets, candidates, information, budget, noise, plans)


def _first(*values) -> float:
    """The first of values that is given (not None, not NaN)."""
    return next(float(v) for v in values if v is not None and not (isinstance(v, float) and math.isnan(v)))


def _noise_of(scene: Scene) -> float:
    """The relative error of an open-beam pixel in one profile's exposure: the median over
    the profiles with errors of median(T_err / sqrt(T))."""
    ratios = [np.median(p.T_err / np.sqrt(np.clip(p.T, 1e-6, None))) for p in scene.profiles
              if p.T is not None and p.T_err is not None]
    if not ratios:
        raise FwdfitError(f"{scene.path}: design.noise: needed (no profile has T_err to take it from)")
    return float(np.median(ratios))


def _candidates(scene: Scene, spectra: tuple[str, ...], distances: tuple[float, ...]) -> tuple[Candidate, ...]:
    """Every spectrum at every distance, and the scene's own measurements."""
    instrument_of = {}
    for p in scene.profiles:
        instrument_of.setdefault(p.spectrum, p.instrument)
    missing = [s for s in spectra if s not in instrument_of]
    if missing:
        raise FwdfitError(f"{scene.path}: design.spectra: {missing[0]!r}: no profile uses it "
                          "(its instrument is taken from one)")
    pairs = [(s, d) for s in spectra for d in distances] + [(p.spectrum, p.distance_mm) for p in scene.profiles]
    return tuple(Candidate(s, instrument_of[s], d) for s, d in dict.fromkeys(pairs))


def _information(scene: Scene, shared: list[FreeParameter], nuisances: tuple[str, ...],
                 candidates: tuple[Candidate, ...], noise: float, accuracy, say: Progress) -> np.ndarray:
    """(C, n, n): each candidate's information per unit exposure, nuisances marginalised."""
    widest = {}
    for p in scene.profiles:
        if p.instrument not in widest or len(p.x_um) > len(widest[p.instrument].x_um):
            widest[p.instrument] = p
    profiles = tuple(Profile(f"c{i}", c.distance_mm, c.spectrum, c.instrument, widest[c.instrument].x_um)
                     for i, c in enumerate(candidates))
    vary = (*(p.name for p in shared), *(f"profiles.*.{key}" for key in nuisances))
    bounds = {p.name: (p.low, p.high) for p in shared}
    candidate_scene = dataclasses.replace(scene, profiles=profiles)
    free = free_parameters(candidate_scene, vary, bounds)
    base = np.array([p.value for p in free])
    h = _DIFFERENCE_STEP * np.array([p.step for p in free])
    model = geometry_of(candidate_scene).build_model(candidate_scene, accuracy, [p.name for p in free], None)
    with say.ticking("compiling"):
        predict = Predictor(model, assembler(candidate_scene, free), len(free))
    say(f"model ready in {predict.compile_time_s:.1f} s ({predict.sources_text()})")
    rows = np.concatenate([base[None], base + np.diag(h), base - np.diag(h)])
    T = predict(rows)[0]
    n = len(free)
    J = (T[1:n + 1] - T[n + 1:]).T / (2 * h)  # (pixels, n)
    if not (np.isfinite(T).all() and np.isfinite(J).all()):
        raise FwdfitError(f"{scene.path}: design: the model is not finite near the scene's values")
    ends = np.cumsum([len(p.x_um) for p in profiles])[:-1]
    n_shared = len(shared)
    information = []
    for i, (Jc, Tc) in enumerate(zip(np.split(J, ends), np.split(T[0], ends))):
        own = [k for k, p in enumerate(free) if p.name.startswith("profiles.") and p.target[1] == (i,)]
        keep = list(range(n_shared)) + own
        Jc = Jc[:, keep] / (noise * np.sqrt(np.clip(Tc, 1e-6, None)))[:, None]
        F = Jc.T @ Jc
        A, B, D = F[:n_shared, :n_shared], F[:n_shared, n_shared:], F[n_shared:, n_shared:]
        information.append(A - B @ np.linalg.pinv(D) @ B.T if own else A)
    return np.stack(information)


def _standard_errors(F: np.ndarray) -> np.ndarray:
    """Standard errors (n,) from an information matrix; inf for an undetermined parameter."""
    scale = np.sqrt(np.clip(np.diag(F), 1e-300, None))
    R = F / np.outer(scale, scale)
    eigenvalues, vectors = np.linalg.eigh(R)
    determined = eigenvalues > 1e-10 * max(eigenvalues.max(), 1e-300)
    variance = (vectors[:, determined] ** 2 / eigenvalues[determined]).sum(axis=1)
    weak = (vectors[:, ~determined] ** 2).sum(axis=1) > 1e-6
    return np.where(weak | (np.diag(F) <= 0), np.inf, np.sqrt(variance) / scale)


def optimal_plan(information: np.ndarray, weights: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Exposures (C,) minimising sum_j weights_j Var_j on the simplex sum = start.sum()."""
    budget = start.sum()
    ridge = _RIDGE * np.diag(np.tensordot(start, information, axes=1))
    t = start.copy()
    for _ in range(_MAX_ITERATIONS):
        F_inverse = np.linalg.inv(np.tensordot(t, information, axes=1) + np.diag(ridge))
        M = F_inverse @ np.diag(weights) @ F_inverse
        g = np.einsum("ij,cji->c", M, information)  # -d phi / d t_c
        mean = t @ g / budget
        if g.max() <= (1 + _TOLERANCE) * mean:
            break
        t = t * np.sqrt(g / mean)
        t *= budget / t.sum()
    t = np.where(t < _NEGLIGIBLE * budget, 0.0, t)
    return t * budget / t.sum()
