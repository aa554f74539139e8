"""Model predictions for many parameter vectors from one compiled program.

Every model evaluation of a fit (the global search, the solver's trial points and
finite differences, the uncertainties) goes through ``Predictor``: the model is
traced and compiled once per geometry, with the data, the starts and the smoothing
outside it. Compile time is what a user waits for on every new geometry, so the
program holds one copy of the model and nothing else; JAX's persistent cache
(``_cache``) keeps it between runs. On a CPU the program takes one parameter vector
per call (a batch gains no parallelism there); on an accelerator it takes
``rows_per_call`` vectors at once (vmap).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._model import ForwardModel
from ._parameters import Assembler


def _predict_rows(model: ForwardModel, assemble: Assembler, values):
    """(T_model, T_att), each (rows, n_pixel_total): every profile, norm and background applied."""

    def one(v):
        params, norm, background = assemble(v)
        T, T_att = model(params)
        return (jnp.concatenate([n * t + b for t, n, b in zip(T, norm, background)]),
                jnp.concatenate([n * t + b for t, n, b in zip(T_att, norm, background)]))

    return jax.vmap(one)(values)


class Predictor:
    """T_model and T_att (rows, n_pixel_total) for rows of free values (rows, n_free).

    model, assemble: the forward model and the map from free values to its inputs
    (``_parameters.assembler``). Compiling happens in the constructor;
    ``compile_time_s`` says how long it took (short when the persistent cache had it).
    """

    def __init__(self, model: ForwardModel, assemble: Assembler, n_free: int,
                 rows_per_call: int | None = None):
        if rows_per_call is None:
            rows_per_call = 1 if jax.default_backend() == "cpu" else 64
        self.rows_per_call, self.n_free = rows_per_call, n_free
        self._args = (model, assemble)
        start = time.perf_counter()
        example = jnp.zeros((rows_per_call, n_free))
        self._compiled = eqx.filter_jit(_predict_rows).lower(model, assemble, example).compile()
        self.compile_time_s = time.perf_counter() - start
        self.n_evaluations = 0

    def __call__(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions for values (rows, n_free) in physical units: (T_model, T_att) as NumPy."""
        values = np.atleast_2d(np.asarray(values, dtype=float))
        n_rows, chunk = values.shape[0], self.rows_per_call
        padded = np.concatenate([values, np.repeat(values[-1:], -n_rows % chunk, axis=0)])
        outputs = [self._compiled(*self._args, jnp.asarray(padded[i:i + chunk]))
                   for i in range(0, padded.shape[0], chunk)]
        self.n_evaluations += n_rows
        T = np.concatenate([np.asarray(o[0]) for o in outputs])[:n_rows]
        T_att = np.concatenate([np.asarray(o[1]) for o in outputs])[:n_rows]
        return T, T_att
