"""Joint least-squares fit of one sample model to every profile of a scene.

The strategy, each step in its own module:

1. starting values read off the data (``_starts``: edges, plateaus, open beam),
   whatever the scene says; a free parameter may have no start value at all;
2. a global scan of what the edges pin only weakly, tilt and SLDs (``_search``);
3. Levenberg-Marquardt from the best few points at once (``_least_squares``);
4. uncertainties from the Jacobian at the optimum (``_uncertainty``);
5. the quality gate: does the data accept the fit, and if not, where not (``_quality``).

Every model evaluation goes through the compiled model (``_predict``: one program per
group of profiles), so a fit compiles the model once; the residuals (norm * T + background - T_meas) / sigma
are formed around it in NumPy.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

import jax
import numpy as np

from ..scene import _registry as registry
from .._errors import FwdfitError, ModelWarning
from ._least_squares import levenberg_marquardt
from ._objective import Objective
from ._parameters import LAYER_FIELDS, FreeParameter, assembler, free_parameters
from ._geometry import Geometry, geometry_of
from ._predict import Predictor
from .._progress import Progress, as_progress
from ._quality import Quality, assess
from ..scene._scene import ERRORS_ESTIMATE, Scene, load_scene
from ._search import global_search
from ._starts import noise_sigma
from ._uncertainty import band, central_differences, covariance, errors_and_correlation

_SEARCH_SMOOTHING_UM = 4.0  # Gaussian sigma of model and data in the global scan
_CANDIDATES = 3  # starting points handed from the global scan to the local solver
_SETTLE_TOLERANCE = 0.3  # standard errors: the held phase of the local solver only finds the basin
_SETTLE_FLOOR = 0.1  # typical steps (0.1 µm, 0.1 /m): rich data pin values far tighter than a scan needs
_TINY_SLOPE = 1e-12  # d value / d u below this counts as zero (a value deep in a bound's transform)
_ERROR_STEP = 0.1  # central-difference step for the final Jacobian, in standard errors


@dataclasses.dataclass(frozen=True)
class FittedProfile:
    """Per-pixel fit output (n,): the data, the model, and the refraction-free profiles.

    T_att is the fitted attenuation-only profile with the same normalisation and
    background as the data; T_corrected = T - (T_model - T_att) is the measurement
    with the fitted refraction signal removed.
    """

    name: str
    x_um: np.ndarray
    T: np.ndarray
    sigma: np.ndarray
    T_model: np.ndarray
    T_att: np.ndarray
    T_att_err: np.ndarray
    T_corrected: np.ndarray


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Fitted values with 1-sigma errors and correlations, in the units of the scene keys.

    ``converged``: the local solver met its tolerance; ``quality``: whether the data
    accept the fit (``quality.passed``) and, if not, where they reject it.
    """

    names: tuple[str, ...]
    values: np.ndarray
    errors: np.ndarray
    correlation: np.ndarray
    chi2: float
    dof: int
    converged: bool
    message: str
    n_steps: int
    compile_time_s: float
    wall_time_s: float  # the fit itself, after compilation
    profiles: tuple[FittedProfile, ...]
    warnings: tuple[str, ...]
    sigma_from_data: bool
    scene: Scene
    chi2_per_start: np.ndarray  # (n_starts,) final chi-square from every local start
    quality: Quality
    start: dict  # free name -> starting value read off the data (NaN where none)
    n_evaluations: int  # model evaluations of the fit (scan, solver, errors)
    model_warnings: tuple[str, ...] = ()  # the model's notes when built (``ModelWarning``: a thin layer left independent)

    @property
    def chi2_reduced(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def accepted(self) -> bool:
        """Converged, and accepted by the data."""
        return self.converged and self.quality.passed

    def __getitem__(self, name: str) -> tuple[float, float]:
        """(value, error) of a parameter by its name."""
        i = self.names.index(name)
        return float(self.values[i]), float(self.errors[i])

    def table(self) -> str:
        """The parameter table as text."""
        width = max(len(n) for n in self.names)
        rows = [f"{n:<{width}}  {v:>14.6g} ± {e:<10.3g}" for n, v, e in zip(self.names, self.values, self.errors)]
        rows.append(f"chi2_reduced = {self.chi2_reduced:.4g} (dof {self.dof}), steps {self.n_steps}, "
                    f"converged {self.converged}")
        return "\n".join(rows)


def _data(scene: Scene):
    images = [p.name for p in scene.profiles if p.image is not None]
    if images:
        raise FwdfitError(f"{scene.path}: profile {images[0]!r} is an image: fit it with fwdfit fit-image")
    missing = [p.name for p in scene.profiles if p.T is None]
    if missing:
        raise FwdfitError(f"{scene.path}: profile {missing[0]!r} has no measured data (file = ...)")
    sigmas, from_data = [], False
    for p in scene.profiles:
        if p.T_err is not None:
            sigmas.append(p.T_err)
        else:
            sigma = noise_sigma(p.T)
            if not sigma > 0:
                raise FwdfitError(f"{scene.path}: profile {p.name!r}: no T_err and no noise to estimate it from")
            sigmas.append(np.full_like(p.T, sigma))
            from_data = True
    return [p.T for p in scene.profiles], sigmas, from_data


def _step_printer(say: Progress):
    def show(step, chi2):
        finite = chi2[np.isfinite(chi2)]
        if finite.size:
            say(f"  step {step:4d}  best chi2 {finite.min():.6g}")
    return show if say.enabled else None


class Fitter:
    """A joint fit of one scene, compiled once: call it to fit, again to refit new data.

    Compilation depends only on the scene's geometry and free parameters; the data
    and the start can change between calls without recompiling, e.g. for a series
    of radiographs of one sample.

    vary, bounds: override the scene's ``[fit]`` table. accuracy: the model's target
    RMS error in T. n_starts: > 1 adds that many - 1 random starts inside the bounds
    to the best points of the global scan. tolerance: stop when a step moves no
    parameter by more than this many standard errors. progress: print what happens.
    solver: the local least-squares solver, called as ``levenberg_marquardt`` (the
    default) is: ``solver(residual_rows, u (K, n), typical (K, n), *, tolerance,
    max_steps, progress, floor=0.0) -> Solution``, with ``residual_rows`` mapping rows of
    unconstrained coordinates (rows, n) to normalised residuals (rows, N).
    geometry: the sample's shape (``_geometry.Geometry``; default ``geometry_of(scene)``).
    Runs in float64.
    """

    def __init__(self, scene: Scene | str, *, vary=None, bounds=None, accuracy: float | None = None,
                 n_starts: int = 1, max_steps: int = 200, tolerance: float = 1e-2,
                 progress: bool | Progress = False, solver=levenberg_marquardt, geometry: Geometry | None = None):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        if not jax.config.jax_enable_x64:
            raise FwdfitError("fit needs float64: call jax.config.update('jax_enable_x64', True) first")
        if not tolerance > 0:
            raise FwdfitError(f"tolerance must be > 0, got {tolerance}")
        if n_starts < 1:
            raise FwdfitError(f"n_starts must be >= 1, got {n_starts}")
        self.scene, self.n_starts, self.tolerance, self.max_steps = scene, n_starts, tolerance, max_steps
        self.say, self.solver = as_progress(progress), solver
        if scene.fit.per_row:
            raise FwdfitError(f"{scene.path}: fit.per_row: only for fwdfit fit-image (an image profile)")
        self.free = free_parameters(scene, vary, bounds)
        self._data = _data(scene)
        tilt = next((p for p in self.free if p.name == "sample.tilt_deg"), None)
        self.geometry = geometry_of(scene) if geometry is None else geometry
        plan_scene = self.geometry.plan_scene(scene, self.free)
        self.geometry.check_data(scene, self._data[0])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ModelWarning)
            self.model = self.geometry.build_model(plan_scene, accuracy, [p.name for p in self.free],
                                                   None if tilt is None else (tilt.low, tilt.high))
        for caught_warning in caught:  # said as usual, and kept for the result
            warnings.warn(caught_warning.message, caught_warning.category, stacklevel=2)
        self.model_warnings = tuple(str(w.message) for w in caught if issubclass(w.category, ModelWarning))
        self.assemble = assembler(plan_scene, self.free)
        self.say(f"preparing the model: {len(scene.profiles)} profiles in {len(self.model.groups)} programs "
                 "(compiled, or loaded from the cache)")
        with self.say.ticking("compiling"):
            self.predict = Predictor(self.model, self.assemble, len(self.free))
        self.compile_time_s = self.predict.compile_time_s
        self.say(f"model ready in {self.compile_time_s:.1f} s ({self.predict.sources_text()})")
        self._pixel_um = [scene.instruments[p.instrument].pixel_um for p in scene.profiles]

    def objective(self, T=None, sigma=None) -> Objective:
        """The fit's objective on data T and sigma (one array per profile; default: the scene's)."""
        if T is None:
            T, sigma, _ = self._data
        return Objective(self.predict, T, sigma, self._pixel_um)

    def random_starts(self, n: int, around: np.ndarray, seed: int = 0) -> np.ndarray:
        """n random starting points (n, n_free): uniform inside two bounds, else spread
        around ``around`` (20 % beside one bound, five typical steps without bounds)."""
        rng = np.random.default_rng(seed)
        rows = np.empty((n, len(self.free)))
        for j, p in enumerate(self.free):
            if math.isfinite(p.low) and math.isfinite(p.high):
                rows[:, j] = rng.uniform(p.low, p.high, n)
            elif math.isfinite(p.low) or math.isfinite(p.high):
                rows[:, j] = p.from_unit(p.to_unit(around[j]) + rng.normal(0.0, 0.2 * abs(p.to_unit(around[j])) + 1, n))
            else:
                rows[:, j] = around[j] + rng.normal(0.0, 5 * p.step, n)
        return rows

    def _values(self, u: np.ndarray) -> np.ndarray:
        return np.stack([p.from_unit(u[..., j]) for j, p in enumerate(self.free)], axis=-1)

    def _units(self, values: np.ndarray) -> np.ndarray:
        return np.stack([p.to_unit(values[..., j]) for j, p in enumerate(self.free)], axis=-1)

    def __call__(self, T=None, T_err=None, *, start=None, seed: int = 0) -> FitResult:
        """Fit; returns the best of the local starts.

        T, T_err: new data, one array per profile on the scene's pixels (default: the
        scene's; T_err defaults to the scene's, else it is estimated from T).
        start: (n_free,) the user's starting values (default: the scene's), one more
        candidate for the global scan.
        """
        scene, free = self.scene, self.free
        data, sigma, sigma_from_data = self._data if T is None else self._new_data(T, T_err)
        objective = self.objective(data, sigma)
        begin = time.perf_counter()
        evaluations = self.predict.n_evaluations
        guess = self.geometry.estimate(scene, free, data, self.model)
        user = np.array([p.value for p in free]) if start is None else np.asarray(start, float)
        if user.shape != (len(free),):
            raise FwdfitError(f"start must have shape ({len(free)},), got {user.shape}")
        complete = np.all(np.isfinite(user)) and all(p.low < v < p.high for p, v in zip(free, user))

        def solve(u, typical, tolerance, **options):
            return self.solver(lambda rows: objective.residuals(self._values(rows)), u, typical,
                               tolerance=tolerance, max_steps=self.max_steps,
                               progress=_step_printer(self.say), **options)

        pinned = np.array([p.name in guess.pinned_names for p in free])

        def settle(row):
            u = self._units(row[None])
            return self._values(solve(u, np.where(pinned, self._typical(u), 0.0), _SETTLE_TOLERANCE,
                                      floor=_SETTLE_FLOOR).u)[0]

        candidates, n_scanned = global_search(
            free, guess, lambda v: objective.chi2(v, _SEARCH_SMOOTHING_UM), self.geometry.at_tilts,
            _CANDIDATES, extra=user[None] if complete else None, settle=settle if pinned.any() else None)
        self._say(f"global scan: {n_scanned} points; local solver from the best {len(candidates)}", evaluations)
        if self.n_starts > 1:
            candidates = np.concatenate([candidates, self.random_starts(self.n_starts - 1, candidates[0], seed)])
        u = self._units(candidates)
        held = np.array([p.name in guess.held_names for p in free])
        if held.any():
            # Interior interfaces stay where the data put them while the SLDs, which the
            # scan only brackets, settle: else an interface slides into a neighbouring
            # fringe's minimum. Then everything moves.
            u = solve(u, np.where(held, 0.0, self._typical(u)), _SETTLE_TOLERANCE).u
        solution = solve(u, self._typical(u), self.tolerance)
        u = solution.u
        self._say(f"local solver: best chi2 {np.min(solution.chi2):.6g}", evaluations)
        chi2 = solution.chi2
        best = int(np.argmin(np.where(np.isfinite(chi2), chi2, np.inf)))
        if not np.isfinite(chi2[best]):
            raise FwdfitError("the fit diverged (non-finite chi-square from every start)")
        values = self._values(u[best])
        result = self._result(data, sigma, sigma_from_data, values, solution, best, int(solution.steps[best]), guess)
        self._say("uncertainties and quality gate", evaluations)
        wall = time.perf_counter() - begin
        return dataclasses.replace(result, wall_time_s=wall,
                                   n_evaluations=self.predict.n_evaluations - evaluations)

    def _say(self, what: str, evaluations: int) -> None:
        self.say(f"{what} ({self.predict.n_evaluations - evaluations} model evaluations)")

    def _typical(self, u: np.ndarray) -> np.ndarray:
        """Largest solver scale (K, n), in u: one typical physical step (at least one unit),
        so that a value converging onto a bound, deep in its transform, stops there."""
        slope = np.stack([p.value_per_unit(u[:, j]) for j, p in enumerate(self.free)], axis=1)
        steps = np.array([p.step for p in self.free])
        return np.maximum(steps / np.maximum(np.abs(slope), _TINY_SLOPE), 1.0)

    def _new_data(self, T, T_err):
        scene = self.scene
        if len(T) != len(scene.profiles) or any(np.shape(t) != p.x_um.shape for t, p in zip(T, scene.profiles)):
            raise FwdfitError("T must hold one array per profile, on the profile's pixels")
        errs = T_err if T_err is not None else [None] * len(T)
        profiles = tuple(dataclasses.replace(p, T=np.array(t, dtype=float),
                                             T_err=p.T_err if e is None else np.array(e, dtype=float))
                         for p, t, e in zip(scene.profiles, T, errs))
        return _data(dataclasses.replace(scene, profiles=profiles))

    def _result(self, data, sigma, sigma_from_data, values, solution, best, steps, guess) -> FitResult:
        scene, free = self.scene, self.free
        data_all, sigma_all = np.concatenate(data), np.concatenate(sigma)
        dof = len(data_all) - len(free)
        # Central differences at the optimum, a tenth of a standard error wide (from the
        # solver's last forward-difference Jacobian, in physical units).
        slope = np.array([p.value_per_unit(u) for p, u in zip(free, self._units(values))])
        rough = covariance(solution.jacobian[best] / np.where(slope == 0, np.inf, slope), 1.0, dof, False)
        steps_phys = _ERROR_STEP * np.sqrt(np.clip(np.diag(rough), 0, None))
        steps_phys = np.where(steps_phys > 0, steps_phys, 1e-6 * np.array([p.step for p in free]))
        J_model, J_att = central_differences(self.predict, values, steps_phys)
        jacobian = J_model / sigma_all[:, None]
        (T_model,), (T_att,) = self.predict(values[None])
        z = (data_all - T_model) / sigma_all
        chi2 = float(np.sum(z * z))
        cov = covariance(jacobian, chi2, dof, sigma_from_data)
        errors, correlation = errors_and_correlation(cov)
        att_err = band(J_att, cov)
        notes = [f"profile {p.name!r} has no T_err: its noise ({s[0]:.3g}) was estimated from the data "
                 f'(errors = "{ERRORS_ESTIMATE}" asks for that on purpose)'
                 for p, s in zip(scene.profiles, sigma) if sigma_from_data and p.T_err is None
                 and p.errors != ERRORS_ESTIMATE]
        for p, column, value, error in zip(free, jacobian.T, values, errors):
            if not np.any(column) or error > 10 * max(abs(value), p.step):
                notes.append(f"{p.name} is not constrained by the data (error {error:.3g})")
            else:
                notes.extend(_at_bound(p, value, error))
        converged = bool(solution.converged[best])
        if not converged:
            notes.append("the solver did not converge: the values are the last accepted step")
        fitted = _fitted_scene(scene, free, values)
        quality = self._quality(data, sigma, T_model, fitted)
        if not quality.passed:
            notes.append(quality.summary())
        for note in notes:
            warnings.warn(note, stacklevel=3)
        profiles, offset = [], 0
        for p, t, s in zip(scene.profiles, data, sigma):
            part = slice(offset, offset + len(p.x_um))
            m, a = T_model[part], T_att[part]
            profiles.append(FittedProfile(p.name, p.x_um, t, s, m, a, att_err[part], t - (m - a)))
            offset += len(p.x_um)
        message = "converged" if converged else "did not converge within max_steps (see the step count)"
        return FitResult(tuple(p.name for p in free), values, errors, correlation, chi2, dof, converged,
                         message, steps, self.compile_time_s, 0.0, tuple(profiles), tuple(notes),
                         sigma_from_data, fitted, solution.chi2, quality,
                         dict(guess.values), 0, self.model_warnings)

    def _quality(self, data, sigma, T_model, fitted: Scene) -> Quality:
        """The quality gate on the unsmoothed residuals, with edge regions at every interface
        of the fitted scene."""
        interfaces, halves, z, offset = [], [], [], 0
        for i, p in enumerate(fitted.profiles):
            faces, half = self.geometry.interfaces(fitted, p)
            interfaces.append(faces)
            halves.append(half)
            n = len(p.x_um)
            z.append((data[i] - T_model[offset:offset + n]) / sigma[i])
            offset += n
        return assess([p.name for p in fitted.profiles], [p.x_um for p in fitted.profiles], z,
                      interfaces, halves, len(self.free))


