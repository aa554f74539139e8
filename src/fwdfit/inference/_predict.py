"""Model predictions for many parameter vectors from the model compiled once per geometry.

Every model evaluation of a fit (the global search, the solver's trial points and
finite differences, the uncertainties) goes through ``Predictor``: the model is
traced and compiled once per geometry, with the data, the starts and the smoothing
outside it, as one program per group of profiles that share a static plan
(``ProfileGroup``), whose outputs are put in scene order in NumPy. XLA's CPU runtime
evaluated the shipped example's four groups as four programs in 11-13 ms against
24-35 ms as one program, for the same compile time (the ten-distance joint scene,
compute-bound in its kernels: 70 against 73 ms). Compile time is what a user waits
for on every new geometry, so each program holds one group of the model and nothing
else. Between runs, the cache folder (``_cache``) keeps each compiled program
(``jax.experimental.serialize_executable``) keyed by its static plan, so that a second
run of a geometry neither traces nor compiles the model (and a scene that shares a
group's plan with an earlier one reuses that group's program); JAX's persistent cache
in the same folder serves the other programs (the sampler's gradient, say). Within one process (a Dask worker fitting image after image, say) the
compiled programs themselves are kept too (``_COMPILED``), so a geometry compiles once
per process. On a CPU a program takes one parameter vector per call (a batch gains no
parallelism there); on an accelerator it takes ``rows_per_call`` vectors at once
(vmap), and on several accelerators those rows are sharded across the devices (a 1-D
mesh over the rows; the model is replicated).
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import serialize_executable

from ..model.block._model import ForwardModel
from ._parameters import Assembler

_COMPILED: dict[str, object] = {}  # this process's compiled programs by program key (oldest dropped first)
_MAX_COMPILED = 32  # programs (one per group of a model)


def forget_compiled() -> None:
    """Drop this process's compiled programs (the next ``Predictor`` compiles or loads anew)."""
    _COMPILED.clear()


def _over_rows(one, values):
    """``one`` (a row (n_free,) -> arrays) over rows (rows, n_free), a leading row axis on
    each result. One row (a CPU's call) is traced without vmap: batching every nested
    operation of the model cost ~10 % more compile time (the shipped example: 8.3-8.5 s
    against 7.5 s), for the same evaluation time."""
    if values.shape[0] == 1:
        return tuple(part[None] for part in one(values[0]))
    return jax.vmap(one)(values)


def _predict_rows(model: ForwardModel, assemble: Assembler, values):
    """(T_model, T_att), each (rows, n_pixel_total): every profile, norm and background applied."""

    def one(v):
        params, norm, background = assemble(v)
        return model.flat(params, norm, background)

    return _over_rows(one, values)


def _group_rows(model: ForwardModel, assemble: Assembler, values):
    """(T_model, T_att) of a one-group model, each (rows, n_group_pixels) in ``group.index`` order."""

    def one(v):
        params, norm, background = assemble(v)
        return model.grouped(params, norm, background)[0]

    return _over_rows(one, values)


class Predictor:
    """T_model and T_att (rows, n_pixel_total) for rows of free values (rows, n_free).

    model, assemble: the forward model and the map from free values to its inputs
    (``_parameters.assembler``). devices: the devices the rows of a call are sharded
    across (default: every accelerator, or one CPU). Compiling (one program per group of
    the model) happens in the constructor; ``compile_time_s`` says how long it took (short
    when the cache folder had the programs).
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
        example = jnp.zeros((rows_per_call, n_free))
        self._rows_sharding = None
        if len(devices) > 1:
            mesh = jax.sharding.Mesh(np.array(devices), ("rows",))
            self._rows_sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("rows"))
            example = jax.device_put(example, self._rows_sharding)
        # the model of each group alone (``ForwardModel.grouped`` then has one entry)
        parts = [eqx.tree_at(lambda m: m.groups, model, (group,)) for group in model.groups]
        self.program_sources: list[str] = []  # per program: "compiled", "loaded" (cache folder) or "reused"
        self._programs = [self._program(part, assemble, example, devices) for part in parts]
        self._order = model.scene_order
        self.n_pixel_total = sum(compiled.out_info[0].shape[1] for compiled, _ in self._programs)
        self.compile_time_s = time.perf_counter() - start
        self.n_evaluations = 0

    @property
    def programs(self) -> tuple:
        """The compiled programs (``jax.stages.Compiled``), one per group of the model."""
        return tuple(compiled for compiled, _ in self._programs)

    def _program(self, model: ForwardModel, assemble: Assembler, example, devices):
        """(compiled program, its array arguments) of one group's model: from this process's
        programs, the stored module, or traced and compiled here."""
        dynamic, static = eqx.partition((model, assemble), eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)

        def run(leaves, values):
            model, assemble = eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)
            return _group_rows(model, assemble, values)

        if len(devices) > 1:
            mesh = self._rows_sharding.mesh
            leaves = jax.device_put(leaves, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
        key = _program_key(leaves, example, f"{treedef}|{self.rows_per_call}|{self.n_free}|{len(devices)}")
        run.__name__ = f"fwdfit_{key}"  # JAX's persistent cache keys on the name: it serves this source's program only
        compiled, source = _COMPILED.get(key), "reused"
        if compiled is None:
            compile_here = lambda: jax.jit(run).lower(leaves, example).compile()
            if len(devices) == 1:  # a stored executable serves one device; a sharded program is compiled here
                trees = (jax.tree_util.tree_structure(((leaves, example), {})),
                         jax.tree_util.tree_structure((example, example)))
                compiled, source = _stored(key, *trees, compile_here)
            else:
                compiled, source = compile_here(), "compiled"
            if len(_COMPILED) >= _MAX_COMPILED:
                del _COMPILED[next(iter(_COMPILED))]
            _COMPILED[key] = compiled
        self.program_sources.append(source)
        return compiled, leaves

    def sources_text(self) -> str:
        """How the programs were had, e.g. "3 compiled, 1 loaded from the cache"."""
        words = {"compiled": "compiled", "loaded": "loaded from the cache", "reused": "already compiled"}
        counts = {s: self.program_sources.count(s) for s in words if s in self.program_sources}
        return ", ".join(f"{n} {words[s]}" for s, n in counts.items())

    def __call__(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions for values (rows, n_free) in physical units: (T_model, T_att) as NumPy."""
        values = np.atleast_2d(np.asarray(values, dtype=float))
        n_rows, chunk = values.shape[0], self.rows_per_call
        if n_rows == 0:
            empty = np.zeros((0, self.n_pixel_total))
            return empty, empty.copy()
        padded = np.concatenate([values, np.repeat(values[-1:], -n_rows % chunk, axis=0)])
        place = (lambda rows: rows) if self._rows_sharding is None else (  # a program takes NumPy rows as they are
            lambda rows: jax.device_put(rows, self._rows_sharding))
        # every call dispatched before any result is read, so the programs overlap
        outputs = [[compiled(leaves, rows) for compiled, leaves in self._programs]
                   for rows in (place(padded[i:i + chunk]) for i in range(0, padded.shape[0], chunk))]
        self.n_evaluations += n_rows
        T, T_att = (np.concatenate([np.concatenate([np.asarray(group[k]) for group in call], axis=1)
                                    for call in outputs])[:n_rows] for k in (0, 1))
        return (T, T_att) if self._order is None else (T[:, self._order], T_att[:, self._order])


