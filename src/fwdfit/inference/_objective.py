"""The fit's objective: the Gaussian likelihood of the measured profiles given free values.

One objective serves every consumer of a fit: the global scan and the least-squares
solver take its residual rows (NumPy, through the compiled ``Predictor``, model and
data smoothed alike where asked), a sampler its log-likelihood as a JAX function
(differentiable, for NUTS), and ``log_likelihood`` gives the same number on the host.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ._predict import Predictor, _predict_rows


class _Smoother:
    """Gaussian smoothing of concatenated profiles (rows, N), each profile on its own, ends padded."""

    def __init__(self, lengths: list[int], pixel_um: list[float], sigma_um: float):
        self.slices = np.cumsum([0] + list(lengths))
        self.kernels = []
        for pixel in pixel_um:
            half = math.ceil(3 * sigma_um / pixel)
            offsets = np.arange(-half, half + 1)
            kernel = np.exp(-0.5 * (offsets * pixel / sigma_um) ** 2) if sigma_um > 0 else (offsets == 0) * 1.0
            self.kernels.append(kernel / kernel.sum())

    def __call__(self, rows: np.ndarray) -> np.ndarray:
        out = np.empty_like(rows)
        for (a, b), kernel in zip(zip(self.slices[:-1], self.slices[1:]), self.kernels):
            half = len(kernel) // 2
            if half == 0:
                out[:, a:b] = rows[:, a:b]
                continue
            padded = np.pad(rows[:, a:b], ((0, 0), (half, half)), mode="edge")
            out[:, a:b] = sum(w * padded[:, k:k + b - a] for k, w in enumerate(kernel))
        return out


class Objective:
    """chi2 = sum(((T_model - T) / sigma)^2) over every profile, as residuals and as a likelihood.

    predict: the compiled model (rows of free values -> T rows). T, sigma: the measured
    profiles and their 1-sigma errors, one array per profile. pixel_um: each profile's
    pixel (for smoothing in µm).
    """

    def __init__(self, predict: Predictor, T: list[np.ndarray], sigma: list[np.ndarray],
                 pixel_um: list[float]):
        self.predict = predict
        self.T, self.sigma = np.concatenate(T), np.concatenate(sigma)
        self._lengths, self._pixel_um = [len(t) for t in T], list(pixel_um)
        self._smoothers: dict[float, _Smoother] = {}

    def residuals(self, values: np.ndarray, smoothing_um: float = 0.0) -> np.ndarray:
        """(T_model - T) / sigma (rows, N) for free values (rows, n_free) in physical units;
        smoothing_um > 0: model and data both smoothed by a Gaussian of that sigma (µm)."""
        smooth = self._smoothers.get(smoothing_um)
        if smooth is None:
            smooth = self._smoothers[smoothing_um] = _Smoother(self._lengths, self._pixel_um, smoothing_um)
        T_model, _ = self.predict(values)
        return (smooth(T_model) - smooth(self.T[None])) / self.sigma

    def chi2(self, values: np.ndarray, smoothing_um: float = 0.0) -> np.ndarray:
        """Chi-square (rows,) of free values (rows, n_free)."""
        return np.sum(self.residuals(values, smoothing_um) ** 2, axis=1)

    @property
    def log_normaliser(self) -> float:
        """log of the Gaussian likelihood's constant: -sum(log(sqrt(2 pi) sigma))."""
        return float(-np.sum(np.log(math.sqrt(2 * math.pi) * self.sigma)))

    def log_likelihood(self, values: np.ndarray) -> np.ndarray:
        """Gaussian log-likelihood (rows,) of free values (rows, n_free), on the host."""
        return self.log_normaliser - 0.5 * self.chi2(values)

    def jax_log_likelihood(self):
        """The same log-likelihood as a pure JAX function (model, assemble, values (n_free,))
        -> (), differentiable in values (and in the model's arrays)."""
        T, sigma, constant = jnp.asarray(self.T), jnp.asarray(self.sigma), self.log_normaliser

        def log_likelihood(model, assemble, values):
            T_model, _ = _predict_rows(model, assemble, values[None])
            z = (T_model[0] - T) / sigma
            return constant - 0.5 * jnp.sum(z * z)

        return log_likelihood
