"""Joint least-squares fit of one sample model to every profile of a scene.

The objective is the vector of weighted residuals (norm * T + background - T_meas)
/ sigma over all profiles, a pure function of the free parameters' unconstrained
coordinates; optimistix' Levenberg-Marquardt minimises it. Uncertainties come from
the exact Jacobian at the optimum (in physical units, so the bound transforms do
not distort them) and are propagated to a 1-sigma band on T_att.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._errors import FwdfitError
from ._parameters import FreeParameter, assembler, free_parameters
from ._plan import build_model
from ._scene import Scene, load_scene

_NOISE_FROM_NEIGHBOURS = 1.0 / (0.6745 * np.sqrt(2.0))  # MAD of differences -> sigma
_SMOOTHING_SCHEDULE_UM = (25.0, 8.0, 3.0, 0.0)  # Gaussian sigma of each stage, coarse to fine
_COARSE_TOLERANCE = 0.3  # standard errors: the coarse stages only need to reach the final basin
_TINY_CURVATURE = 1e-12
_TINY_SLOPE = 1e-12  # d value / d u below this counts as zero (a value deep in a bound's transform)
_UNPIN_FRACTION = 0.1  # coarse stages restart a value on a bound this fraction of the box inside
_DIFFERENCE_STEP = 1e-3  # forward-difference step, in solver units (typical steps for the first Jacobian)


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
    """Fitted values with 1-sigma errors and correlations, in the units of the scene keys."""

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
    wall_time_s: float
    profiles: tuple[FittedProfile, ...]
    warnings: tuple[str, ...]
    sigma_from_data: bool
    scene: Scene
    chi2_per_start: np.ndarray  # (n_starts,) final chi-square from every start (inf if it diverged)

    @property
    def chi2_reduced(self) -> float:
        return self.chi2 / max(self.dof, 1)

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


def estimate_sigma(T: np.ndarray) -> float:
    """Noise of a profile from the scatter of neighbouring-pixel differences (robust)."""
    differences = np.diff(T)
    return float(np.median(np.abs(differences - np.median(differences))) * _NOISE_FROM_NEIGHBOURS)


def _data(scene: Scene):
    missing = [p.name for p in scene.profiles if p.T is None]
    if missing:
        raise FwdfitError(f"{scene.path}: profile {missing[0]!r} has no measured data (file = ...)")
    sigmas, from_data = [], False
    for p in scene.profiles:
        if p.T_err is not None:
            sigmas.append(p.T_err)
        else:
            sigma = estimate_sigma(p.T)
            if not sigma > 0:
                raise FwdfitError(f"{scene.path}: profile {p.name!r}: no T_err and no noise to estimate it from")
            sigmas.append(np.full_like(p.T, sigma))
            from_data = True
    return [p.T for p in scene.profiles], sigmas, from_data


class Objective(eqx.Module):
    """Weighted residuals over all profiles as a function of the free physical values.

    ``smoothing`` (odd length) is convolved with model and data before they are
    compared: a wide Gaussian for the coarse stage of a fit, a unit impulse after.
    """

    model: eqx.Module
    assemble: eqx.Module
    T: tuple
    sigma: tuple
    smoothing: jax.Array

    def with_smoothing(self, width_px: float) -> "Objective":
        half = (self.smoothing.shape[0] - 1) // 2
        offsets = np.arange(-half, half + 1)
        kernel = (offsets == 0).astype(float) if width_px == 0 else np.exp(-0.5 * (offsets / width_px) ** 2)
        return eqx.tree_at(lambda o: o.smoothing, self, jnp.asarray(kernel / kernel.sum()))

    def _smooth(self, values):
        half = (self.smoothing.shape[0] - 1) // 2
        return jnp.convolve(jnp.pad(values, half, mode="edge"), self.smoothing, mode="valid")

    def predict(self, values):
        """(T_model, T_att) per profile, with each profile's norm and background applied."""
        params, norm, background = self.assemble(values)
        T, T_att = self.model(params)
        return ([n * t + b for t, n, b in zip(T, norm, background)],
                [n * t + b for t, n, b in zip(T_att, norm, background)])

    def residuals(self, values):
        T_model, _ = self.predict(values)
        return jnp.concatenate([(self._smooth(m) - self._smooth(t)) / s
                                for m, t, s in zip(T_model, self.T, self.sigma)])


