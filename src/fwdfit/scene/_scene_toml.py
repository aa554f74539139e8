"""Scenes to TOML text: the one writer of scene files (``load_scene`` reads them back).

``load_scene(dump_scene(scene))`` is ``scene`` again, field for field (floats by ``repr``,
which round-trips exactly). A key at its reader's default is left out. Data live in
files: a profile's measured table, image and spectrum tables are written as their
paths; a profile without a file is written as its pixel grid (``x_min_um``,
``x_max_um``), its in-memory data are not written.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Collection
from pathlib import Path

import numpy as np

from . import _registry as registry
from .._errors import FwdfitError
from ._scene import DEFAULT_ACCURACY, Layer, Profile, Scene, pixel_grid
from ._spectrum import BandSpectrum, GaussianLine, TabulatedSpectrum
from ..io._tables import temporary_path

_Table = tuple[str, str, list[tuple[str, object]]]  # header, placeholder prefix, (key, value)


def dump_scene(scene: Scene, relative_to: str | Path | None = None, *, comment: str = "",
               placeholders: Collection[str] = ()) -> str:
    """The scene as TOML text.

    relative_to: the folder the text will be saved in; file paths are written relative to
    it (absolute when None). comment: lines written first, each as ``# line``.
    placeholders: keys written commented out, for a template to fill in: a table
    (``"sample"``, also its layers) or one key (``"instrument.aperture_mm"``,
    ``"profiles.distance_mm"``). A table whose keys are all placeholders is commented
    out with them. Raises ``FwdfitError`` for what a scene file cannot hold (a spectrum
    table that came from no file).
    """
    folder = None if relative_to is None else Path(relative_to)
    lines = [f"# {line}" if line else "#" for line in comment.splitlines()]
    for header, prefix, entries in _tables(scene, folder):
        text = [f"{key} = {_value(value)}" for key, value in entries]
        hidden = [_hidden(prefix, key, placeholders) for key, _ in entries]
        text = [f"# {line}" if hide else line for line, hide in zip(text, hidden)]
        header_line = f"# {header}" if hidden and all(hidden) else header
        lines += ([""] if lines else []) + [header_line] + text
    return "\n".join(lines) + "\n"


def save_scene(scene: Scene, path: str | Path, **options) -> Path:
    """Write ``dump_scene(scene, path's folder, **options)`` to ``path`` (whole or not at
all; its folder is made if missing)."""
    path = Path(path)
    text = dump_scene(scene, path.parent, **options)
    path.parent.mkdir(parents=True, exist_ok=True)
    with temporary_path(path) as staging:
        staging.write_text(text, encoding="utf-8")
        os.replace(staging, path)
    return path


def _hidden(prefix: str, key: str, placeholders: Collection[str]) -> bool:
    return (prefix in placeholders or prefix.split(".")[0] in placeholders
            or f"{prefix}.{key}" in placeholders)


def _tables(scene: Scene, folder: Path | None) -> list[_Table]:
    def path(file) -> str:
        file = Path(file).resolve()
        return str(file) if folder is None else os.path.relpath(file, folder.resolve())

    s = scene.sample
    shape = _changed([("geometry", s.geometry), ("core", s.core)], {"geometry": "block", "core": ""})
    values = [(key, getattr(s, key)) for key in registry.part("sample", s.geometry)]
    tables: list[_Table] = [("[sample]", "sample", shape + [
        (key, value) for key, value in _changed(values, registry.defaults("sample", s.geometry))
        if not (isinstance(value, float) and math.isnan(value))])]  # NaN: a start left to the fit
    tables += [("[[sample.layers]]", "sample.layers", _layer(layer, s.geometry, s.rod and i == len(s.layers) - 1))
               for i, layer in enumerate(s.layers)]
    for name, inst in scene.instruments.items():
        entries = [(key, getattr(inst, key)) for key in
                   ("aperture", "aperture_mm", "aperture_distance_m", "pixel_um", "psf_fwhm_um", "fresnel")]
        tables.append(("[instrument]" if name == "" else f"[instruments.{_key(name)}]", "instrument",
                       _changed(entries, {"psf_fwhm_um": 0.0, "fresnel": False})))
    for name, spectrum in scene.spectra.items():
        tables.append((f"[spectra.{_key(name)}]", "spectra", _spectrum(name, spectrum, path)))
    tables += [("[[profiles]]", "profiles", _profile(index, p, scene, path))
               for index, p in enumerate(scene.profiles)]
    fit = scene.fit
    entries = _changed([("vary", list(fit.vary)), ("per_row", list(fit.per_row))], {"vary": [], "per_row": []})
    entries += [(f"bounds.{_key(name)}", list(pair)) for name, pair in fit.bounds.items()]
    if entries:
        tables.append(("[fit]", "fit", entries))
    if scene.accuracy != DEFAULT_ACCURACY:
        tables.append(("[model]", "model", [("accuracy", scene.accuracy)]))
    design = scene.design
    entries = [(key, list(value) if isinstance(value, tuple) else value)
               for key, value in dataclasses.asdict(design).items()
               if value != () and not (isinstance(value, float) and math.isnan(value))]
    if entries:
        tables.append(("[design]", "design", entries))
    return tables


def _changed(entries: list[tuple[str, object]], defaults: dict) -> list[tuple[str, object]]:
    """The entries whose value differs from the reader's default (None: no default)."""
    return [(key, value) for key, value in entries if defaults.get(key) is None or value != defaults[key]]


