"""Test helpers: reference tables, scenes built on the fly, edge metrics, exact
straight-ray Beer-Lambert profiles and central differences.

Everything here is NumPy (or plain JAX calls of the public API) and independent of the
model's internals, so it can serve as the reference the model is checked against.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

DATA = Path(__file__).parent / "data"
MCSTAS = DATA / "mcstas"
RAYTRACE = DATA / "raytrace"

# Every shipped reference scene, by case name.
REFERENCE_SCENES = {
    "mcstas_boa_tilt0.00": MCSTAS / "scene_boa_tilt0.00.toml",
    "mcstas_boa_tilt0.24": MCSTAS / "scene_boa_tilt0.24.toml",
    "mcstas_icon_tilt0.00": MCSTAS / "scene_icon_tilt0.00.toml",
    "mcstas_icon_tilt0.24": MCSTAS / "scene_icon_tilt0.24.toml",
    "raytrace_al_boa_tilt0": RAYTRACE / "al_boa_tilt0" / "scene.toml",
    "raytrace_al_boa_tilt0.24_psf": RAYTRACE / "al_boa_tilt0.24_psf" / "scene.toml",
    "raytrace_al_icon_tilt0.24": RAYTRACE / "al_icon_tilt0.24" / "scene.toml",
    "raytrace_oxide5_boa": RAYTRACE / "oxide5_boa" / "scene.toml",
}
BOA_SPECTRUM = MCSTAS / "spectrum_boa.csv"


# --------------------------------------------------------------------------- reference tables


def read_table(path: Path) -> dict[str, np.ndarray]:
    """A CSV table with a header row, as a dict of float columns."""
    with open(path, encoding="utf-8") as stream:
        header = stream.readline().strip().split(",")
    rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {name.strip(): rows[:, i] for i, name in enumerate(header)}


def load_reference(case_dir: Path, name: str) -> dict[str, np.ndarray]:
    """One reference profile as ``x_um, T, T_err, T_att, T_att_err`` (n_pixel,) arrays.

    McStas folders hold ``<name>.csv`` (x_um,T,T_err,T_err_uncorr) and a separate run
    ``<name>_attenuation_only.csv`` whose T column is T_att; ray-tracer folders hold
    both in ``<name>.csv`` (x_um,T,T_err,T_att,T_att_err).
    """
    case_dir = Path(case_dir)
    main = read_table(case_dir / f"{name}.csv")
    if "T_att" in main:
        return {k: main[k] for k in ("x_um", "T", "T_err", "T_att", "T_att_err")}
    att = read_table(case_dir / f"{name}_attenuation_only.csv")
    if not np.array_equal(att["x_um"], main["x_um"]):
        raise ValueError(f"{case_dir}/{name}: the attenuation-only run has another pixel grid")
    return {"x_um": main["x_um"], "T": main["T"], "T_err": main["T_err"],
            "T_att": att["T"], "T_att_err": att["T_err"]}


# --------------------------------------------------------------------------- edge metrics


def smoothing_pixels(distance_mm: float, aperture_mm: float, aperture_distance_m: float,
                     pixel_um: float) -> int:
    """Running-mean width (pixels) used before taking extrema: an eighth of the penumbra.

    The penumbra Delta * D / L sets the width of the edge features at distance Delta
    (6 µm = 2.5 pixels at 1.1 mm, 180 µm = 75 pixels at 34.4 mm for BOA). A running mean
    over an eighth of it is 1 pixel (none) up to 4.8 mm and 9 pixels at 34.4 mm: it
    averages the reference's Monte Carlo noise (single-bin errors reach 5-10 % of the
    small far-distance peaks) down by up to 3x and lowers those peaks by at most ~25 %,
    identically for model and reference.
    """
    penumbra_um = distance_mm * 1e3 * aperture_mm / (aperture_distance_m * 1e3)
    return max(1, int(penumbra_um / (8.0 * pixel_um)))


def running_mean(values: np.ndarray, n: int) -> np.ndarray:
    """Centred running mean over n pixels, edges extended with their end values."""
    if n <= 1:
        return np.asarray(values, float)
    padded = np.pad(np.asarray(values, float), n, mode="edge")
    return np.convolve(padded, np.ones(n) / n, mode="same")[n:-n]


def edge_heights(x_um, T, T_att_baseline, centre_um: float, n_smooth: int):
    """Gain-peak height and loss-dip depth at each edge: ``[(gain, loss) left, (gain, loss) right]``.

    T and the baseline are first smoothed by ``running_mean(., n_smooth)``. On each side
    of the sample (x < centre, x > centre):

    - gain = max(T) - 1: how far the refracted and reflected rays lift the open beam
      just outside the edge;
    - loss = T_att_baseline(x_min) - T(x_min), x_min where T is smallest: how far the
      dip inside the edge falls below the attenuation-only profile, i.e. the refraction
      signal, not the attenuation.

    Model and reference are compared with the same function, the same ``n_smooth`` and
    the same baseline (the reference's T_att), so a difference is a difference in T.
    """
    x_um = np.asarray(x_um)
    T_s, base_s = running_mean(T, n_smooth), running_mean(T_att_baseline, n_smooth)
    heights = []
    for side in (x_um < centre_um, x_um > centre_um):
        t, b = T_s[side], base_s[side]
        i = int(np.argmin(t))
        heights.append((float(t.max() - 1.0), float(b[i] - t[i])))
    return heights


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


# --------------------------------------------------------------------------- scenes on the fly


def scene_differences(a, b, where: str = "scene") -> list[str]:
    """Where two scenes (or any of their parts) differ, field by field: arrays bit for bit
    (NaN equal to NaN), paths as the files they name; a scene's own ``path`` is ignored."""
    import dataclasses

    if dataclasses.is_dataclass(a) and type(a) is type(b):
        return [d for f in dataclasses.fields(a) if f.compare and not (where == "scene" and f.name == "path")
                for d in scene_differences(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")]
    if isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys():
        return [d for k in a for d in scene_differences(a[k], b[k], f"{where}[{k!r}]")]
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in scene_differences(x, y, f"{where}[{i}]")]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        same = (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype
                and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
        return [] if same else [where]
    if isinstance(a, Path) and isinstance(b, Path):
        return [] if a.resolve() == b.resolve() else [f"{where}: {a} != {b}"]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if type(a) is type(b) and a == b else [f"{where}: {a!r} != {b!r}"]


def make_scene(layers, *, profiles, spectrum, depth_mm=2.0, tilt_deg=0.0, centre_um=0.0,
               aperture="square", aperture_mm=40.0, aperture_distance_m=7.5, pixel_um=2.4,
               psf_fwhm_um=0.0, fresnel=False, vary=()):
    """A ``Scene`` value with one instrument and one spectrum named ``s``.

    layers: ``Layer`` values; profiles: list of (name, distance_mm, x_min_um, x_max_um);
    spectrum: a spectrum value (``white_beam()``, ``GaussianLine``).
    """
    import fwdfit

    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=depth_mm, tilt_deg=tilt_deg, centre_um=centre_um, layers=tuple(layers)),
        instruments={"": fwdfit.Instrument(aperture, aperture_mm, aperture_distance_m, pixel_um,
                                           psf_fwhm_um=psf_fwhm_um, fresnel=fresnel)},
        spectra={"s": spectrum},
        profiles=tuple(fwdfit.Profile(name, distance_mm, "s", "", fwdfit.pixel_grid(x_min, x_max, pixel_um))
                       for name, distance_mm, x_min, x_max in profiles),
        fit=fwdfit.FitSpec(tuple(vary)))


def write_scene(folder: Path, *args, name: str = "scene.toml", **kwargs):
    """Save ``make_scene(*args, **kwargs)`` as ``folder/name`` and load it (validated)."""
    import fwdfit

    return fwdfit.load_scene(fwdfit.save_scene(make_scene(*args, **kwargs), Path(folder) / name))


def small_scene(values: dict, *, file: Path | None = None, vary=(), bounds=None):
    """One Al block (mu = 9.06 + 0.774 lambda /m), the ICON 4.6 Å line (circular 40 mm
    aperture at 5.5 m), one profile ``line`` at 1.1 mm over +-600 µm, read from ``file`` if
    given. ``values``: ``sample.centre_um``, ``layers.Al.thickness_um``,
    ``layers.Al.sld_e6_per_A2``."""
    import fwdfit

    layer = fwdfit.Layer("Al", values["layers.Al.thickness_um"], values["layers.Al.sld_e6_per_A2"], 9.06, 0.774)
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.0, centre_um=values["sample.centre_um"], layers=(layer,)),
        instruments={"": fwdfit.Instrument("circular", 40.0, 5.5, 2.4)},
        spectra={"l46": fwdfit.GaussianLine(4.6, 0.15)},
        profiles=(fwdfit.Profile("line", 1.1, "l46", "", fwdfit.pixel_grid(-600.0, 600.0, 2.4), file=file),),
        fit=fwdfit.FitSpec(tuple(vary), dict(bounds or {})))