def _values_of(free, u):
    """Physical values (n_free,) from unconstrained coordinates u (n_free,)."""
    return jnp.stack([p.from_unit(u[i]) for i, p in enumerate(free)])


def _solve(objective: Objective, u0, tolerance, final, free, max_steps: int, verbose):
    """Solve from one start u0 (n_free,); returns (u, chi2, converged, steps) at the end.

    The solver works in w = u / scale, with scale the standard errors of u from the
    Jacobian at the start, at most one typical step for parameters the data hardly
    constrain, which then move no faster than the rest: the damping treats all
    parameters alike, and the solver stops when the last step moved no parameter by
    more than ``tolerance`` standard errors and no residual by more than
    ``tolerance`` sigma. The typical step is u's unit in the coarse stages (uniform
    moves towards the final basin) and one typical physical step in the ``final``
    one (a boolean array): a value that converges onto a bound, deep in its
    transform, then stops once its physical steps are small, rather than walking
    u out towards infinity. It returns u, not values, so that the next stage starts
    exactly there (a value at its bound has no finite u to convert back to).

    The solver's Jacobians are forward differences (one model evaluation per free
    parameter): on the CPU they cost a fifth of the forward-mode Jacobian, whose
    tangents break XLA's fusion of the kernels; the errors use the exact one.
    """

    def plain(u):
        return objective.residuals(_values_of(free, u))

    def evaluate(u, step):
        """Residuals at u and their forward-difference Jacobian (n_residual, n_free).

        One mapped evaluation serves both (the first row is u itself), so the model
        is compiled once.
        """
        shifts = jnp.concatenate([jnp.zeros((1, u.shape[0]), u.dtype), jnp.diag(step)])
        shifted = jax.lax.map(lambda s: plain(u + s), shifts)
        r = shifted[0]
        return r, ((shifted[1:] - r[None, :]) / step[:, None]).T

    _, J0 = evaluate(u0, jnp.full_like(u0, _DIFFERENCE_STEP))
    curvature = J0.T @ J0 + _TINY_CURVATURE * jnp.eye(u0.shape[0], dtype=u0.dtype)
    # One typical physical step, in u: 1 unless the value sits deep in a bound's transform.
    _, value_per_u = jax.jvp(lambda u: _values_of(free, u), (u0,), (jnp.ones_like(u0),))
    physical = jnp.asarray([p.step for p in free], u0.dtype) / jnp.maximum(jnp.abs(value_per_u), _TINY_SLOPE)
    typical = jnp.where(final, jnp.maximum(physical, 1.0), 1.0)
    scale = jnp.minimum(jnp.sqrt(jnp.diag(jnp.linalg.inv(curvature))), typical)

    # Gauss-Newton needs the Jacobian at every trial point: give it with the residuals.
    @jax.custom_jvp
    def residuals(w):
        return plain(w * scale)

    @residuals.defjvp
    def _residuals_jvp(primals, tangents):
        r, J = evaluate(primals[0] * scale, _DIFFERENCE_STEP * scale)
        return r, (J * scale) @ tangents[0]

    solver = optx.LevenbergMarquardt(rtol=0.0, atol=tolerance, verbose=verbose)
    solution = optx.least_squares(lambda w, _: residuals(w), solver, u0 / scale,
                                  max_steps=max_steps, throw=False)
    u = solution.value * scale
    # The residuals at the solution, kept in the solver's state (no further model evaluation).
    chi2 = jnp.sum(solution.state.f_info.residual ** 2)
    return u, chi2, solution.result == optx.RESULTS.successful, solution.stats["num_steps"]


def _progress(**info) -> None:
    def show(step, loss):
        step, loss = np.ravel(step)[0], np.ravel(loss)[0]
        print(f"  step {int(step):4d}  chi2 {2 * float(loss):.6g}", flush=True)

    jax.debug.callback(show, info["num_steps"][1], info["loss_last_accepted_step"][1])