def _layer(layer: Layer, geometry: str = "block", core: bool = False) -> list[tuple[str, object]]:
    """A layer's keys (those ``geometry`` takes): its material's source (formula and density,
    or NCrystal cfg) and the constants that differ from the material's (they override it);
    NaN (a start left to the fit) is left out, and so is the thickness of a rod's ``core``
    (the rest of the radius)."""
    if layer.same_as:
        return [("name", layer.name), ("same_as", layer.same_as)]
    entries: list[tuple[str, object]] = [("name", layer.name)]
    material = layer.material
    if material is not None and material.ncrystal_cfg:
        entries.append(("ncrystal", material.ncrystal_cfg))
    elif material is not None and material.formula:
        entries += [("material", material.formula), ("density_g_cm3", material.density_g_cm3)]
    else:
        material = None
    values = [(key, getattr(layer, key)) for key in registry.part("layers", geometry)
              if not (core and key == "thickness_um")]
    defaults = registry.defaults("layers", geometry) | {"mu_per_m_per_A": None}  # 0 only beside an explicit mu_per_m
    if material is not None:  # the reader's defaults: the material's (mu_per_m_per_A: 0 beside a mu_per_m)
        defaults |= {"sld_e6_per_A2": material.sld_e6_per_A2, "mu_per_m": material.mu_per_m}
        if layer.mu_per_m == material.mu_per_m:
            defaults["mu_per_m_per_A"] = material.mu_per_m_per_A
    return entries + [(key, value) for key, value in _changed(values, defaults) if not math.isnan(value)]


def _spectrum(name: str, spectrum, path) -> list[tuple[str, object]]:
    if isinstance(spectrum, GaussianLine):
        return [("wavelength_A", spectrum.wavelength_A), ("fwhm_rel", spectrum.fwhm_rel)]
    entries: list[tuple[str, object]] = []
    if isinstance(spectrum, BandSpectrum):
        entries = [("lambda_min_A", spectrum.lambda_min_A), ("lambda_max_A", spectrum.lambda_max_A)]
        spectrum = spectrum.table
    if isinstance(spectrum, TabulatedSpectrum):
        if spectrum.path is None:
            raise FwdfitError(f"spectra.{name}: a table that came from no file cannot be written "
                              "into a scene (write it with lambda_A,weight columns first)")
        entries.append(("file", path(spectrum.path)))
    return entries


def _profile(index: int, p: Profile, scene: Scene, path) -> list[tuple[str, object]]:
    entries = [("name", p.name), ("distance_mm", p.distance_mm), ("spectrum", p.spectrum)]
    entries += _changed([("instrument", p.instrument)], {"instrument": ""})
    pixel_um = scene.instruments[p.instrument].pixel_um
    where = f"profiles[{index}] ({p.name})"
    if p.image_file is not None:
        entries.append(("image", path(p.image_file)))
        if p.image_err_file is not None:
            entries.append(("image_err", path(p.image_err_file)))
        layout = p.image_layout
        skipped = 0 if layout is None else layout.first[1]  # pixels of the file left of the region
        entries += _changed([("x0_um", _grid_start(p.x_um, pixel_um, where) - skipped * pixel_um)], {"x0_um": 0.0})
        if layout is not None:
            entries += _changed([("profile_along", layout.along)], {"profile_along": "rows"})
            if layout.roi != (0, layout.shape[0], 0, layout.shape[1]):
                entries.append(("roi", list(layout.roi)))
            if layout.mask_file is not None:
                entries.append(("mask", path(layout.mask_file)))
    elif p.file is not None:
        entries.append(("file", path(p.file)))
    else:
        x_min = _grid_start(p.x_um, pixel_um, where)
        entries += [("x_min_um", x_min), ("x_max_um", x_min + len(p.x_um) * pixel_um)]
    return entries + _changed([(key, getattr(p, key)) for key in registry.part("profiles") if key != "distance_mm"],
                              registry.defaults("profiles"))


def _grid_start(x_um: np.ndarray, pixel_um: float, where: str) -> float:
    """The grid's left edge from which ``pixel_grid`` gives ``x_um`` back bit for bit
    (the nearest float to the centre minus half a pixel, or a neighbour a few ulps off)."""
    x_um = np.asarray(x_um, float)
    if x_um.ndim != 1 or len(x_um) < 2:
        raise FwdfitError(f"{where}: x_um needs at least two pixels")
    start = up = down = float(x_um[0] - 0.5 * pixel_um)
    candidates = [start]
    for _ in range(4):
        up, down = float(np.nextafter(up, math.inf)), float(np.nextafter(down, -math.inf))
        candidates += [up, down]
    for candidate in candidates:
        if np.array_equal(pixel_grid(candidate, candidate + len(x_um) * pixel_um, pixel_um), x_um):
            return candidate
    grid = pixel_grid(start, start + len(x_um) * pixel_um, pixel_um)
    if grid.shape == x_um.shape and np.allclose(grid, x_um, rtol=0.0, atol=1e-9 * pixel_um):
        return start
    raise FwdfitError(f"{where}: x_um is not a grid of pixel_um = {pixel_um:g} and the profile "
                      "has no file: a scene cannot hold it")


def _key(name: str) -> str:
    """A TOML key: bare where it may be, else quoted."""
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else _value(name)


def _value(value) -> str:
    """A TOML value: bool, string (basic, control characters escaped), int, float or list."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return '"' + "".join(f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c
                             for c in escaped) + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, int):  # a pixel index (roi)
        return str(value)
    return repr(float(value))
