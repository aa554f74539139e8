"""Joint least-squares fit of one sample model to every profile of a scene.

The objective is the vector of weighted residuals (norm * T + background - T_meas)
/ sigma over all profiles, a pure function of the free parameters' unconstrained
coordinates; optimistix' Levenberg-Marquardt minimises it. Uncertainties come from
the exact Jacobian at the optimum (in physical units, so the bound transforms do
not distort them) and are propagated to a 1-sigma band on T_att.
"""

from __future__ import annotations

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


def _solve(objective: Objective, u0, free, solver, max_steps: int):
    """Solve from one start u0 (n_free,); returns (values, chi2, converged, steps)."""

    def values_of(u):
        return jnp.stack([p.from_unit(u[i]) for i, p in enumerate(free)])

    def plain(u):
        return objective.residuals(values_of(u))

    # Gauss-Newton needs the Jacobian at every trial point: compute it with the
    # residuals in one forward-mode pass, so the model is traced once for both.
    @jax.custom_jvp
    def residuals(u):
        return plain(u)

    @residuals.defjvp
    def _residuals_jvp(primals, tangents):
        def twice(u):
            r = plain(u)
            return r, r

        jacobian, value = jax.jacfwd(twice, has_aux=True)(primals[0])
        return value, jacobian @ tangents[0]

    solution = optx.least_squares(lambda u, _: residuals(u), solver, u0, max_steps=max_steps,
                                  throw=False)
    chi2 = jnp.sum(solution.state.f_info.residual ** 2)  # at the last accepted step
    return (values_of(solution.value), chi2, solution.result == optx.RESULTS.successful,
            solution.stats["num_steps"])


def _progress(**info) -> None:
    def show(step, loss):
        step, loss = np.ravel(step)[0], np.ravel(loss)[0]
        print(f"  step {int(step):4d}  chi2 {2 * float(loss):.6g}", flush=True)

    jax.debug.callback(show, info["num_steps"][1], info["loss_last_accepted_step"][1])


def _starts(free, n_starts: int, seed: int) -> np.ndarray:
    """Starting points (n_starts, n_free) in unconstrained units; the first is the scene's."""
    u0 = np.array([float(p.to_unit(p.value)) for p in free])
    rng = np.random.default_rng(seed)
    starts = [u0]
    for _ in range(n_starts - 1):
        u = []
        for p, centre in zip(free, u0):
            if np.isfinite(p.low) and np.isfinite(p.high):
                u.append(rng.normal(centre, 1.0))  # spread over the box
            elif np.isfinite(p.low) or np.isfinite(p.high):
                u.append(centre + rng.normal(0.0, 0.2))  # ~20 % relative
            else:
                u.append(centre + rng.normal(0.0, 5.0))  # ~5 typical steps
        starts.append(np.array(u))
    return np.stack(starts)


def fit(scene: Scene | str, *, vary=None, bounds=None, accuracy: float | None = None,
        n_starts: int = 1, seed: int = 0, max_steps: int = 200, rtol: float = 1e-5,
        atol: float = 1e-5, progress: bool = False) -> FitResult:
    """Fit the free parameters of a scene to all of its measured profiles at once.

    vary, bounds: override the scene's ``[fit]`` table. accuracy: the model's target
    RMS error in T. n_starts: > 1 runs that many starting points batched with vmap
    (the scene's values and random ones inside the bounds) and keeps the best.
    progress: print step and chi-square while fitting. Runs in float64.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    if not jax.config.jax_enable_x64:
        raise FwdfitError("fit needs float64: call jax.config.update('jax_enable_x64', True) first")
    free = free_parameters(scene, vary, bounds)
    T, sigma, sigma_from_data = _data(scene)
    model = build_model(scene, accuracy, free=[p.name for p in free])
    pixel_um = min(scene.instruments[p.instrument].pixel_um for p in scene.profiles)
    coarse_px = _SMOOTHING_SCHEDULE_UM[0] / pixel_um
    objective = Objective(model, assembler(scene, free), tuple(map(jnp.asarray, T)),
                          tuple(map(jnp.asarray, sigma)), jnp.zeros(2 * math.ceil(3 * coarse_px) + 1))
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol,
                                     verbose=_progress if progress and n_starts == 1 else False)
    starts = jnp.asarray(_starts(free, n_starts, seed))
    # The objective is an argument, not a closure: constants would be folded at compile time.
    runner = eqx.filter_jit(jax.vmap(lambda o, u0: _solve(o, u0, free, solver, max_steps),
                                     in_axes=(None, 0)))
    start_time = time.perf_counter()
    compiled = runner.lower(objective, starts).compile()
    compile_time = time.perf_counter() - start_time
    start_time = time.perf_counter()
    # Coarse to fine: model and data smoothed first (a wide basin in which the refraction
    # peaks cancel out), then the full-resolution fit from there.
    total_steps = 0
    for stage, smoothing_um in enumerate(_SMOOTHING_SCHEDULE_UM):
        if progress:
            print(f"stage {stage + 1}/{len(_SMOOTHING_SCHEDULE_UM)}: model and data smoothed "
                  f"by a {smoothing_um:g} µm Gaussian", flush=True)
        values, chi2, success, steps = compiled(objective.with_smoothing(smoothing_um / pixel_um), starts)
        total_steps += np.asarray(steps)
        starts = jnp.stack([jnp.stack([p.to_unit(v[i]) for i, p in enumerate(free)]) for v in values])
    values, chi2, success, steps = jax.block_until_ready((values, chi2, success, steps))
    wall_time = time.perf_counter() - start_time
    finite = np.isfinite(np.asarray(chi2)) & np.all(np.isfinite(np.asarray(values)), axis=1)
    if not finite.any():
        raise FwdfitError("the fit diverged (non-finite chi-square from every start)")
    best = int(np.argmin(np.where(finite, np.asarray(chi2), np.inf)))
    return _result(scene, free, objective, np.asarray(values[best]), float(chi2[best]),
                   bool(success[best]), int(total_steps[best]), compile_time, wall_time, sigma_from_data)


@eqx.filter_jit
def _linearise(objective: Objective, values):
    """Residual Jacobian, model profiles and T_att Jacobian at ``values``, in one pass."""

    def outputs(v):
        T_model, T_att = objective.predict(v)
        residuals = jnp.concatenate([(m - t) / s for m, t, s in zip(T_model, objective.T, objective.sigma)])
        return (residuals, jnp.concatenate(T_att)), (T_model, T_att)

    (jacobian, att_jacobian), profiles = jax.jacfwd(outputs, has_aux=True)(values)
    return jacobian, att_jacobian, profiles


def _result(scene, free, objective: Objective, values, chi2, converged, steps, compile_time,
            wall_time, sigma_from_data) -> FitResult:
    values_j = jnp.asarray(values)
    jacobian, att_jacobian, (T_model, T_att) = _linearise(objective, values_j)
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
                     sigma_from_data, fitted)


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