class Fitter:
    """A joint fit of one scene, compiled once: call it to fit, again to refit new data.

    Compilation (tens of seconds) depends only on the scene's geometry, free
    parameters and number of starts; the data, the starting values and the
    tolerance can change between calls without recompiling, e.g. for a series of
    radiographs of one sample.

    vary, bounds: override the scene's ``[fit]`` table. accuracy: the model's target
    RMS error in T. n_starts: > 1 runs that many starting points (the scene's values
    and random ones inside the bounds; one after another on a CPU, batched with vmap
    on an accelerator) and keeps the best.
    tolerance: stop when a step moves no parameter by more than this many standard
    errors. progress: print step and chi-square while fitting. Runs in float64.
    """

    def __init__(self, scene: Scene | str, *, vary=None, bounds=None, accuracy: float | None = None,
                 n_starts: int = 1, max_steps: int = 200, tolerance: float = 1e-2,
                 progress: bool = False):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        if not jax.config.jax_enable_x64:
            raise FwdfitError("fit needs float64: call jax.config.update('jax_enable_x64', True) first")
        if not tolerance > 0:
            raise FwdfitError(f"tolerance must be > 0, got {tolerance}")
        self.scene, self.n_starts, self.tolerance, self.progress = scene, n_starts, tolerance, progress
        self.free = free_parameters(scene, vary, bounds)
        T, sigma, self.sigma_from_data = _data(scene)
        tilt = next((p for p in self.free if p.name == "sample.tilt_deg"), None)
        model = build_model(scene, accuracy, free=[p.name for p in self.free],
                            tilt_range_deg=None if tilt is None else (tilt.low, tilt.high))
        self.pixel_um = min(scene.instruments[p.instrument].pixel_um for p in scene.profiles)
        coarse_px = _SMOOTHING_SCHEDULE_UM[0] / self.pixel_um
        self.objective = Objective(model, assembler(scene, self.free), tuple(map(jnp.asarray, T)),
                                   tuple(map(jnp.asarray, sigma)), jnp.zeros(2 * math.ceil(3 * coarse_px) + 1))
        free = self.free
        verbose = _progress if progress and n_starts == 1 else False
        # The objective is an argument, not a closure: constants would be folded at compile time.
        # The starts run one after another on a CPU, where a batch gains no parallelism and
        # every start would wait for the slowest; on an accelerator they run batched (vmap).
        batch = 1 if jax.default_backend() == "cpu" else n_starts
        runner = eqx.filter_jit(
            lambda o, u0s, tol, final: jax.lax.map(
                lambda u0: _solve(o, u0, tol, final, free, max_steps, verbose), u0s, batch_size=batch))
        start_time = time.perf_counter()
        lowered = runner.lower(self.objective, jnp.zeros((n_starts, len(free))), jnp.asarray(tolerance),
                               jnp.asarray(True))
        # XLA compiles the solver on a second thread while this one compiles the exact
        # derivative that gives the errors at the optimum (one call compiles it).
        values = jnp.asarray([p.value for p in free])
        with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
            solver = pool.submit(lowered.compile)
            jax.block_until_ready(_directional(self.objective, values, jnp.zeros_like(values)))
            self._compiled = solver.result()
        self.compile_time_s = time.perf_counter() - start_time

    def starts(self, seed: int = 0) -> np.ndarray:
        """Starting values (n_starts, n_free) in physical units: the scene's, then random ones."""
        u0 = np.array([float(p.to_unit(p.value)) for p in self.free])
        rng = np.random.default_rng(seed)
        rows = [u0]
        for _ in range(self.n_starts - 1):
            u = []
            for p, centre in zip(self.free, u0):
                if np.isfinite(p.low) and np.isfinite(p.high):
                    u.append(rng.normal(centre, 1.0))  # spread over the box
                elif np.isfinite(p.low) or np.isfinite(p.high):
                    u.append(centre + rng.normal(0.0, 0.2))  # ~20 % relative
                else:
                    u.append(centre + rng.normal(0.0, 5.0))  # ~5 typical steps
            rows.append(np.array(u))
        return np.array([[float(p.from_unit(v)) for p, v in zip(self.free, row)] for row in rows])

    def __call__(self, T=None, T_err=None, *, starts=None, seed: int = 0) -> FitResult:
        """Fit; returns the best of the starts.

        T, T_err: new data, one array per profile on the scene's pixels (default: the
        scene's; T_err defaults to the scene's, else it is estimated from T).
        starts: (n_starts, n_free) physical starting values inside the bounds
        (default: ``self.starts(seed)``).
        """
        scene, objective, sigma_from_data = self.scene, self.objective, self.sigma_from_data
        if T is not None:
            profiles = []
            for p, t, e in zip(scene.profiles, T, T_err if T_err is not None else [None] * len(T)):
                profiles.append(dataclasses.replace(p, T=np.asarray(t, dtype=float).copy(),
                                                    T_err=p.T_err if e is None else np.asarray(e, dtype=float).copy()))
            if len(profiles) != len(scene.profiles) or any(
                    q.T.shape != p.x_um.shape for q, p in zip(profiles, scene.profiles)):
                raise FwdfitError("T must hold one array per profile, on the profile's pixels")
            scene = dataclasses.replace(scene, profiles=tuple(profiles))
            data, sigma, sigma_from_data = _data(scene)
            objective = eqx.tree_at(lambda o: (o.T, o.sigma), objective,
                                    (tuple(map(jnp.asarray, data)), tuple(map(jnp.asarray, sigma))))
        starts = self.starts(seed) if starts is None else np.asarray(starts, dtype=float)
        if starts.shape != (self.n_starts, len(self.free)):
            raise FwdfitError(f"starts must have shape ({self.n_starts}, {len(self.free)}), got {starts.shape}")
        for p, column in zip(self.free, starts.T):
            if not np.all((column > p.low) & (column < p.high)):
                raise FwdfitError(f"starts: {p.name} must lie inside its bounds ({p.low:g}, {p.high:g})")
        u = jnp.asarray([[float(p.to_unit(v)) for p, v in zip(self.free, row)] for row in starts])
        start_time = time.perf_counter()
        # Coarse to fine: model and data smoothed first (a wide basin in which the refraction
        # peaks cancel out), then the full-resolution fit from there. The coarse stages only
        # need to land in the final basin.
        total_steps = 0
        for stage, smoothing_um in enumerate(_SMOOTHING_SCHEDULE_UM):
            final = stage == len(_SMOOTHING_SCHEDULE_UM) - 1
            if self.progress:
                print(f"stage {stage + 1}/{len(_SMOOTHING_SCHEDULE_UM)}: model and data smoothed "
                      f"by a {smoothing_um:g} µm Gaussian", flush=True)
            tolerance = self.tolerance if final else max(self.tolerance, _COARSE_TOLERANCE)
            if 0 < stage and not final:
                # A coarse stage that ended on a bound had too little information to hold it
                # there (the smoothing hides weak interfaces): the finer one starts inside.
                u = jnp.stack([p.inside(u[:, i], _UNPIN_FRACTION) for i, p in enumerate(self.free)], axis=1)
            u, chi2, success, steps = self._compiled(objective.with_smoothing(smoothing_um / self.pixel_um),
                                                     u, jnp.asarray(tolerance), jnp.asarray(final))
            total_steps += np.asarray(steps)
        values = jax.vmap(lambda x: _values_of(self.free, x))(u)
        values, chi2, success = jax.block_until_ready((values, chi2, success))
        wall_time = time.perf_counter() - start_time
        finite = np.isfinite(np.asarray(chi2)) & np.all(np.isfinite(np.asarray(values)), axis=1)
        if not finite.any():
            raise FwdfitError("the fit diverged (non-finite chi-square from every start)")
        best = int(np.argmin(np.where(finite, np.asarray(chi2), np.inf)))
        return _result(scene, self.free, objective, np.asarray(values[best]),
                       np.where(finite, np.asarray(chi2), np.inf), best, bool(success[best]),
                       int(total_steps[best]), self.compile_time_s, wall_time, sigma_from_data)


