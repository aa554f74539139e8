"""Posterior sampling with NUTS (blackjax) on the least-squares fit's objective.

The posterior of the free values is the Gaussian likelihood of the fit,
exp(-chi2 / 2) with chi2 = sum(((T_model - T) / sigma)^2) over every profile (sigma:
T_err, else the fit's noise estimate), times a prior uniform inside each free
parameter's bounds. NUTS runs in the fit's unconstrained coordinates u
(``FreeParameter.from_unit``), so the density carries the log-Jacobian of that map,
whitened by the fit: u = u_fit + L w with L L^T the fit's covariance in u (a constant
Jacobian), so that the warm-up starts from a unit mass matrix on the posterior's scale.

The chains start from the fit's optimum, spread by its covariance, and adapt step
size and a dense mass matrix with blackjax's window adaptation. The model and its exact gradient (JAX autodiff) are compiled once, as a
program for all chains at once; blackjax's own (small) programs reach it through a
host callback, so no sampler program holds a copy of the model.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import FwdfitError
from ._fit import FitResult, Fitter

QUANTILES = (2.5, 16.0, 50.0, 84.0, 97.5)  # percent, as posterior.json reports them


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior draws (chains, draws, n_free) in the units of the scene keys, with diagnostics.

    ``fit``: the least-squares fit the chains started from. ``divergences``: divergent
    transitions after warm-up; ``acceptance_rate``: mean NUTS acceptance; ``ess`` and
    ``rhat`` (n_free,): bulk effective sample size and rank-normalised split R-hat
    (blackjax.diagnostics); times in seconds (``sampling_time_s`` covers warm-up and
    draws, ``compile_time_s`` the gradient program).
    """

    names: tuple[str, ...]
    draws: np.ndarray
    fit: FitResult
    divergences: int
    acceptance_rate: float
    ess: np.ndarray
    rhat: np.ndarray
    n_warmup: int
    compile_time_s: float
    sampling_time_s: float

    @property
    def ess_per_s(self) -> np.ndarray:
        """Effective samples per second of sampling (warm-up included), per parameter (n_free,)."""
        return self.ess / self.sampling_time_s

    @property
    def mean(self) -> np.ndarray:
        return self.draws.reshape(-1, len(self.names)).mean(axis=0)

    @property
    def sd(self) -> np.ndarray:
        return self.draws.reshape(-1, len(self.names)).std(axis=0, ddof=1)

    @property
    def correlation(self) -> np.ndarray:
        """Posterior correlation matrix (n_free, n_free)."""
        return np.atleast_2d(np.corrcoef(self.draws.reshape(-1, len(self.names)), rowvar=False))

    def table(self) -> str:
        """The posterior table as text: mean ± sd, R-hat and ESS per parameter; the run."""
        width = max(len(n) for n in self.names)
        rows = [f"{n:<{width}}  {m:>14.6g} ± {s:<10.3g} R-hat {r:.3f}  ESS {e:.0f}"
                for n, m, s, r, e in zip(self.names, self.mean, self.sd, self.rhat, self.ess)]
        chains, draws, _ = self.draws.shape
        rows.append(f"posterior: {chains} chains x {draws} draws, {self.divergences} divergences, "
                    f"acceptance {self.acceptance_rate:.2f}, {np.min(self.ess_per_s):.3g} effective "
                    f"samples/s (sampling {self.sampling_time_s:.1f} s)")
        return "\n".join(rows)

    def summary(self) -> dict:
        """What posterior.json holds: per parameter mean, sd, quantiles, ESS, R-hat; and the run."""
        flat = self.draws.reshape(-1, len(self.names))
        quantiles = np.percentile(flat, QUANTILES, axis=0)
        parameters = {
            name: {"mean": float(self.mean[j]), "sd": float(self.sd[j]),
                   "quantiles": {f"{q:g}%": float(quantiles[k, j]) for k, q in enumerate(QUANTILES)},
                   "ess": _number(self.ess[j]), "rhat": _number(self.rhat[j]),
                   "least_squares": {"value": float(self.fit.values[j]), "error": float(self.fit.errors[j])}}
            for j, name in enumerate(self.names)}
        chains, draws, _ = self.draws.shape
        return {"parameters": parameters,
                "correlation": {"names": list(self.names), "matrix": np.round(self.correlation, 6).tolist()},
                "chains": chains, "draws_per_chain": draws, "warmup_per_chain": self.n_warmup,
                "divergences": self.divergences, "acceptance_rate": self.acceptance_rate,
                "ess_per_s": {n: _number(e) for n, e in zip(self.names, self.ess_per_s)},
                "min_ess_per_s": _number(np.min(self.ess_per_s)),
                "sampling_time_s": self.sampling_time_s, "compile_time_s": self.compile_time_s}