IMAGE_VARY = ("sample.tilt_deg", "sample.centre_um", "layers.Al.thickness_um", "layers.Al.sld_e6_per_A2",
              "layers.Al.mu_per_m")


def image_scene(image_file: Path, *, thickness_um: float, x0_um: float, n_cols: int, pixel_um: float = 2.4,
                image_err_file: Path | None = None, per_row=(), layers=None, psf_fwhm_um: float = 0.0,
                vary=None):
    """An Al block (2.70 g/cm3, start tilt 0.15°) at 8.5 mm, the ICON 2.7 Å line, one
    image profile ``radiograph`` of ``n_cols`` columns from ``x0_um``; ``IMAGE_VARY`` free.
    ``layers``: the sample's layers instead of the block (thickness_um then unused)."""
    import fwdfit

    profile = fwdfit.Profile("radiograph", 8.5, "l27", "", fwdfit.pixel_grid(x0_um, x0_um + n_cols * pixel_um, pixel_um),
                             image_file=image_file, image_err_file=image_err_file)
    if layers is None:
        layers = (fwdfit.Layer.from_material("Al", thickness_um, fwdfit.constants_from_formula("Al", 2.70)),)
    return fwdfit.Scene(fwdfit.Sample(depth_mm=2.0, tilt_deg=0.15, centre_um=0.0, layers=tuple(layers)),
                        {"": fwdfit.Instrument("circular", 40.0, 5.5, pixel_um, psf_fwhm_um=psf_fwhm_um)},
                        {"l27": fwdfit.GaussianLine(2.7, 0.15)}, (profile,),
                        fwdfit.FitSpec(IMAGE_VARY if vary is None else tuple(vary), per_row=tuple(per_row)))