def _program_key(leaves, example, plan: str) -> str:
    """The program's key: plan (text that, with the argument shapes and the code,
    identifies the program), the shapes and dtypes, fwdfit's source and the versions,
    the backend and the host CPU."""
    from .._version import __version__

    shapes = ";".join(f"{x.shape}{x.dtype}" for x in [*leaves, example])
    return hashlib.sha256("|".join([__version__, _source_digest(), jax.__version__, jax.default_backend(),
                                    _host_cpu(), plan, shapes]).encode()).hexdigest()[:32]


@functools.cache
def _source_digest() -> str:
    """SHA-256 of fwdfit's Python sources (~2 ms): a checkout between releases, with the
    version unchanged, must not load programs that other code compiled."""
    digest = hashlib.sha256()
    package = Path(__file__).parents[1]  # fwdfit/: every module of every folder
    for path in sorted(package.rglob("*.py"), key=lambda path: path.relative_to(package).as_posix()):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


@functools.cache
def _host_cpu() -> str:
    """The host CPU's instruction-set flags (Linux), else its name: an executable compiled
    for one CPU may not run on another (a cache folder on a shared home)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as stream:
            return next((line for line in stream if line.startswith("flags")), "")
    except OSError:
        return platform.processor()


_PERSISTENT_CACHE_HITS = [0]  # programs JAX's persistent cache has served in this process


def _count_cache_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _PERSISTENT_CACHE_HITS[0] += 1


jax.monitoring.register_event_listener(_count_cache_hit)


def _stored(key: str, in_tree, out_tree, compile_here):
    """(program, "loaded" or "compiled"): the compiled program ``key`` (from ``_program_key``)
    from the cache folder, else ``compile_here()``, stored there for the next run. A stored executable loads in ~0.1 s
    (JAX's persistent cache takes ~0.2 s, since it must lower the program to find it);
    without the cache folder nothing is stored, nor is a program JAX's cache served."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return compile_here(), "compiled"
    path = Path(folder) / "fwdfit-programs" / f"{key}.xla"
    try:
        return serialize_executable.deserialize_and_load(path.read_bytes(), in_tree, out_tree), "loaded"
    except Exception:  # noqa: BLE001 - none yet, or from another jaxlib, or damaged: compile anew
        pass
    hits_before = _PERSISTENT_CACHE_HITS[0]
    compiled = compile_here()
    if _PERSISTENT_CACHE_HITS[0] != hits_before:
        # served by JAX's persistent cache (this key's file was damaged or deleted): such an
        # executable serializes without its kernels ("Function ... not found" when the next run
        # loads it), so it is not stored; a damaged file goes, and JAX's cache serves it next time
        path.unlink(missing_ok=True)
        return compiled, "loaded"
    try:
        serialized, _, _ = serialize_executable.serialize(compiled)
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(handle, "wb") as stream:
            stream.write(serialized)
        os.replace(temporary, path)
    except (OSError, ValueError):
        pass  # a read-only cache, or a program XLA cannot serialize: compiled again next time
    return compiled, "compiled"