def fit(scene: Scene | str, *, vary=None, bounds=None, accuracy: float | None = None,
        n_starts: int = 1, seed: int = 0, max_steps: int = 200, tolerance: float = 1e-2,
        progress: bool = False, solver=levenberg_marquardt) -> FitResult:
    """Fit the free parameters of a scene to all of its measured profiles at once.

    vary, bounds: override the scene's ``[fit]`` table. accuracy: the model's target
    RMS error in T. n_starts: > 1 adds random starts (drawn with ``seed``) to the
    global scan's best points. tolerance: stop when a step moves no parameter by more
    than this many standard errors. progress: print what happens. solver: the local
    least-squares solver (see ``Fitter``). Runs in float64. To refit new data without
    recompiling, use ``Fitter``.
    """
    fitter = Fitter(scene, vary=vary, bounds=bounds, accuracy=accuracy, n_starts=n_starts,
                    max_steps=max_steps, tolerance=tolerance, progress=progress, solver=solver)
    return fitter(seed=seed)


def _fitted_scene(scene: Scene, free: tuple[FreeParameter, ...], values) -> Scene:
    """The scene with its free parameters set to the fitted values."""
    layers = list(scene.sample.layers)
    profiles = list(scene.profiles)
    sample_updates = {}
    for p, value in zip(free, values):
        key, index = p.target
        if key in LAYER_FIELDS:
            for i in index:
                layers[i] = dataclasses.replace(layers[i], **{key: float(value)})
        elif registry.BY_KEY[key].part == "profiles":
            profiles[index[0]] = dataclasses.replace(profiles[index[0]], **{key: float(value)})
        else:
            sample_updates[key] = float(value)
    sample = dataclasses.replace(scene.sample, layers=tuple(layers), **sample_updates)
    return dataclasses.replace(scene, sample=sample, profiles=tuple(profiles))


def _at_bound(p, value: float, error: float) -> list[str]:
    """A note when the fit pinned ``p`` at one of its bounds (within a tenth of its error): the
    data pull it beyond, so its value and error describe the bound, not the data."""
    for side, bound in (("lower", p.low), ("upper", p.high)):
        if math.isfinite(bound) and abs(value - bound) < 0.1 * error:
            return [f"{p.name} = {value:.4g} is pinned at its {side} bound {bound:g}: the data pull it beyond; "
                    "fix it, or check the scene (a material's mu_per_m_per_A, a start)"]
    return []
