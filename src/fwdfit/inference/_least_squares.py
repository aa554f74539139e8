"""Levenberg-Marquardt for many independent least-squares problems at once (NumPy).

The solver's logic is a few small matrix operations per step and runs on the host;
the model evaluations it asks for (trial points, forward-difference Jacobians) are
gathered across all problems into one call of ``residuals``, which evaluates a
compiled model on rows of parameter vectors (``_predict``). One compiled model thus
serves every start, stage and step of a fit.

A difference Jacobian costs one evaluation per parameter, so between them the
Jacobian follows Broyden's rank-one updates from the steps taken (MINPACK's
hybrid methods do the same); it is recomputed by differences every few steps, when
a step fails with an updated Jacobian, and before a problem may stop.

Coordinates: the solver works in w = u / scale, with u the unconstrained
coordinates (``_parameters``) and scale the standard errors of u at the start,
capped by a typical step: the damping then treats all parameters alike, and the
tolerance reads in standard errors.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

_TINY_CURVATURE = 1e-12
_INITIAL_DAMPING = 1e-3  # times the largest curvature
_MAX_DAMPING = 1e14  # a problem whose damping exceeds this cannot improve: it stops
_MIN_GAIN_RATIO = 1e-4  # a step is accepted when it achieves this share of the predicted decrease
_GRACE_STEPS = 5  # steps every problem takes before it can be abandoned ...
_HOPELESS = 1.5  # ... for a chi-square this many times the best
_BROYDEN_STEPS = 4  # accepted steps with updated Jacobians before differences are taken again


@dataclasses.dataclass(frozen=True)
class Solution:
    """Where each problem ended: u (K, n), chi2 (K,), residuals (K, N), the solver's last
    Jacobian with respect to u (K, N, n; differences, perhaps Broyden-updated since),
    converged (K,) (False too for a problem stopped because a better one came within a
    standard error of it, or was far better after a few steps), steps (K,)."""

    u: np.ndarray
    chi2: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    converged: np.ndarray
    steps: np.ndarray


def _jacobians(residuals, u, r, scale, difference_step, problems):
    """Forward-difference Jacobians (K, N, n) of residuals at u (K, n) with values r (K, N);
    problems (K,): the problem of each row."""
    K, n = u.shape
    steps = difference_step * scale  # (K, n)
    moving = np.flatnonzero(np.any(steps != 0, axis=0))  # held coordinates (scale 0) cost nothing
    shifted = u[:, None, :] + np.eye(n)[moving][None] * steps[:, moving, None]  # (K, m, n)
    rows = residuals(shifted.reshape(K * len(moving), n), np.repeat(problems, len(moving)))
    J = np.zeros((K, r.shape[1], n))
    J[:, :, moving] = ((rows.reshape(K, len(moving), -1) - r[:, None, :]) / steps[:, moving, None]).transpose(0, 2, 1)
    return np.where(np.isfinite(J), J, 0.0)


def _abandon(chi2, steps, active) -> None:
    """Stop every problem that, after _GRACE_STEPS steps, still has a chi-square more than
    _HOPELESS times the best: it is in another basin and would only cost evaluations."""
    best = np.min(chi2)
    active &= ~((steps >= _GRACE_STEPS) & (chi2 > _HOPELESS * best))


def _merge(u, chi2, scale, active) -> None:
    """Stop every problem that has come within one standard error (in every coordinate)
    of one with a lower chi-square: both would end in the same place."""
    idx = np.flatnonzero(active)
    order = idx[np.argsort(chi2[idx])]
    for rank, i in enumerate(order):
        if not active[i]:
            continue
        for j in order[rank + 1:]:
            if active[j] and np.all(np.abs(u[j] - u[i]) <= scale[i]):
                active[j] = False


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray], u0: np.ndarray,
                        typical: np.ndarray, *, tolerance: float, max_steps: int,
                        floor: float = 0.0, difference_step: float = 1e-3, independent: bool = False,
                        progress: Callable[[int, np.ndarray], None] | None = None) -> Solution:
    """Minimise sum(residuals(u)**2) from each row of u0 (K, n).

    residuals: rows of u (m, n) -> residual rows (m, N), non-finite where the model fails.
    independent: the K rows are K different problems (e.g. one per image row, each with
    data of its own) rather than K starts of one: residuals is then called as
    residuals(u (m, n), problems (m,)), problems the index of each row's problem, and
    no problem is merged into or abandoned for another.
    typical: (n,) or (K, n) largest scale of each coordinate (one typical step, in u); 0 holds
    a coordinate where it starts.
    tolerance: a problem stops when its step moves no parameter by more than this many
    standard errors, or (floor > 0) by more than floor typical steps, whichever is more: a
    floor ends a solve that only has to find a basin where the data pin the values far
    tighter than that. difference_step: forward-difference step in standard errors.
    progress: called after every step with (step, chi2 (K,)).
    """
    u = np.array(u0, dtype=float)
    K, n = u.shape
    if not independent:
        one_problem = residuals
        residuals = lambda rows, problems: one_problem(rows)  # noqa: E731
    r = residuals(u, np.arange(K))
    chi2 = np.where(np.all(np.isfinite(r), axis=1), np.sum(r * r, axis=1), np.inf)
    r = np.where(np.isfinite(r), r, 0.0)
    # One difference Jacobian, in steps of the typical scale, gives the standard errors
    # that set the solver's scale (and serves as its first Jacobian).
    J = _jacobians(residuals, u, r, np.broadcast_to(np.asarray(typical, float), (K, n)), difference_step,
                   np.arange(K))
    curvature = J.transpose(0, 2, 1) @ J + _TINY_CURVATURE * np.eye(n)
    errors = np.sqrt(np.clip(np.diagonal(np.linalg.pinv(curvature, hermitian=True), axis1=1, axis2=2), 0, None))
    scale = np.minimum(np.where(errors > 0, errors, np.inf), typical)
    typical = np.broadcast_to(np.asarray(typical, float), (K, n))
    # the stopping limit of each coordinate's step, in standard errors
    limit = np.maximum(tolerance, floor * np.divide(typical, scale, out=np.zeros_like(scale), where=scale > 0))
    damping = _INITIAL_DAMPING * np.max(np.diagonal(J.transpose(0, 2, 1) @ J * scale[:, None, :] * scale[:, :, None],
                                                    axis1=1, axis2=2), axis=1)
    growth = np.full(K, 2.0)
    age = np.zeros(K, int)  # Broyden updates since the last difference Jacobian
    active = np.isfinite(chi2)
    converged = np.zeros(K, bool)
    steps = np.zeros(K, int)
    for step in range(max_steps):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        Jw = J[idx] * scale[idx, None, :]  # (k, N, n)
        A = Jw.transpose(0, 2, 1) @ Jw
        g = np.einsum("kNn,kN->kn", Jw, r[idx])
        damped = A + damping[idx, None, None] * np.eye(n)
        delta = -np.linalg.solve(damped, g[..., None])[..., 0]  # (k, n) in standard errors
        trial = u[idx] + delta * scale[idx]
        r_trial = residuals(trial, idx)
        finite = np.all(np.isfinite(r_trial), axis=1)
        chi2_trial = np.where(finite, np.sum(np.where(np.isfinite(r_trial), r_trial, 0.0) ** 2, axis=1), np.inf)
        predicted = -(2 * np.einsum("kn,kn->k", g, delta) + np.einsum("kn,knm,km->k", delta, A, delta))
        ratio = (chi2[idx] - chi2_trial) / np.maximum(predicted, 1e-300)
        accepted = finite & (ratio > _MIN_GAIN_RATIO)
        steps[idx] += 1
        small = np.all(np.abs(delta) < limit[idx], axis=1)
        stale = age[idx] > 0
        # Broyden: the Jacobian learns from every finite trial, accepted or not.
        moved = delta * scale[idx]
        for j in np.flatnonzero(finite):
            k = idx[j]
            miss = r_trial[j] - r[k] - J[k] @ moved[j]
            J[k] += np.outer(miss, moved[j]) / max(moved[j] @ moved[j], 1e-300)
        a = idx[accepted]
        u[a], r[a], chi2[a] = trial[accepted], r_trial[accepted], chi2_trial[accepted]
        age[a] += 1
        rho = ratio[accepted]
        damping[a] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        growth[a] = 2.0
        # A failed step with a stale Jacobian is the Jacobian's fault, not the damping's.
        rejected = idx[~accepted & ~stale]
        damping[rejected] *= growth[rejected]
        growth[rejected] *= 2.0
        converged[idx[small & ~stale]] = True
        active[idx[(small & ~stale) | (damping[idx] > _MAX_DAMPING)]] = False
        if not independent:
            _merge(u, chi2, scale, active)
            _abandon(chi2, steps, active)
        refresh = idx[active[idx] & ((age[idx] >= _BROYDEN_STEPS) | (stale & (small | ~accepted)))]
        if len(refresh):
            J[refresh] = _jacobians(residuals, u[refresh], r[refresh], scale[refresh], difference_step, refresh)
            age[refresh] = 0
        if progress is not None:
            progress(step + 1, chi2)
    return Solution(u, chi2, r, J, converged, steps)