IMAGE_TRACE = dict(depth_mm=2.0, tilt_deg=0.24, aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5,
                   distance_mm=8.5)


def traced_image(layers, centres_um, *, x0_um: float, n_cols: int, pixel_um: float = 2.4, sub: int = 8,
                 psf_fwhm_um: float = 0.0, n_rays: int = 4_000_000, seed: int = 3, **trace):
    """Rows of the exact reference (``fwdfit.trace_reference_rows``) for an image whose stack
    centre is ``centres_um`` (rows,) µm in each row: the ICON 2.7 Å line at 8.5 mm, tilt
    0.24° (``IMAGE_TRACE``, overridden by ``trace``). Returns (centres used (rows,), T, T_att
    (rows, n_cols)): one trace, so every row shares its Monte Carlo noise."""
    import fwdfit

    lam, weight = gaussian_line_table(2.7, 0.15)
    reference = fwdfit.trace_reference_rows(
        list(layers), centres_um=np.asarray(centres_um, float), x0_um=x0_um, pixel_um=pixel_um, n_pixels=n_cols,
        sub=sub, spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=n_rays, seed=seed,
        psf_fwhm_um=psf_fwhm_um, **{**IMAGE_TRACE, **trace})
    return reference.centres_um, reference.T, reference.T_att


def al_layer(name="Al", thickness_um=1000.0, sld=2.078, mu=1.39, mu_per_A=0.0):
    import fwdfit

    return fwdfit.Layer(name, float(thickness_um), float(sld), float(mu), float(mu_per_A))


def white_beam():
    """The BOA white-beam table as a spectrum value (its file kept for writing scenes)."""
    import fwdfit

    lam, weight = boa_spectrum()
    return fwdfit.TabulatedSpectrum(lam, weight, BOA_SPECTRUM)


def boa_spectrum() -> tuple[np.ndarray, np.ndarray]:
    """The BOA white-beam table (lambda_A, weight) used by the shared references."""
    table = read_table(BOA_SPECTRUM)
    return table["lambda_A"], table["weight"]


def gaussian_line_table(wavelength_A: float, fwhm_rel: float, n: int = 401):
    """A Gaussian line as a fine table (lambda_A, weight) over +-4 sigma, for the tracer."""
    sigma = fwhm_rel * wavelength_A / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    lam = np.linspace(wavelength_A - 4 * sigma, wavelength_A + 4 * sigma, n)
    return lam, np.exp(-0.5 * ((lam - wavelength_A) / sigma) ** 2)