def _number(x) -> float | None:
    """A float for JSON, None where undefined (diagnostics of too few draws or chains)."""
    return float(x) if np.isfinite(x) else None


def _log_density(fitter: Fitter, data, sigma):
    """log posterior (up to a constant) of whitened w (n_free,), u = u_fit + L w: JAX, differentiable.

    data, sigma: one array per profile (the measured T and its 1-sigma error)."""
    free = fitter.free
    log_likelihood = fitter.objective(data, sigma).jax_log_likelihood()

    def log_density(model, assemble, u_fit, L, w):
        u = u_fit + L @ w
        values = jnp.stack([p.from_unit(u[j], jnp) for j, p in enumerate(free)])
        log_jacobian = sum(p.log_value_per_unit(u[j], jnp) for j, p in enumerate(free))
        return log_likelihood(model, assemble, values) + log_jacobian

    return log_density


class _HostDensity:
    """The log density and its gradient for C chains at once, compiled once: (C, n) -> (C,), (C, n).

    Called from inside blackjax's programs through ``jax.pure_callback``; a call with
    fewer rows (one chain) is padded.
    """

    def __init__(self, fitter: Fitter, data, sigma, n_chains: int, u_fit: np.ndarray, L: np.ndarray):
        dynamic, static = eqx.partition((fitter.model, fitter.assemble), eqx.is_array)
        dynamic = (dynamic, jnp.asarray(u_fit), jnp.asarray(L))
        log_density = _log_density(fitter, data, sigma)

        def batch(dynamic, w):
            arrays, u_fit, L = dynamic
            model, assemble = eqx.combine(arrays, static)
            one = lambda row: log_density(model, assemble, u_fit, L, row)
            return jax.vmap(jax.value_and_grad(one))(w)

        start = time.perf_counter()
        self._dynamic, self.rows = dynamic, n_chains
        self._compiled = jax.jit(batch).lower(dynamic, jnp.zeros((n_chains, len(fitter.free)))).compile()
        self.compile_time_s = time.perf_counter() - start

    def __call__(self, w):
        """Value (...,) and gradient (..., n) at whitened coordinates w (..., n), at most C rows."""
        w = np.asarray(w, dtype=float)
        rows = w.reshape(-1, w.shape[-1])
        n = rows.shape[0]
        padded = np.concatenate([rows, np.repeat(rows[-1:], self.rows - n, axis=0)])
        value, grad = self._compiled(self._dynamic, jnp.asarray(padded))
        return np.asarray(value)[:n].reshape(w.shape[:-1]), np.asarray(grad)[:n].reshape(w.shape)


def _traced_density(host: _HostDensity):
    """A JAX-differentiable log density of w (n,) -> () that calls ``host`` for value and gradient."""

    def both(w):
        shapes = (jax.ShapeDtypeStruct(w.shape[:-1], w.dtype), jax.ShapeDtypeStruct(w.shape, w.dtype))
        return jax.pure_callback(host, shapes, w, vmap_method="expand_dims")

    @jax.custom_jvp
    def log_density(w):
        return both(w)[0]

    @log_density.defjvp
    def _(primals, tangents):
        (w,), (dw,) = primals, tangents
        value, grad = both(w)
        return value, jnp.sum(grad * dw, axis=-1)

    return log_density


def _unit_covariance(fitter: Fitter, result: FitResult) -> tuple[np.ndarray, np.ndarray]:
    """The fit's optimum (n,) and covariance (n, n) in unconstrained coordinates u."""
    u = fitter._units(result.values)
    slope = np.array([p.value_per_unit(x) for p, x in zip(fitter.free, u)])
    cov = result.correlation * np.outer(result.errors, result.errors) / np.outer(slope, slope)
    return u, cov