def fit(scene: Scene | str, *, vary=None, bounds=None, accuracy: float | None = None,
        n_starts: int = 1, seed: int = 0, max_steps: int = 200, tolerance: float = 1e-2,
        progress: bool = False) -> FitResult:
    """Fit the free parameters of a scene to all of its measured profiles at once.

    vary, bounds: override the scene's ``[fit]`` table. accuracy: the model's target
    RMS error in T. n_starts: > 1 runs that many starting points (the scene's values
    and random ones inside the bounds, drawn with ``seed``; see ``Fitter``) and keeps
    the best. tolerance: stop when a step moves no parameter by more than
    this many standard errors. progress: print step and chi-square while fitting.
    Runs in float64. To refit new data without recompiling, use ``Fitter``.
    """
    fitter = Fitter(scene, vary=vary, bounds=bounds, accuracy=accuracy, n_starts=n_starts,
                    max_steps=max_steps, tolerance=tolerance, progress=progress)
    return fitter(seed=seed)


@eqx.filter_jit
def _directional(objective: Objective, values, tangent):
    """Residuals and T_att, their exact derivatives along ``tangent``, and the model profiles."""

    def outputs(v):
        T_model, T_att = objective.predict(v)
        residuals = jnp.concatenate([(m - t) / s for m, t, s in zip(T_model, objective.T, objective.sigma)])
        return (residuals, jnp.concatenate(T_att)), (T_model, T_att)

    _, derivatives, profiles = jax.jvp(outputs, (values,), (tangent,), has_aux=True)
    return derivatives, profiles