# --------------------------------------------------------------------------- exact Beer-Lambert


def spectrum_average_transmission(lam, weight, mu_per_m, mu_per_m_per_A, length_um):
    """<exp(-(mu0 + mu1 lambda) l)> over a piecewise-linear spectrum table, for path lengths l.

    Trapezoid rule on 4001 points across the table (relative error ~1e-7).
    """
    fine = np.linspace(lam[0], lam[-1], 4001)
    density = np.interp(fine, lam, weight)
    density[[0, -1]] *= 0.5
    mu = (mu_per_m + mu_per_m_per_A * fine) * 1e-6  # 1/µm
    length_um = np.atleast_1d(np.asarray(length_um, float))
    return np.exp(-np.outer(length_um, mu)) @ density / density.sum()


def straight_ray_profile(x_um, pixel_um, *, thickness_um, mu_per_m, mu_per_m_per_A, depth_mm,
                         tilt_deg, centre_um, aperture, aperture_mm, aperture_distance_m,
                         distance_mm, lam, weight, n_sub=24, n_aperture=600):
    """Pixel-averaged transmission of one homogeneous block for straight rays, by brute force.

    Every ray from an aperture point x_ap to a detector point X is a straight line; its
    length inside the (tilted) rectangle is found by clipping the line against the
    rectangle's two pairs of faces in the sample frame, and its transmission is the
    spectrum average of exp(-mu(lambda) * length) (tabulated against length). The pixel
    average is a midpoint rule over n_sub points per pixel and n_aperture points over the
    aperture's x-marginal (uniform: square; sqrt(1 - v^2): circular). No refraction.
    """
    L_um, delta_um, D_um = aperture_distance_m * 1e6, distance_mm * 1e3, aperture_mm * 1e3
    half_w, half_d = 0.5 * thickness_um, 0.5e3 * depth_mm
    phi = math.radians(tilt_deg)
    cos_p, sin_p = math.cos(phi), math.sin(phi)
    v = (np.arange(n_aperture) + 0.5) / n_aperture * 2.0 - 1.0
    w_ap = np.ones_like(v) if aperture == "square" else np.sqrt(1.0 - v * v)
    w_ap = w_ap / w_ap.sum()
    x_ap = 0.5 * D_um * v
    sub = ((np.arange(n_sub) + 0.5) / n_sub - 0.5) * pixel_um
    X_all = (np.asarray(x_um, float)[:, None] + sub[None, :]).ravel()
    # The longest path is below depth / cos(tilt + steepest ray) + a margin: tabulate to it.
    grid = np.linspace(0.0, 1.01 * 2 * half_d / math.cos(abs(phi) + D_um / L_um) + 1.0, 2001)
    table = spectrum_average_transmission(lam, weight, mu_per_m, mu_per_m_per_A, grid)
    per_point = np.empty(X_all.size)
    for start in range(0, X_all.size, 2048):  # chunks keep the (points, aperture) arrays small
        X = X_all[start:start + 2048]
        slope = (X[:, None] - x_ap[None, :]) / L_um  # dx/dz of each ray
        # x(z) = X + (z - Delta) slope; in the sample frame u = (x - c) cos - z sin,
        # w = (x - c) sin + z cos, both linear in z: u = u0 + u1 z, w = w0 + w1 z.
        x0 = X[:, None] - delta_um * slope - centre_um
        u0, u1 = x0 * cos_p, slope * cos_p - sin_p
        w0, w1 = x0 * sin_p, slope * sin_p + cos_p
        with np.errstate(divide="ignore", invalid="ignore"):
            ua, ub = (-half_w - u0) / u1, (half_w - u0) / u1
        wa, wb = (-half_d - w0) / w1, (half_d - w0) / w1
        z_in = np.maximum(np.minimum(ua, ub), np.minimum(wa, wb))
        z_out = np.minimum(np.maximum(ua, ub), np.maximum(wa, wb))
        length = np.maximum(z_out - z_in, 0.0) * np.sqrt(1.0 + slope * slope)
        per_point[start:start + 2048] = np.interp(length, grid, table) @ w_ap
    return per_point.reshape(len(x_um), n_sub).mean(axis=1)


# --------------------------------------------------------------------------- derivatives


