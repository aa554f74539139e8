"""Scene files (TOML, docs/SCENE.md): parsing and validation into frozen specs.

Every error names the file and the key and is one line (``FwdfitError``). Every number
is checked against the validity domain of ``_limits`` (docs/SCENE.md, "Validity domain").
Units are those of the keys: µm, mm, m, degrees, Å, 1e-6 Å^-2, 1/m.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from . import _registry as registry
from .._errors import FwdfitError
from ._limits import (DOMAIN, MAX_DIVERGENCE, MAX_PIXELS, MAX_PSF_PIXELS, SEE, check_domain,
                      check_domain_rows)
from ._materials import MaterialConstants, constants_from_formula, constants_from_ncrystal
from ._design_spec import DesignSpec, read_design
from ._spectrum import BandSpectrum, GaussianLine, Spectrum, TabulatedSpectrum
from ..io._tables import read_columns


DEFAULT_ACCURACY = 1e-3


@dataclasses.dataclass(frozen=True)
class Layer:
    """One layer of the stack; ``same_as`` names the earlier layer it is tied to.

    ``density_scale`` multiplies the SLD and the whole mu(lambda) (table included).
    ``roughness_mrad``: RMS slope of the local normal of the layer's right-hand face.
    ``sld_end_e6_per_A2``, ``mu_end_per_m``: the values at the right-hand side of a graded
    layer (linear across it from ``sld_e6_per_A2``, ``mu_per_m``); NaN: uniform.
    """

    name: str
    thickness_um: float
    sld_e6_per_A2: float
    mu_per_m: float
    mu_per_m_per_A: float = 0.0
    same_as: str | None = None
    material: MaterialConstants | None = None
    density_scale: float = 1.0
    roughness_mrad: float = 0.0
    sld_end_e6_per_A2: float = math.nan
    mu_end_per_m: float = math.nan

    @classmethod
    def from_material(cls, name: str, thickness_um: float, material: MaterialConstants,
                      density_scale: float = 1.0) -> Layer:
        """A layer with the constants of ``material`` (``constants_from_formula`` or NCrystal)."""
        return cls(name, thickness_um, material.sld_e6_per_A2, material.mu_per_m,
                   material.mu_per_m_per_A, material=material, density_scale=density_scale)

    def tied(self, name: str) -> Layer:
        """A layer named ``name`` tied to this one (``same_as``): every value shared."""
        return dataclasses.replace(self, name=name, same_as=self.same_as or self.name)

    def mu_per_m_at(self, wavelength_A, right: bool = False) -> np.ndarray:
        """Attenuation (1/m) at wavelengths (Å), table and density scale included; at the
        right-hand side of a graded layer where ``right``."""
        lam = np.asarray(wavelength_A, dtype=float)
        end = self.mu_end_per_m if right and not math.isnan(self.mu_end_per_m) else self.mu_per_m
        mu = end + self.mu_per_m_per_A * lam
        if self.material is not None and self.material.mu_table is not None:
            mu = mu + self.material.mu_table(lam)
        return self.density_scale * mu


@dataclasses.dataclass(frozen=True)
class Sample:
    """The layer stack; ``drift_um_per_mm`` shifts each profile by drift * distance_mm
    (a stage or beam-axis misalignment); ``left_roughness_mrad`` is the RMS normal slope of
    the stack's first (left, vacuum | first layer) face, each layer's own is its right-hand face.
    ``rotation_deg``: an image's edge rotated in the image plane, its centre in profile r
    moved by tan(rotation) * (r - centre profile) * pixel_um (fit-image only).

    ``geometry``: ``"block"`` (layers side by side along x, ``depth_mm`` along the beam) or
    ``"cylinder"`` (concentric shells about an axis along the detector's columns at
    ``centre_um``: the layers from the outside in, the outermost of radius
    ``outer_radius_um``; ``core = "vacuum"`` a tube, else the innermost layer fills the
    core, a rod, whose thickness is the rest of the radius). A cylinder's ``depth_mm`` is
    its diameter (its extent along the beam), its tilt 0.
    """

    depth_mm: float
    tilt_deg: float
    centre_um: float
    layers: tuple[Layer, ...]
    drift_um_per_mm: float = 0.0
    left_roughness_mrad: float = 0.0
    rotation_deg: float = 0.0
    geometry: str = "block"
    outer_radius_um: float = math.nan
    core: str = ""  # a cylinder's core: "" the innermost layer (a rod), "vacuum" (a tube)

    @property
    def rod(self) -> bool:
        """A cylinder whose innermost layer fills the core."""
        return self.geometry == "cylinder" and self.core != CORE_VACUUM


@dataclasses.dataclass(frozen=True)
class Instrument:
    aperture: str  # "square" or "circular"
    aperture_mm: float
    aperture_distance_m: float
    pixel_um: float
    psf_fwhm_um: float = 0.0
    fresnel: bool = False


@dataclasses.dataclass(frozen=True)
class ImageLayout:
    """Where an image profile's rows come from in its image file (rows x columns, ``shape``):
    the region ``roi`` (row0, row1, col0, col1, half-open) and, with ``along = "columns"``,
    its columns as the profiles (the image transposed: the edge runs across the rows).
    ``mask_file``: the image whose non-zero pixels are left out, if any."""

    shape: tuple[int, int]
    roi: tuple[int, int, int, int]
    along: str = "rows"
    mask_file: Path | None = None

    @property
    def first(self) -> tuple[int, int]:
        """(profile, pixel) index in the file of the first profile's first pixel."""
        row0, _, col0, _ = self.roi
        return (row0, col0) if self.along == "rows" else (col0, row0)

    def profiles(self, image: np.ndarray) -> np.ndarray:
        """The file's image (shape) to the profiles (n_profiles, n_pixels): cut, transposed."""
        row0, row1, col0, col1 = self.roi
        region = image[row0:row1, col0:col1]
        return region if self.along == "rows" else region.T

    def image(self, profiles: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """The profiles (n_profiles, n_pixels) back in the file's shape, ``fill`` outside the region."""
        row0, row1, col0, col1 = self.roi
        out = np.full(self.shape, fill, dtype=profiles.dtype)
        out[row0:row1, col0:col1] = profiles if self.along == "rows" else profiles.T
        return out


@dataclasses.dataclass(frozen=True)
class Profile:
    """One measured or simulated profile: pixel centres ``x_um`` (n,), data if measured.

    Nuisances: the prediction is ``norm * T + background`` with the sample shifted
    sideways by ``shift_um``; ``file`` is the measured table's path, if any. An image
    profile (``image = "T.tif"``, for ``fwdfit fit-image``) holds rows of such profiles
    in ``image`` instead of ``T``, on the pixels ``x_um`` of its columns.
    """

    name: str
    distance_mm: float
    spectrum: str
    instrument: str
    x_um: np.ndarray
    T: np.ndarray | None = None
    T_err: np.ndarray | None = None
    shift_um: float = 0.0
    norm: float = 1.0
    background: float = 0.0
    file: Path | None = None
    image: np.ndarray | None = None  # (rows, n) normalised transmission, NaN = masked
    image_err: np.ndarray | None = None  # (rows, n) its 1-sigma errors, if given
    image_file: Path | None = None
    image_err_file: Path | None = None
    errors: str = ""  # "estimate": noise estimated from T on purpose; "": T_err where given
    image_layout: ImageLayout | None = None  # an image profile's region and orientation in its file


def pixel_count(x_min_um: float, x_max_um: float, pixel_um: float) -> int:
    """How many whole pixels of ``pixel_um`` fit from ``x_min_um`` to ``x_max_um``."""
    return int(math.floor((x_max_um - x_min_um) / pixel_um + 1e-6))


def pixel_grid(x_min_um: float, x_max_um: float, pixel_um: float) -> np.ndarray:
    """Centres (n,) of the whole pixels of ``pixel_um`` from ``x_min_um`` to ``x_max_um``:
    a profile's ``x_um`` as a scene's ``x_min_um``/``x_max_um`` (or an image's ``x0_um``
    and width) give it."""
    return x_min_um + (np.arange(max(pixel_count(x_min_um, x_max_um, pixel_um), 0)) + 0.5) * pixel_um


@dataclasses.dataclass(frozen=True)
class FitSpec:
    vary: tuple[str, ...] = ()
    bounds: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    per_row: tuple[str, ...] = ()  # fit-image: parameters fitted per row (besides the centre)


@dataclasses.dataclass(frozen=True)
class Scene:
    sample: Sample
    instruments: dict[str, Instrument]  # "" is the default [instrument]
    spectra: dict[str, Spectrum]
    profiles: tuple[Profile, ...]
    fit: FitSpec = dataclasses.field(default_factory=FitSpec)
    accuracy: float = DEFAULT_ACCURACY
    path: Path | None = None
    design: DesignSpec = dataclasses.field(default_factory=DesignSpec)

    def input_files(self) -> tuple[Path, ...]:
        """Every file the scene was read from: the scene file, profile tables and images,
        spectrum tables (an output folder must hold none of them)."""
        files = [self.path]
        for p in self.profiles:
            files += [p.file, p.image_file, p.image_err_file, p.image_layout and p.image_layout.mask_file]
        files += [getattr(s, "path", None) for s in self.spectra.values()]
        files += [getattr(getattr(s, "table", None), "path", None) for s in self.spectra.values()]
        return tuple(dict.fromkeys(Path(f) for f in files if f is not None))


CORE_VACUUM = "vacuum"
_SAMPLE_KEYS = {"layers", "geometry", "core", *registry.part("sample")}
_LAYER_KEYS = {"name", "material", "density_g_cm3", "ncrystal", "same_as", *registry.part("layers")}
_FROM_DATA = tuple(key for key, q in registry.part("layers").items() if q.from_data)  # a fit may leave them out
_INSTRUMENT_KEYS = {"aperture", "aperture_mm", "aperture_distance_m", "pixel_um",
                    "psf_fwhm_um", "fresnel"}
_IMAGE_KEYS = ("image_err", "x0_um", "profile_along", "roi", "mask")  # only with image = ...
_PROFILE_KEYS = {"name", "spectrum", "instrument", "file", "x_min_um", "x_max_um", "image", *_IMAGE_KEYS,
                 "errors", *registry.part("profiles")}
PROFILE_ALONG = ("rows", "columns")
ERRORS_ESTIMATE = "estimate"  # errors = "estimate": the noise from the data, a T_err column ignored
# Columns a profile table may hold besides x_um, T, T_err, read past: those fwdfit writes
# (simulate, fit), the shipped example's truth, and the McStas reference tables'.
PASSIVE_COLUMNS = ("T_att", "T_att_err", "T_att_true", "T_model", "T_corrected", "T_corrected_err",
                   "T_err_uncorr", "I_sample", "I_sample_err", "I_open", "I_open_err", "N_open_rays")
_BAND_KEYS = ("lambda_min_A", "lambda_max_A")
_TOP_KEYS = {"sample", "instrument", "instruments", "spectra", "profiles", "fit", "model", "design"}


class _Reader:
    """Typed access to one TOML table, with errors that name the file and key."""

    def __init__(self, path: Path, table: Any, where: str, allowed: set[str]):
        self.path, self.where = path, where
        if not isinstance(table, dict):
            self.fail(where, "must be a table")
        unknown = sorted(set(table) - allowed)
        if unknown:
            self.fail(self.key(unknown[0]), "unknown key")
        self.table = table

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def fail(self, key: str, message: str):
        raise FwdfitError(f"{self.path}: {key}: {message}")

    def has(self, name: str) -> bool:
        return name in self.table

    def number(self, name, default=None, *, minimum=None, positive=False) -> float:
        if name not in self.table:
            if default is None:
                self.fail(self.key(name), "missing")
            return default
        value = self.table[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(self.key(name), f"must be a finite number, got {value!r}")
        if name in DOMAIN:
            check_domain(name, value, f"{self.path}: {self.key(name)}")
        if positive and value <= 0:
            self.fail(self.key(name), f"must be positive, got {value}")
        if minimum is not None and value < minimum:
            self.fail(self.key(name), f"must be >= {minimum}, got {value}")
        return float(value)

    def string(self, name, default=None, choices=None) -> str:
        if name not in self.table:
            if default is None:
                self.fail(self.key(name), "missing")
            return default
        value = self.table[name]
        if not isinstance(value, str) or not value:
            self.fail(self.key(name), f"must be a non-empty string, got {value!r}")
        if choices and value not in choices:
            self.fail(self.key(name), f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def boolean(self, name, default: bool) -> bool:
        value = self.table.get(name, default)
        if not isinstance(value, bool):
            self.fail(self.key(name), f"must be true or false, got {value!r}")
        return value


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file; profile and spectrum files are read relative to it."""
    path = Path(path)
    try:
        with open(path, "rb") as stream:
            document = tomllib.load(stream)
    except FileNotFoundError:
        raise FwdfitError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise FwdfitError(f"{path}: is a folder, not a scene file") from None
    except UnicodeDecodeError:
        raise FwdfitError(f"{path}: not a text TOML file (not UTF-8)") from None
    except tomllib.TOMLDecodeError as error:
        raise FwdfitError(f"{path}: not valid TOML ({error})") from None
    top = _Reader(path, document, "", _TOP_KEYS)
    if not top.has("sample"):
        top.fail("sample", "missing")
    fit = _fit(path, document.get("fit", {}))
    sample = _sample(path, document["sample"], fit.vary)
    instruments = _instruments(path, document)
    spectra = _spectra(path, document.get("spectra", {}))
    profiles = _profiles(path, document.get("profiles", []), instruments, spectra)
    model = _Reader(path, document.get("model", {}), "model", {"accuracy"})
    accuracy = model.number("accuracy", DEFAULT_ACCURACY, positive=True)
    design = read_design(path, document.get("design", {}), spectra)
    _check_combinations(path, sample, instruments, profiles)
    return Scene(sample, instruments, spectra, profiles, fit, accuracy, path, design)


def _check_combinations(path: Path, sample: Sample, instruments: dict[str, Instrument],
                        profiles: tuple[Profile, ...]) -> None:
    """The validity domain's limits on combinations of keys and on constants derived from
    a material: each layer's SLD and mu, each instrument's blur against its pixel, each
    profile's detector outside the sample and the aperture's angular size (paraxial).

    The tilted stack reaches ``reach`` mm up- and downstream of its centre: half its depth
    plus half its width times |sin(tilt)| (the model's interfaces span the depth about
    centres moved along the beam by the tilt; a 50 mm wide stack tilted by 0.24° reaches
    0.1 mm further than its depth alone).
    """
    for index, layer in enumerate(sample.layers):
        if layer.material is not None and layer.same_as is None:
            for key in ("sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A"):
                check_domain(key, getattr(layer, key),
                             f"{path}: sample.layers[{index}]: {key} of its material")
    for name, instrument in instruments.items():
        if instrument.psf_fwhm_um > MAX_PSF_PIXELS * instrument.pixel_um:
            raise FwdfitError(
                f"{path}: {'instruments.' + name if name else 'instrument'}.psf_fwhm_um: "
                f"{instrument.psf_fwhm_um:g} is more than {MAX_PSF_PIXELS:g} pixels of "
                f"{instrument.pixel_um:g} um ({SEE})")
    tilt = math.radians(sample.tilt_deg)
    width_mm = 1e-3 * sum(t for t in (layer.thickness_um for layer in sample.layers) if math.isfinite(t))
    reach = 0.5 * sample.depth_mm + 0.5 * width_mm * abs(math.sin(tilt))
    if math.isnan(reach):  # a cylinder's radius left to the fit: checked once fitted
        reach = 0.0
    for index, profile in enumerate(profiles):
        where = f"{path}: profiles[{index}].distance_mm"
        if profile.distance_mm <= reach:
            needs = ("the outer radius" if sample.geometry == "cylinder"
                     else "depth_mm / 2 + half the stack's width x |sin(tilt)|")
            raise FwdfitError(f"{where}: {profile.distance_mm:g} puts the detector inside the "
                              f"sample (needs > {reach:g}: {needs}; {SEE})")
        instrument = instruments[profile.instrument]
        to_aperture_mm = 1e3 * instrument.aperture_distance_m - profile.distance_mm - reach
        if not instrument.aperture_mm <= MAX_DIVERGENCE * to_aperture_mm:
            raise FwdfitError(
                f"{where}: {profile.distance_mm:g} leaves {to_aperture_mm:g} mm from the sample "
                f"to the aperture, which then spans more than {MAX_DIVERGENCE:g} rad "
                f"(aperture_mm = {instrument.aperture_mm:g}; the model is paraxial; {SEE})")


def _sample(path: Path, table: Any, vary: tuple[str, ...]) -> Sample:
    reader = _Reader(path, table, "sample", _SAMPLE_KEYS)
    geometry = reader.string("geometry", "block", choices=registry.GEOMETRIES)
    _refuse_others(reader, table, geometry, "sample", {"core"} if geometry != "cylinder" else set())
    layers_table = table.get("layers")
    if not isinstance(layers_table, list) or not layers_table:
        reader.fail("sample.layers", "at least one [[sample.layers]] is needed")
    layers: list[Layer] = []
    for index, layer_table in enumerate(layers_table):
        layers.append(_layer(path, layer_table, f"sample.layers[{index}]", layers, vary, geometry))
    if geometry == "cylinder":
        return _cylinder(reader, tuple(layers), vary)
    return Sample(layers=tuple(layers), **_plain(reader, "sample"))


def _refuse_others(reader: _Reader, table: dict, geometry: str, part: str, more: set[str] = frozenset()) -> None:
    """Fail on the first key of ``table`` that the registry keeps for other geometries (or is in ``more``)."""
    others = {key for key, q in registry.part(part).items() if geometry not in q.geometries} | set(more)
    refused = sorted(others & set(table))
    if refused:
        reader.fail(reader.key(refused[0]), f"a {geometry} does not take this key")


def _cylinder(reader: _Reader, layers: tuple[Layer, ...], vary: tuple[str, ...]) -> Sample:
    """A cylinder's sample: its radius (left out only where fit.vary names it), its core,
    and a rod's innermost layer filling the rest of the radius."""
    radius = reader.number("outer_radius_um", math.nan if "sample.outer_radius_um" in vary else None,
                           positive=True)
    core = reader.string("core", "", choices=(CORE_VACUUM,))
    shells = layers if core == CORE_VACUUM else layers[:-1]
    for index, layer in enumerate(shells):
        if math.isnan(layer.thickness_um) and f"layers.{layer.same_as or layer.name}.thickness_um" not in vary:
            reader.fail(f"sample.layers[{index}].thickness_um", "missing")
    reach = sum(layer.thickness_um for layer in shells)
    for index, layer in enumerate(shells):
        if sum(l.thickness_um for l in shells[:index + 1]) > radius:
            reader.fail(f"sample.layers[{index}].thickness_um", f"the shells reach {reach:g} um in from the "
                        f"outer radius {radius:g} um: past the axis")
    if core != CORE_VACUUM:
        inner, index = layers[-1], len(layers) - 1
        rest = radius - reach
        if f"layers.{inner.name}.thickness_um" in vary:
            reader.fail("fit.vary", f"layers.{inner.name}.thickness_um: the innermost layer of a rod fills the "
                        "rest of the radius (vary sample.outer_radius_um or the shells' thicknesses)")
        if not (math.isnan(inner.thickness_um) or math.isclose(inner.thickness_um, rest, rel_tol=1e-9, abs_tol=1e-6)):
            reader.fail(f"sample.layers[{index}].thickness_um", f"{inner.thickness_um:g}: the innermost layer of "
                        f"a rod fills the rest of the radius, {rest:g} um (leave the key out)")
        layers = layers[:-1] + (dataclasses.replace(inner, thickness_um=rest),)
    return Sample(depth_mm=2e-3 * radius, tilt_deg=0.0, layers=layers, geometry="cylinder",
                  outer_radius_um=radius, core=core, **_plain(reader, "sample", "cylinder"))


def _plain(reader: _Reader, part: str, geometry: str | None = None) -> dict[str, float]:
    """A scene part's fitted quantities that are read as they are (``_registry``: neither a
    start from the data nor a material's constant), by key (those ``geometry`` takes)."""
    return {key: reader.number(key, q.default, positive=q.positive)
            for key, q in registry.part(part, geometry).items() if not (q.from_data or q.material)}


def _layer(path: Path, table: Any, where: str, earlier: list[Layer], vary: tuple[str, ...] = (),
           geometry: str = "block") -> Layer:
    """One layer. A value named in ``vary`` may be left out: it is NaN, a start the fit
    estimates from the data (a rod's innermost layer's thickness: the rest of the radius,
    ``_cylinder``)."""
    reader = _Reader(path, table, where, _LAYER_KEYS)
    _refuse_others(reader, table, geometry, "layers")
    name = reader.string("name")
    optional = {key for key in _FROM_DATA if f"layers.{name}.{key}" in vary}
    if geometry == "cylinder":
        optional.add("thickness_um")  # a rod's innermost layer; _cylinder checks the others
    if any(layer.name == name for layer in earlier):
        reader.fail(reader.key("name"), f"duplicate layer name {name!r}")
    if reader.has("same_as"):
        target = reader.string("same_as")
        others = sorted(set(table) - {"name", "same_as"})
        if others:
            reader.fail(reader.key(others[0]), "a same_as layer takes every other key from its twin")
        tied = next((layer for layer in earlier if layer.name == target), None)
        if tied is None:
            reader.fail(reader.key("same_as"), f"names no earlier layer: {target!r}")
        return tied.tied(name)
    material = None
    if reader.has("material") or reader.has("ncrystal"):
        material = _material(reader)
    explicit = {key: reader.number(key) for key in ("sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A")
                if reader.has(key)}
    if material is None and not {"sld_e6_per_A2", "mu_per_m"} <= explicit.keys() | optional:
        reader.fail(where, "needs a material (material + density_g_cm3, or ncrystal) "
                    "or both sld_e6_per_A2 and mu_per_m (either may be left out when fit.vary names it)")
    if material is None:
        explicit = {key: math.nan for key in ("sld_e6_per_A2", "mu_per_m")} | explicit
    if "mu_per_m" in explicit and explicit["mu_per_m"] < 0:
        reader.fail(reader.key("mu_per_m"), "must be >= 0")
    base = material or MaterialConstants(0.0, 0.0)
    return Layer(
        name=name,
        thickness_um=reader.number("thickness_um", math.nan if "thickness_um" in optional else None,
                                   minimum=0.0),
        sld_e6_per_A2=explicit.get("sld_e6_per_A2", base.sld_e6_per_A2),
        mu_per_m=explicit.get("mu_per_m", base.mu_per_m),
        mu_per_m_per_A=explicit.get("mu_per_m_per_A", base.mu_per_m_per_A
                                    if "mu_per_m" not in explicit else 0.0),
        material=material,
        **_plain(reader, "layers", geometry),
    )


def _material(reader: _Reader) -> MaterialConstants:
    key = "ncrystal" if reader.has("ncrystal") else "material"
    name = reader.string(key)  # the reader's own errors name the file already
    density = None if key == "ncrystal" else reader.number("density_g_cm3", positive=True)
    try:
        if density is None:
            return constants_from_ncrystal(name)
        return constants_from_formula(name, density)
    except FwdfitError as error:
        reader.fail(reader.key(key), str(error))


def _instrument(path: Path, table: Any, where: str) -> Instrument:
    reader = _Reader(path, table, where, _INSTRUMENT_KEYS)
    return Instrument(
        aperture=reader.string("aperture", choices=("square", "circular")),
        aperture_mm=reader.number("aperture_mm", positive=True),
        aperture_distance_m=reader.number("aperture_distance_m", positive=True),
        pixel_um=reader.number("pixel_um", positive=True),
        psf_fwhm_um=reader.number("psf_fwhm_um", 0.0, minimum=0.0),
        fresnel=reader.boolean("fresnel", False),
    )


def _instruments(path: Path, document: dict) -> dict[str, Instrument]:
    instruments = {}
    if "instrument" in document:
        instruments[""] = _instrument(path, document["instrument"], "instrument")
    extra = document.get("instruments", {})
    if not isinstance(extra, dict):
        raise FwdfitError(f"{path}: instruments: must be a table of named instruments")
    for name, table in extra.items():
        instruments[name] = _instrument(path, table, f"instruments.{name}")
    if not instruments:
        raise FwdfitError(f"{path}: instrument: missing")
    return instruments


def _spectra(path: Path, table: Any) -> dict[str, Spectrum]:
    if not isinstance(table, dict) or not table:
        raise FwdfitError(f"{path}: spectra: at least one [spectra.NAME] is needed")
    spectra = {}
    for name, entry in table.items():
        where = f"spectra.{name}"
        reader = _Reader(path, entry, where, {"file", "wavelength_A", "fwhm_rel", *_BAND_KEYS})
        band = [key for key in _BAND_KEYS if reader.has(key)]
        if band and (reader.has("wavelength_A") or reader.has("fwhm_rel")):
            reader.fail(where, "a band (lambda_min_A, lambda_max_A) and a line "
                        "(wavelength_A, fwhm_rel) cannot be combined")
        if band and len(band) < 2:
            reader.fail(reader.key(({*_BAND_KEYS} - {*band}).pop()), "missing (a band needs both limits)")
        if not reader.has("file") and not band:  # the domain's limits hold GaussianLine's own checks
            spectra[name] = GaussianLine(reader.number("wavelength_A", positive=True),
                                         reader.number("fwhm_rel", minimum=0.0))
            continue
        limits = [reader.number(key, positive=True) for key in _BAND_KEYS] if band else []
        for key, value in zip(_BAND_KEYS, limits):
            check_domain("lambda_A", value, f"{path}: {reader.key(key)}")
        file = path.parent / reader.string("file") if reader.has("file") else None
        try:  # the table's errors name the table; this names the scene and key too
            table = None
            if file is not None:
                columns = read_columns(file, ["lambda_A", "weight"])
                check_domain_rows("lambda_A", columns["lambda_A"], f"{file}: lambda_A")
                table = TabulatedSpectrum(columns["lambda_A"], columns["weight"], file)
            spectra[name] = BandSpectrum(*limits, table) if band else table
        except FwdfitError as error:
            reader.fail(where, str(error))
    return spectra


def _profiles(path, table, instruments, spectra) -> tuple[Profile, ...]:
    if not isinstance(table, list) or not table:
        raise FwdfitError(f"{path}: profiles: at least one [[profiles]] is needed")
    profiles = []
    for index, entry in enumerate(table):
        reader = _Reader(path, entry, f"profiles[{index}]", _PROFILE_KEYS)
        name = reader.string("name")
        if any(p.name == name for p in profiles):
            reader.fail(reader.key("name"), f"duplicate profile name {name!r}")
        if name in (".", "..") or any(char in name for char in "/\\\0") or len(name.encode()) > 200:
            reader.fail(reader.key("name"), f"{name!r} cannot name an output file "
                        "(no / or \\, at most 200 bytes)")
        spectrum = reader.string("spectrum")
        if spectrum not in spectra:
            reader.fail(reader.key("spectrum"), f"no [spectra.{spectrum}] in the scene")
        instrument = reader.string("instrument", "")
        if instrument not in instruments:
            reader.fail(reader.key("instrument"), f"no instrument named {instrument!r}")
        pixel_um = instruments[instrument].pixel_um
        T = T_err = file = image = image_err = image_file = err_file = None
        for key, needs in (("image", "file"), ("image", "x_min_um"), ("image", "x_max_um"),
                           ("image_err", "file"), ("x0_um", "file")):
            if reader.has(key) and reader.has(needs):
                reader.fail(reader.key(key), f"a profile takes either {key} or {needs}, not both")
        if reader.has("errors") and not reader.has("file"):
            reader.fail(reader.key("errors"), "only for a measured profile (file = ...)")
        for key in _IMAGE_KEYS:
            if reader.has(key) and not reader.has("image"):
                reader.fail(reader.key(key), "only for an image profile (image = ...)")
        layout = None
        if reader.has("image"):
            image_file = path.parent / reader.string("image")
            err_file = path.parent / reader.string("image_err") if reader.has("image_err") else None
            mask_file = path.parent / reader.string("mask") if reader.has("mask") else None
            image, image_err = read_image(reader, image_file, err_file)
            layout = _image_layout(reader, image.shape, mask_file)
            image, image_err = laid_out(reader, layout, image, image_err)
            x0_um = reader.number("x0_um", 0.0) + layout.first[1] * pixel_um
            x_um = pixel_grid(x0_um, x0_um + image.shape[1] * pixel_um, pixel_um)
        elif reader.has("file"):
            file = path.parent / reader.string("file")
            columns = read_columns(file, ["x_um", "T"], ["T_err"], passive=PASSIVE_COLUMNS)
            x_um, T, T_err = columns["x_um"], columns["T"], columns.get("T_err")
            if reader.string("errors", "", choices=(ERRORS_ESTIMATE,)) == ERRORS_ESTIMATE:
                T_err = None
            if T_err is not None and np.any(T_err <= 0):
                reader.fail(reader.key("file"), "T_err must be > 0 everywhere")
            if np.any(np.diff(x_um) <= 0):
                reader.fail(reader.key("file"), "x_um must increase")
            if len(x_um) > MAX_PIXELS:
                reader.fail(reader.key("file"), f"{len(x_um)} rows, more than {MAX_PIXELS} ({SEE})")
            for column, values in columns.items():
                check_domain_rows(column, values, f"{path}: {reader.key('file')}: {file}: {column}")
        else:
            x_min, x_max = reader.number("x_min_um"), reader.number("x_max_um")
            n_pixels = pixel_count(x_min, x_max, pixel_um)
            if n_pixels < 2:
                reader.fail(reader.key("x_max_um"), "the pixel grid needs x_max_um > x_min_um + 2 pixels")
            if n_pixels > MAX_PIXELS:
                reader.fail(reader.key("x_max_um"),
                            f"the pixel grid has {n_pixels} pixels, more than {MAX_PIXELS} ({SEE})")
            x_um = pixel_grid(x_min, x_max, pixel_um)
        profiles.append(Profile(
            name=name, spectrum=spectrum, instrument=instrument, x_um=x_um, T=T, T_err=T_err,
            **_plain(reader, "profiles"), file=file, image=image, image_err=image_err,
            image_file=image_file, image_err_file=err_file, errors=reader.string("errors", ""),
            image_layout=layout))
    return tuple(profiles)


def _image_layout(reader: _Reader, shape: tuple[int, int], mask_file: Path | None) -> ImageLayout:
    """profile_along and roi of an image profile, checked against its image's shape."""
    along = reader.string("profile_along", "rows", choices=PROFILE_ALONG)
    roi = (0, shape[0], 0, shape[1])
    if reader.has("roi"):
        value = reader.table["roi"]
        if (not isinstance(value, list) or len(value) != 4
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
            reader.fail(reader.key("roi"), f"must be four whole pixel indices [row0, row1, col0, col1], got {value!r}")
        row0, row1, col0, col1 = value
        if not (0 <= row0 < row1 <= shape[0] and 0 <= col0 < col1 <= shape[1]):
            reader.fail(reader.key("roi"), f"{value} is not a region of the image ({shape[0]} x {shape[1]} pixels: "
                        f"0 <= row0 < row1 <= {shape[0]}, 0 <= col0 < col1 <= {shape[1]})")
        roi = tuple(value)
    return ImageLayout(tuple(shape), roi, along, mask_file)


def laid_out(reader: _Reader, layout: ImageLayout, image: np.ndarray, image_err: np.ndarray | None):
    """The image (and errors) of a file as its profiles (``layout``), masked pixels NaN;
    the profiles must be at least 16 and at most MAX_PIXELS pixels long."""
    if layout.mask_file is not None:
        mask = _read_tiff_2d(reader, "mask", layout.mask_file, floats=False)
        if mask.shape != image.shape:
            reader.fail(reader.key("mask"), f"{layout.mask_file.name} is {mask.shape[0]} x {mask.shape[1]} pixels, "
                        f"the image {image.shape[0]} x {image.shape[1]}")
        image = np.where(mask != 0, np.nan, image)
    image = layout.profiles(image)
    image_err = None if image_err is None else layout.profiles(image_err)
    what = "columns" if layout.along == "rows" else "rows"
    if image.shape[1] > MAX_PIXELS:
        reader.fail(reader.key("image"), f"{image.shape[1]} {what} in a profile, more than {MAX_PIXELS} ({SEE})")
    if image.shape[1] < 16:
        reader.fail(reader.key("image"), f"{image.shape[1]} {what} in a profile: it needs at least 16 pixels")
    return image, image_err


def read_image(reader: _Reader, image_file: Path, err_file: Path | None):
    """An image profile's normalised transmission (rows, n) and its errors (or None), float64.

    Non-finite pixels (in either) are masked: NaN in the image. Errors must be > 0 where
    finite and have the image's shape.
    """
    image = _read_tiff_2d(reader, "image", image_file)
    image_err = None if err_file is None else _read_tiff_2d(reader, "image_err", err_file)
    if image_err is not None:
        if image_err.shape != image.shape:
            reader.fail(reader.key("image_err"), f"{err_file.name} is {image_err.shape[0]} x "
                        f"{image_err.shape[1]} pixels, the image {image.shape[0]} x {image.shape[1]}")
        if np.any(image_err[np.isfinite(image_err)] <= 0):
            reader.fail(reader.key("image_err"), "errors must be > 0 where given")
        image = np.where(np.isfinite(image_err), image, np.nan)
    return np.where(np.isfinite(image), image, np.nan), image_err


def with_image(scene: Scene, image_file: str | Path) -> Scene:
    """The scene with its one image profile's image read from ``image_file`` (checked as
    ``image = ...`` is), for a series of images fitted with one scene as template. The new
    image must have the template's rows and columns; the template's ``image_err`` (its
    own image's errors) is dropped, so each image's noise is estimated from the image.
    """
    index = next(i for i, p in enumerate(scene.profiles) if p.image is not None)
    profile = scene.profiles[index]
    reader = _Reader(scene.path, {}, f"profiles[{index}]", set())
    image, _ = read_image(reader, Path(image_file), None)
    shape = profile.image_layout.shape
    if image.shape != shape:
        raise FwdfitError(f"{image_file}: {image.shape[0]} x {image.shape[1]} pixels, the template image "
                          f"{profile.image_file.name} {shape[0]} x {shape[1]}")
    image, _ = laid_out(reader, profile.image_layout, image, None)
    replaced = dataclasses.replace(profile, image=image, image_err=None, image_file=Path(image_file),
                                   image_err_file=None)
    profiles = scene.profiles[:index] + (replaced,) + scene.profiles[index + 1:]
    return dataclasses.replace(scene, profiles=profiles)


def _read_tiff_2d(reader: _Reader, key: str, file: Path, floats: bool = True) -> np.ndarray:
    import tifffile

    try:
        data = tifffile.imread(file)
    except FileNotFoundError:
        reader.fail(reader.key(key), f"{file}: file not found")
    except Exception as error:  # tifffile raises many types for a damaged or foreign file
        message = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        reader.fail(reader.key(key), f"{file}: not a readable TIFF image ({message})")
    data = np.squeeze(data)
    if data.ndim != 2 or min(data.shape) < 1:
        reader.fail(reader.key(key), f"{file}: needs one 2-D image (rows x columns), got shape {data.shape}")
    if floats and not np.issubdtype(data.dtype, np.floating):
        reader.fail(reader.key(key), f"{file}: pixel type {data.dtype}: needs a float image "
                    "of normalised transmission, not raw counts")
    return data.astype(float)


def _fit(path: Path, table: Any) -> FitSpec:
    reader = _Reader(path, table, "fit", {"vary", "bounds", "per_row"})
    vary = table.get("vary", [])
    if not isinstance(vary, list) or not all(isinstance(v, str) for v in vary):
        reader.fail("fit.vary", "must be a list of parameter names")
    per_row = table.get("per_row", [])
    if not isinstance(per_row, list) or not all(isinstance(v, str) for v in per_row):
        reader.fail("fit.per_row", "must be a list of parameter names")
    bounds_table = table.get("bounds", {})
    if not isinstance(bounds_table, dict):
        reader.fail("fit.bounds", "must be a table of name = [low, high]")
    bounds = {}
    for name, pair in bounds_table.items():
        ok = (isinstance(pair, list) and len(pair) == 2
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair))
        if not ok:
            reader.fail(f"fit.bounds.{name}", "must be [low, high]")
        if not pair[0] < pair[1]:
            reader.fail(f"fit.bounds.{name}", f"low must be below high, got {pair}")
        bounds[name] = (float(pair[0]), float(pair[1]))
    return FitSpec(tuple(vary), bounds, tuple(per_row))
