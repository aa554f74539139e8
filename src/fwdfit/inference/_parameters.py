"""Free parameters: names as in ``[fit] vary``, bounds, and the maps between
the solver's unconstrained coordinates, physical values and model parameters.

Names: ``sample.tilt_deg``, ``sample.centre_um``, ``sample.depth_mm``,
``sample.drift_um_per_mm``, ``layers.<layer>.<thickness_um | sld_e6_per_A2 |
mu_per_m | mu_per_m_per_A | density_scale>``, ``profiles.<profile>.<distance_mm | shift_um | norm |
background>``; ``profiles.*.<key>`` frees one parameter per profile. A layer
tied with ``same_as`` shares its twin's parameters under either name.

Bounds are enforced by transforms (a sigmoid between two bounds, a softplus
beyond one bound), so the solver works unconstrained. The transforms are NumPy:
the solver's logic runs on the host around one compiled model (``_predict``).

A free parameter may have no start value in the scene (NaN): the fit estimates
it from the data (``_starts``).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import numpy as np

from ..scene import _registry as registry
from .._errors import FwdfitError
from ..model._arrays import to_device
from ._geometry import geometry_of
from ..scene._limits import MAX_TILT_DEG
from ..scene._scene import Scene

LAYER_FIELDS = tuple(registry.part("layers"))  # per-layer model parameters


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """One free parameter: its name, scene value (NaN: none given), bounds and typical step (scene units)."""

    name: str
    value: float
    low: float
    high: float
    step: float
    target: tuple  # (field, indices) it sets

    # Solver coordinates u are in units of ``step`` near the start: Levenberg-Marquardt
    # damping then treats all parameters alike. Between two bounds a widened sigmoid,
    # above (below) one bound a softplus, which stays linear far from the bound and
    # keeps a useful gradient close to it.

    def to_unit(self, value):
        """Physical value -> unconstrained coordinate (NumPy, elementwise)."""
        value = np.asarray(value, dtype=float)
        if math.isfinite(self.low) and math.isfinite(self.high):
            fraction = (value - self.low) / (self.high - self.low)
            return self._width * (np.log(fraction) - np.log1p(-fraction))
        if math.isfinite(self.low) or math.isfinite(self.high):
            gap = (value - self.low) if math.isfinite(self.low) else (self.high - value)
            x = gap / self.step
            return x + np.log(-np.expm1(-x))  # inverse softplus, stable for large x
        return (value - self.origin) / self.step

    def from_unit(self, u, xp=np):
        """Unconstrained coordinate -> physical value inside the bounds (elementwise; xp:
        the array module, NumPy or ``jax.numpy``)."""
        u = xp.asarray(u, dtype=float)
        if math.isfinite(self.low) and math.isfinite(self.high):
            return self.low + (self.high - self.low) * 0.5 * (1.0 + xp.tanh(0.5 * u / self._width))
        softplus = xp.logaddexp(0.0, u)
        if math.isfinite(self.low):
            return self.low + self.step * softplus
        if math.isfinite(self.high):
            return self.high - self.step * softplus
        return self.origin + self.step * u

    def value_per_unit(self, u):
        """d value / d u at u (NumPy, elementwise)."""
        u = np.asarray(u, dtype=float)
        if math.isfinite(self.low) and math.isfinite(self.high):
            s = 0.5 * (1.0 + np.tanh(0.5 * u / self._width))
            return (self.high - self.low) * s * (1.0 - s) / self._width
        sigmoid = 0.5 * (1.0 + np.tanh(0.5 * u))
        if math.isfinite(self.low) or math.isfinite(self.high):
            return self.step * sigmoid
        return np.full_like(u, self.step)

    def log_value_per_unit(self, u, xp=np):
        """log(d value / d u) at u (elementwise; xp: NumPy or ``jax.numpy``), exact where
        ``value_per_unit`` underflows: the log-Jacobian of ``from_unit``."""
        u = xp.asarray(u, dtype=float)
        if math.isfinite(self.low) and math.isfinite(self.high):
            x = u / self._width  # s = sigmoid(x): log s = -softplus(-x), log(1 - s) = -softplus(x)
            return (math.log((self.high - self.low) / self._width)
                    - xp.logaddexp(0.0, -x) - xp.logaddexp(0.0, x))
        if math.isfinite(self.low) or math.isfinite(self.high):
            return math.log(self.step) - xp.logaddexp(0.0, -u)
        return xp.full_like(u, math.log(self.step))

    @property
    def origin(self) -> float:
        """Where u = 0 lies for an unbounded parameter: its start, else 0."""
        return self.value if math.isfinite(self.value) else 0.0

    @property
    def _width(self) -> float:
        """Sigmoid scale giving slope ``step`` per unit at the middle of the box."""
        return max((self.high - self.low) / (4.0 * self.step), 1.0)


def _resolve(scene: Scene, name: str) -> list[tuple[str, str, tuple, tuple, float]]:
    """(canonical name, key, field target, default bounds, step) for one ``vary`` entry."""
    parts = name.split(".")
    quantity = registry.BY_KEY.get(parts[-1])
    geometry = scene.sample.geometry
    if quantity is not None and quantity.part == parts[0] and geometry not in quantity.geometries:
        raise FwdfitError(f"{scene.path}: fit.vary: {name!r}: a {geometry} has no {parts[-1]}")
    part = None if quantity is None or quantity.part != parts[0] else quantity.part
    key, bounds, step = parts[-1], *((quantity.bounds, quantity.step) if part else ((), 0.0))
    layers = {layer.name: layer for layer in scene.sample.layers}
    if part == "sample" and len(parts) == 2:
        return [(name, key, (key, ()), bounds, step)]
    if part == "layers" and len(parts) >= 3:
        layer = layers.get(".".join(parts[1:-1]))
        if layer is not None:
            root = layer.same_as or layer.name
            tied = tuple(i for i, l in enumerate(scene.sample.layers) if (l.same_as or l.name) == root)
            return [(f"layers.{root}.{key}", key, (key, tied), bounds, step)]
    if part == "profiles" and len(parts) >= 3:
        label = ".".join(parts[1:-1])
        names = [p.name for p in scene.profiles]
        chosen = range(len(names)) if label == "*" else [names.index(label)] if label in names else []
        return [(f"profiles.{names[i]}.{key}", key, (key, (i,)), bounds, step) for i in chosen]
    raise FwdfitError(f"{scene.path}: fit.vary: unknown parameter {name!r} (parameter names: "
                      "sample.KEY, layers.LAYER.KEY, profiles.PROFILE.KEY; see docs/SCENE.md)")


def _scene_value(scene: Scene, key: str, target: tuple) -> float:
    _, index = target
    part = registry.BY_KEY[key].part
    if part == "layers":
        return registry.layer_value(scene.sample.layers[index[0]], key)
    if part == "profiles":
        return getattr(scene.profiles[index[0]], key)
    return getattr(scene.sample, key)


def free_parameters(scene: Scene, vary=None, bounds=None) -> tuple[FreeParameter, ...]:
    """The free parameters named by ``vary`` (default the scene's ``[fit] vary``)."""
    vary = scene.fit.vary if vary is None else tuple(vary)
    bounds = scene.fit.bounds if bounds is None else dict(bounds)
    if not vary:
        raise FwdfitError(f"{scene.path}: fit.vary: no parameter to fit")
    free, seen = [], set()
    for entry in vary:
        for canonical, key, target, default, step in _resolve(scene, entry):
            if canonical in seen:
                continue
            if registry.BY_KEY[key].model == "image":  # fit-image takes it out of vary before this
                raise FwdfitError(f"{scene.path}: fit.vary: {entry!r}: only fwdfit fit-image fits it "
                                  "(a quantity of an image's rows, which a profile does not have)")
            seen.add(canonical)
            given = entry in bounds or canonical in bounds
            low, high = bounds.get(entry, bounds.get(canonical, default))
            value = _scene_value(scene, key, target)
            if key == "distance_mm" and not given:
                low = 0.5 * scene.sample.depth_mm
            if key == "tilt_deg" and not given and math.isfinite(value):
                high = min(max(high, 2.0 * abs(value)), MAX_TILT_DEG)
                low = -high
            if registry.BY_KEY[key].signed_by_start and not given and value < 0:
                low, high = -high, -low  # a negative-SLD material (Ti, V, water, a hydride)
            if math.isnan(value):
                free.append(FreeParameter(canonical, value, low, high, step, target))
                continue
            if not low <= value <= high:
                source = f"fit.bounds.{entry}" if given else (
                    f"fit.vary.{entry}: the default bounds of {key}; set fit.bounds.{entry} to change them")
                raise FwdfitError(f"{scene.path}: {source}: start value {value} is outside [{low}, {high}]")
            if value in (low, high) and key != "background":
                value = value + (0.01 * step if value == low else -0.01 * step)
            free.append(FreeParameter(canonical, value, low, high, step, target))
    unknown = sorted(set(bounds) - set(vary) - seen)
    if unknown:
        raise FwdfitError(f"{scene.path}: fit.bounds.{unknown[0]}: not a parameter named in fit.vary")
    return tuple(free)


class Assembler(eqx.Module):
    """Physical values (n_free,) -> (model parameters, norm (n_profile,), background (n_profile,)).

    base: the geometry's parameters at the scene's values (``Geometry.initial_params``), a
    Module with a field per registry key that the model takes, and ``distance_mm`` and
    ``shift_um`` per profile."""

    base: eqx.Module
    profile_shift_um: jax.Array
    drift_um_per_mm: jax.Array
    norm: jax.Array
    background: jax.Array
    targets: tuple = eqx.field(static=True)

    def __call__(self, values):
        fields = {f.name: getattr(self.base, f.name) for f in dataclasses.fields(self.base)}
        extra = {"shift_um": self.profile_shift_um, "drift_um_per_mm": self.drift_um_per_mm,
                 "norm": self.norm, "background": self.background}
        for field, (scalar, positions, indices) in _by_field(self.targets).items():
            store = extra if field in extra else fields
            if scalar is not None:
                store[field] = values[scalar]
            if positions:  # one gather and one scatter per field, however many profiles
                store[field] = store[field].at[np.asarray(indices)].set(values[np.asarray(positions)])
        fields["shift_um"] = extra["shift_um"] + extra["drift_um_per_mm"] * fields["distance_mm"]
        return type(self.base)(**fields), extra["norm"], extra["background"]


def _by_field(targets: tuple) -> dict[str, tuple[int | None, list[int], list[int]]]:
    """field -> (position of its scalar value or None, value positions, array indices) of targets."""
    fields: dict = {}
    for position, (field, index) in enumerate(targets):
        scalar, positions, indices = fields.get(field, (None, [], []))
        if not index:
            scalar = position
        positions, indices = positions + [position] * len(index), indices + list(index)
        fields[field] = (scalar, positions, indices)
    return fields


def assembler(scene: Scene, free: tuple[FreeParameter, ...], dtype=None) -> Assembler:
    """The map from free values to model inputs, with every other value from the scene
    (its geometry's parameters, ``Geometry.initial_params``)."""
    as_array = lambda values: to_device(values, dtype)
    return Assembler(
        base=geometry_of(scene).initial_params(scene, dtype),
        profile_shift_um=as_array([p.shift_um for p in scene.profiles]),
        drift_um_per_mm=as_array(scene.sample.drift_um_per_mm),
        norm=as_array([p.norm for p in scene.profiles]),
        background=as_array([p.background for p in scene.profiles]),
        targets=tuple(p.target for p in free),
    )
