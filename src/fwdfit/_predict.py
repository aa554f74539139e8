"""Model predictions for many parameter vectors from one compiled program.

Every model evaluation of a fit (the global search, the solver's trial points and
finite differences, the uncertainties) goes through ``Predictor``: the model is
traced and compiled once per geometry, with the data, the starts and the smoothing
outside it. Compile time is what a user waits for on every new geometry, so the
program holds one copy of the model and nothing else. Between runs, JAX's persistent
cache (``_cache``) keeps the compiled program, and the program itself is kept as a
serialized ``jax.export`` module keyed by the static plan, so that a second run of a
geometry neither traces nor compiles the model. Within one process (a Dask worker
fitting image after image, say) the compiled program itself is kept too (``_COMPILED``),
so a geometry compiles once per process. On a CPU the program takes one
parameter vector per call (a batch gains no parallelism there); on an accelerator it
takes ``rows_per_call`` vectors at once (vmap), and on several accelerators those rows
are sharded across the devices (a 1-D mesh over the rows; the model is replicated).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._model import ForwardModel
from ._parameters import Assembler

_COMPILED: dict[str, object] = {}  # this process's compiled programs by program key (oldest dropped first)
_MAX_COMPILED = 16


def forget_compiled() -> None:
    """Drop this process's compiled programs (the next ``Predictor`` compiles or loads anew)."""
    _COMPILED.clear()


def _predict_rows(model: ForwardModel, assemble: Assembler, values):
    """(T_model, T_att), each (rows, n_pixel_total): every profile, norm and background applied."""

    def one(v):
        params, norm, background = assemble(v)
        return model.flat(params, norm, background)

    return jax.vmap(one)(values)


class Predictor:
    """T_model and T_att (rows, n_pixel_total) for rows of free values (rows, n_free).

    model, assemble: the forward model and the map from free values to its inputs
    (``_parameters.assembler``). devices: the devices the rows of a call are sharded
    across (default: every accelerator, or one CPU). Compiling happens in the constructor;
    ``compile_time_s`` says how long it took (short when the persistent cache had it).
    """

    def __init__(self, model: ForwardModel, assemble: Assembler, n_free: int,
                 rows_per_call: int | None = None, devices: list | None = None):
        on_cpu = jax.default_backend() == "cpu"
        if devices is None:
            devices = jax.devices()[:1] if on_cpu else jax.devices()
        if rows_per_call is None:
            rows_per_call = 1 if on_cpu and len(devices) == 1 else 64 * len(devices)
        rows_per_call = -(-rows_per_call // len(devices)) * len(devices)  # whole rows per device
        self.rows_per_call, self.n_free, self.devices = rows_per_call, n_free, tuple(devices)
        start = time.perf_counter()
        dynamic, static = eqx.partition((model, assemble), eqx.is_array)
        self._leaves, treedef = jax.tree_util.tree_flatten(dynamic)

        def run(leaves, values):
            model, assemble = eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)
            return _predict_rows(model, assemble, values)

        example = jnp.zeros((rows_per_call, n_free))
        self._rows_sharding = None
        if len(devices) > 1:
            mesh = jax.sharding.Mesh(np.array(devices), ("rows",))
            self._rows_sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("rows"))
            replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
            self._leaves = jax.device_put(self._leaves, replicated)
            example = jax.device_put(example, self._rows_sharding)
        key = _program_key(self._leaves, example, f"{treedef}|{rows_per_call}|{n_free}|{len(devices)}")
        self._compiled = _COMPILED.get(key)
        if self._compiled is None:
            # a stored module serves one device; a sharded program is traced here
            program = _exported(run, self._leaves, example, key) if len(devices) == 1 else run
            self._compiled = jax.jit(program).lower(self._leaves, example).compile()
            if len(_COMPILED) >= _MAX_COMPILED:
                del _COMPILED[next(iter(_COMPILED))]
            _COMPILED[key] = self._compiled
        self.n_pixel_total = self._compiled.out_info[0].shape[1]
        self.compile_time_s = time.perf_counter() - start
        self.n_evaluations = 0

    def __call__(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions for values (rows, n_free) in physical units: (T_model, T_att) as NumPy."""
        values = np.asarray(values, dtype=float).reshape(-1, self.n_free)
        n_rows, chunk = values.shape[0], self.rows_per_call
        if n_rows == 0:
            empty = np.zeros((0, self.n_pixel_total))
            return empty, empty.copy()
        padded = np.concatenate([values, np.repeat(values[-1:], -n_rows % chunk, axis=0)])
        place = jnp.asarray if self._rows_sharding is None else (
            lambda rows: jax.device_put(rows, self._rows_sharding))
        outputs = [self._compiled(self._leaves, place(padded[i:i + chunk]))
                   for i in range(0, padded.shape[0], chunk)]
        self.n_evaluations += n_rows
        T = np.concatenate([np.asarray(o[0]) for o in outputs])[:n_rows]
        T_att = np.concatenate([np.asarray(o[1]) for o in outputs])[:n_rows]
        return T, T_att


def _program_key(leaves, example, plan: str) -> str:
    """The program's key: plan (text that, with the argument shapes and the versions,
    identifies the program), the shapes and dtypes, the versions and the backend."""
    from . import __version__

    shapes = ";".join(f"{x.shape}{x.dtype}" for x in [*leaves, example])
    return hashlib.sha256("|".join([__version__, jax.__version__, jax.default_backend(), plan, shapes])
                          .encode()).hexdigest()[:32]


def _exported(run, leaves, example, key: str):
    """``run`` as a callable for jit: a stored ``jax.export`` module of it (``key``, from
    ``_program_key``) when the persistent cache is on (made and stored on the first run),
    else ``run`` itself.
    """
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return run
    path = Path(folder) / "fwdfit-programs" / f"{key}.jaxexport"
    try:
        return jax.export.deserialize(bytearray(path.read_bytes())).call
    except (OSError, ValueError):
        pass
    exported = jax.export.export(jax.jit(run))(leaves, example)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(handle, "wb") as stream:
            stream.write(exported.serialize())
        os.replace(temporary, path)
    except OSError:
        pass  # a read-only cache: the program is simply traced again next time
    return exported.call