def central_difference(f, x: float, h: float) -> float:
    """(f(x + h) - f(x - h)) / 2h, with f a scalar function of a float."""
    return (float(f(x + h)) - float(f(x - h))) / (2.0 * h)


# --------------------------------------------------------------------------- model calls


def _weighted(params, model, weights):
    """sum_p w_p . T_p + v_p . T_att_p: a random linear functional touching every pixel."""
    import jax.numpy as jnp

    T, T_att = model(params)
    value = sum(jnp.dot(w, t) for w, t in zip(weights[0], T))
    value = value + sum(jnp.dot(w, t) for w, t in zip(weights[1], T_att))
    return value, (T, T_att)


def _make_jitted():
    import equinox as eqx

    value_and_grad = eqx.filter_jit(eqx.filter_value_and_grad(_weighted, has_aux=True))
    value = eqx.filter_jit(lambda params, model, weights: _weighted(params, model, weights)[0])
    return value_and_grad, value


# Module-level, so that tests in different files that build models of the same shapes
# share one compilation (compiling value-and-gradient takes ~10 s per model on 2 cores).
weighted_value_and_grad, weighted_value = _make_jitted()


def random_weights(scene, dtype, seed=0):
    """Normal random weights (one array per profile) for T and for T_att."""
    import jax.numpy as jnp

    rng = np.random.default_rng(seed)
    sizes = [len(p.x_um) for p in scene.profiles]
    return ([jnp.asarray(rng.normal(size=n), dtype) for n in sizes],
            [jnp.asarray(rng.normal(size=n), dtype) for n in sizes])


def replace_params(params, **changes):
    """A copy of ModelParams with fields replaced (values cast to the params' dtype)."""
    import equinox as eqx
    import jax.numpy as jnp

    dtype = params.tilt_deg.dtype
    names = list(changes)
    return eqx.tree_at(lambda p: [getattr(p, n) for n in names], params,
                       [jnp.asarray(changes[n], dtype) for n in names])


# --------------------------------------------------------------------------- shared scenes


def oxide_layer(name, thickness_um, sld, mu, mu_per_A=0.3):
    return al_layer(name, thickness_um, sld, mu, mu_per_A)


STACK_LAYERS = [oxide_layer("ox2_left", 80.0, 3.518, 12.0), oxide_layer("ox1_left", 160.0, 3.304, 24.0),
                al_layer(mu=1.39, mu_per_A=0.1),
                oxide_layer("ox1_right", 160.0, 3.304, 24.0), oxide_layer("ox2_right", 80.0, 3.518, 12.0)]


def stack_scene(folder: Path):
    """Five independent layers (oxide 80 | 160 | Al 1000 | 160 | 80 µm), BOA white beam,
    one profile at 34.4 mm (+-1300 µm), kernel windows sized for tilt 0.5°.

    Shared by the hard-case and gradient tests: models built from it with
    ``free=free_layer_parameters(scene)`` have the same compiled shapes, so
    ``weighted_value_and_grad`` compiles once per precision for both files.
    """
    return write_scene(folder, STACK_LAYERS, name="stack.toml", tilt_deg=0.5,
                       profiles=[("d34.4mm", 34.4, -1300.0, 1300.0)],
                       spectrum=white_beam())


def free_layer_parameters(scene) -> list[str]:
    """Every layer parameter as a ``vary`` name, so that no interface is pruned."""
    return [f"layers.{layer.name}.{key}" for layer in scene.sample.layers
            for key in ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A")]


def skin_scene(thickness_um, free=(), fresnel=False, roughness_mrad=0.0):
    """An oxide skin (SLD 4.5, mu 100 /m) on 1 mm of Al, ICON 4 Å line, the outer edge at 1.1 mm;
    thickness_um None: the bare Al block on the same instrument and pixels. roughness_mrad: the
    RMS slope of the skin's inner face (skin | Al)."""
    import dataclasses

    import fwdfit

    skin = [] if thickness_um is None else [dataclasses.replace(oxide_layer("skin", thickness_um, 4.5, 100.0),
                                                                roughness_mrad=roughness_mrad)]
    layers = skin + [al_layer()]
    return make_scene(layers, profiles=[("d01.1mm", 1.1, -530.0, -470.0)],
                      spectrum=fwdfit.GaussianLine(4.0, 0.15), aperture="circular",
                      aperture_distance_m=5.5, fresnel=fresnel, vary=free)