def sample(scene, n_draws: int, *, chains: int = 4, warmup: int | None = None, seed: int = 0,
           fitter: Fitter | None = None, result: FitResult | None = None, T=None, T_err=None,
           **fit_options) -> Posterior:
    """NUTS draws from the posterior of a scene's free parameters (fit first, then sample).

    n_draws: draws per chain after warm-up; chains: independent chains, run together;
    warmup: adaptation steps per chain (default max(300, n_draws / 2)). fitter / result:
    an existing ``Fitter`` of the scene and its ``FitResult`` of these data (default: fit
    here, with ``fit_options`` as for ``Fitter``, e.g. accuracy). T, T_err: other data
    than the scene's, as for ``Fitter.__call__``. Needs blackjax (``pip install
    'fwdfit[sample]'``) and float64.
    """
    if int(n_draws) != n_draws or n_draws < 1:
        raise FwdfitError(f"the number of draws must be a whole number >= 1, got {n_draws}")
    if int(chains) != chains or chains < 1:
        raise FwdfitError(f"chains must be a whole number >= 1, got {chains}")
    warmup = max(300, n_draws // 2) if warmup is None else warmup
    if int(warmup) != warmup or warmup < 10:
        raise FwdfitError(f"warmup must be a whole number >= 10, got {warmup}")
    blackjax = blackjax_module()
    from blackjax.adaptation.base import get_filter_adapt_info_fn

    fitter = fitter if fitter is not None else Fitter(scene, **fit_options)
    result = result if result is not None else fitter(T, T_err, seed=seed)
    data, sigma, _ = fitter._data if T is None else fitter._new_data(T, T_err)
    u_best, cov_u = _unit_covariance(fitter, result)
    if not np.all(np.isfinite(cov_u)) or np.any(np.linalg.eigvalsh(cov_u) <= 0):
        raise FwdfitError("the fit's covariance is singular: a free parameter is not constrained by the data")

    L = np.linalg.cholesky(cov_u)
    host = _HostDensity(fitter, data, sigma, chains, u_best, L)
    log_density = _traced_density(host)
    starts = np.random.default_rng(seed).normal(size=(chains, len(u_best)))
    keys = jax.random.split(jax.random.key(seed), 2 * chains)

    begin = time.perf_counter()
    adaptation = blackjax.window_adaptation(blackjax.nuts, log_density, is_mass_matrix_diagonal=False,
                                            adaptation_info_fn=get_filter_adapt_info_fn())
    (states, parameters), _ = jax.jit(jax.vmap(lambda k, x: adaptation.run(k, x, warmup)))(
        keys[:chains], jnp.asarray(starts))

    def chain(key, state, step_size, inverse_mass_matrix):
        kernel = blackjax.nuts(log_density, step_size, inverse_mass_matrix)

        def step(state, key):
            state, info = kernel.step(key, state)
            return state, (state.position, info.is_divergent, info.acceptance_rate)

        return jax.lax.scan(step, state, jax.random.split(key, n_draws))[1]

    positions, divergent, acceptance = jax.jit(jax.vmap(chain))(
        keys[chains:], states, parameters["step_size"], parameters["inverse_mass_matrix"])
    positions = u_best + np.asarray(positions) @ L.T
    seconds = time.perf_counter() - begin
    draws = np.stack([p.from_unit(positions[..., j]) for j, p in enumerate(fitter.free)], axis=-1)
    ess, rhat = diagnostics(blackjax, draws)
    return Posterior(result.names, draws, result, int(np.sum(divergent)), float(np.mean(acceptance)),
                     ess, rhat, warmup, host.compile_time_s, seconds)


def diagnostics(blackjax, draws: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bulk ESS and rank-normalised split R-hat (n_free,) of draws (chains, draws, n_free)."""
    if draws.shape[1] < 4:  # too few draws to split chains: no diagnostics
        return np.full(draws.shape[2], np.nan), np.full(draws.shape[2], np.nan)
    ess = np.asarray(jax.jit(blackjax.diagnostics.ess_bulk)(draws)).reshape(-1)  # jit: seconds, not tens
    if draws.shape[0] < 2:
        return ess, np.full(draws.shape[2], np.nan)
    return ess, np.asarray(jax.jit(blackjax.diagnostics.rhat)(draws)).reshape(-1)


def blackjax_module():
    try:
        import blackjax
    except ImportError:
        raise FwdfitError("sampling needs blackjax: pip install 'fwdfit[sample]'") from None
    return blackjax