def _linearise(objective: Objective, values):
    """Residual Jacobian, T_att Jacobian and model profiles at ``values`` (exact, forward mode).

    One tangent per call rather than ``jacfwd``: the single-tangent derivative
    compiles in about half the time, and its calls cost little next to a fit.
    """
    columns = [_directional(objective, values, tangent) for tangent in jnp.eye(values.shape[0], dtype=values.dtype)]
    jacobian, att_jacobian = (jnp.stack(c, axis=1) for c in zip(*(derivatives for derivatives, _ in columns)))
    return jacobian, att_jacobian, columns[0][1]


def _result(scene, free, objective: Objective, values, chi2_per_start, best, converged, steps,
            compile_time, wall_time, sigma_from_data) -> FitResult:
    chi2 = float(chi2_per_start[best])
    jacobian, att_jacobian, (T_model, T_att) = _linearise(objective, jnp.asarray(values))
    jacobian, att_jacobian = np.asarray(jacobian), np.asarray(att_jacobian)
    n_data = jacobian.shape[0]
    dof = n_data - len(free)
    notes = []
    curvature = jacobian.T @ jacobian
    covariance = np.linalg.pinv(curvature, rcond=1e-12, hermitian=True)
    if sigma_from_data:
        covariance = covariance * chi2 / max(dof, 1)
    errors = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    outer = np.outer(errors, errors)
    correlation = np.divide(covariance, outer, out=np.zeros_like(covariance), where=outer > 0)
    for p, column, value, error in zip(free, jacobian.T, values, errors):
        if not np.any(column) or error > 10 * max(abs(value), p.step):
            notes.append(f"{p.name} is not constrained by the data (error {error:.3g})")
    att_err = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", att_jacobian, covariance, att_jacobian), 0, None))
    profiles, offset = [], 0
    for p, data, s, m, a in zip(scene.profiles, objective.T, objective.sigma, T_model, T_att):
        n = len(p.x_um)
        m, a = np.asarray(m), np.asarray(a)
        profiles.append(FittedProfile(p.name, p.x_um, np.asarray(data), np.asarray(s), m, a,
                                      att_err[offset:offset + n], np.asarray(data) - (m - a)))
        offset += n
    message = "converged" if converged else "did not converge within max_steps (see the step count)"
    if not converged:
        notes.append("the solver did not converge: the values are the last accepted step")
    for note in notes:
        warnings.warn(note, stacklevel=3)
    fitted = _fitted_scene(scene, free, values)
    return FitResult(tuple(p.name for p in free), values, errors, correlation, chi2, dof, converged,
                     message, steps, compile_time, wall_time, tuple(profiles), tuple(notes),
                     sigma_from_data, fitted, chi2_per_start)


def _fitted_scene(scene: Scene, free: tuple[FreeParameter, ...], values) -> Scene:
    """The scene with its free parameters set to the fitted values."""
    layers = list(scene.sample.layers)
    profiles = list(scene.profiles)
    sample_updates = {}
    for p, value in zip(free, values):
        key, index = p.target
        if key in ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A"):
            for i in index:
                layers[i] = dataclasses.replace(layers[i], **{key: float(value)})
        elif key in ("distance_mm", "shift_um", "norm", "background"):
            profiles[index[0]] = dataclasses.replace(profiles[index[0]], **{key: float(value)})
        else:
            sample_updates[key] = float(value)
    sample = dataclasses.replace(scene.sample, layers=tuple(layers), **sample_updates)
    return dataclasses.replace(scene, sample=sample, profiles=tuple(profiles))
