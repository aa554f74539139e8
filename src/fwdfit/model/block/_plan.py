"""From a scene to a compiled-shape forward model: grids, windows and quadrature sizes.

Everything here is static (NumPy): it decides how much work the model does.
The accuracy knob (target RMS error in T) sets the quadrature sizes; the kernel
windows cover every pixel a refracted or reflected ray can reach, around the
landing centre that the model computes from the current parameters, for every
tilt the model must serve; interfaces with neither refractive nor attenuation
contrast get no kernel; zero-thickness layers are skipped.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Collection
from typing import NamedTuple

import numpy as np

from ...scene import _registry as registry
from ...scene._registry import layer_value as layer_value
from ..._errors import FwdfitError, ModelWarning
from .._arrays import bragg_breaks_A as bragg_breaks_A
from .._arrays import check_pixels as check_pixels
from .._arrays import mu_tables as _mu_tables
from .._arrays import to_device as to_device
from .._kernel import landing_range, landing_regions
from ...scene._limits import MAX_TILT_DEG, check_domain
from ._model import ForwardModel, Interface, ModelParams, ProfileGroup, largest_tilt
from ...scene._scene import Scene
from ...scene._spectrum import BandSpectrum, GaussianLine, wavelength_quadrature
from ._thin import ThinLayer

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_PSF_TRUNCATION_SIGMAS = 5.0
_WINDOW_MARGIN = 1.05  # kernel windows: head-room over the furthest deflected ray
_WINDOW_MARGIN_FREE = 1.25  # more head-room when parameters move during a fit
_OFFSET_GRID = 2049  # grazing offsets at which the kernel windows' reach is evaluated
_TILT_GRID = 65  # normal tilts of a rough face at which the sub-windows' width is evaluated
# The mid-plane step profile (the plateaus) costs little: its spectrum average uses this
# many wavelength nodes at least (the plateau of a 2 mm Al block within 2e-5 of exact).
_STEP_WAVELENGTHS = 64
# A band narrower than this fraction of its centre needs no more wavelength nodes than a line.
_NARROW_BAND_REL = 0.3
# A plain band narrower than this fraction of its centre (a time-of-flight bin) needs one
# Gauss segment (4 nodes) at accuracy 1e-3: within 1e-5 RMS of 64 nodes (tests/test_tof_scaling.py).
_BIN_BAND_REL = 0.05
# Padding of wavelength nodes (nodes x kernel window edges) worth saving one group: about what a
# group's compile time buys in a fit's ~200 evaluations on a CPU.
_PAD_BUDGET = 4000
_LAMBDA_NODES_SCALE = 0.6  # kernel wavelength nodes relative to the calibration before the step nodes
_THIN_ANGLE_NODES = 3  # Gauss nodes of the attenuation inside a coupled thin layer (``_thin._weighted_mass``)
# With Fresnel reflection they also carry the reflectivities of both faces (measured: a 1.2 µm skin
# going to 0 µm is 7.8e-4, 1.3e-4 and 2.0e-5 off the bare block with Fresnel at 3, 4 and 6 nodes)
_THIN_FRESNEL_ANGLE_NODES = 6
# The thin kernels' integrands have more kinks than the depth cuts catch exactly: twice the depth
# nodes per piece (measured: RMS 0.0027 -> 0.0013 for a 2 µm skin at 10 mm, 0.24°).
_THIN_DEPTH_FACTOR = 2
# The coupled kernels carry intensity that moves with the critical angle (~ lambda), such as the
# guided channel of Ti inside Al: a white beam gets half as many wavelength nodes again (measured:
# 4 µm Ti in Al, BOA 1.1 mm, RMS 0.0020 -> 0.0006 against the tracer, whose noise is 0.0006; lines
# need no more).
_THIN_LAMBDA_FACTOR = 1.5
_GUIDED_CELLS = 32  # angle cells of the rays guided inside a coupled thin layer (``_thin.guided_kernel``)
# Depth nodes per smooth piece at accuracy 1e-3: base + per_log * log(lever ratio).
_DEPTH_NODES_BASE = 1.5
_DEPTH_NODES_PER_LOG = 0.5
# ... and at least 1 + (mu contrast x depth) / this, for the crossing rays' attenuation
# exp(-mu_1 (z - z_lo) - mu_2 (z_hi - z)), far from polynomial in z across a strong absorber's
# face (measured, T_att at 10 mm of a block with mu x depth = 10 and 20: 2 nodes 1.0e-2 and
# 2.3e-2 off the converged model, 4 and 6 nodes 2.1e-5 and 2.5e-6), at most _MAX_ATTENUATION_NODES:
# beyond mu x depth ~ 36 the rays crossing within depth / (mu x depth) of the face's end, which
# the nodes then miss, carry at most ~3e-3 of a pixel (mu x depth ~ 300), less either way.
_DEPTH_NODES_PER_ATTENUATION = 4.0
_MAX_ATTENUATION_NODES = 10
# One depth node per piece where the lever hardly changes along the depth and faces hardly
# absorb: at accuracy 1e-3, log(lever ratio) at most _ONE_NODE_LOG_RATIO (a 2 mm deep sample
# from ~21 mm on) and mu contrast x depth at most _ONE_NODE_ATTENUATION, both scaled by
# accuracy / 1e-3 (the error of one node grows about linearly in each). Measured against the
# converged model, RMS of T: the ICON Al block at 0.24° with Fresnel reflection, one node
# 9.9e-4, 6.3e-4, 3.9e-4 and 1.7e-4 at 10, 15, 21 and 34.4 mm (two: <= 5e-5); the BOA blocks at
# 19.6-34.4 mm and the five-layer oxide with every term at 34.4 mm within 1e-4 of two nodes;
# T_att of an absorber at 21 and 34.4 mm, one node, mu x depth 0.25, 0.5, 1: 1e-4, 2.6e-4, 7.7e-4.
# The crossing rays and the step assignment they replace then differ by ~1e-4 of the intensity
# the kernels move (quadratures on different depth cuts), where two nodes conserve it to 1e-12.
# Scenes with coupled thin layers keep the rule above (their kernels have more kinks than the cuts catch).
_ONE_NODE_LOG_RATIO = 0.1
_ONE_NODE_ATTENUATION = 0.25
# Rough faces: equiprobable strata of the normal's tilt (``_model._tilt_quantiles``). A stratum's
# tilt differs at each wavelength node, so a face is sampled at strata x wavelength-node tilts,
# and the RMS error in T falls like 1 / (that count), about as fast on a line as in a white beam:
# against 48-64 strata, count x error was 0.031 at 0.5 mrad (BOA white beam, 10 mm, 2 strata),
# 0.058-0.065 at 2 mrad (BOA white beam at 1.1 and 10 mm, 2-8 strata; the ICON line at 10 mm, 6-8
# strata, 0.070 at 4; the five-layer oxide 0.030-0.059 at 1.1-34.4 mm) and 0.086 at 5 mrad (BOA
# white beam, 10 mm, 6 strata): no longer at 34.4 mm than at 10, as the kernel spreads over more
# pixels while the tilts move its rays further. So count = _ROUGH_SAMPLES x sqrt(RMS slope / mrad)
# x 1e-3 / accuracy, rounded up to whole strata (those cases' errors at that count: 9.1e-4 to
# 9.9e-4 at 0.5 and 2 mrad, 7.7e-4 at 5), and at least _ROUGH_MIN_STRATA (one stratum left the
# five-layer oxide with every face at 0.5 mrad 0.0019 RMS off at 1.1 mm, two 0.0006). Below: the
# largest tilt in RMS slopes that profiles are grouped for (each group's windows then cover the
# largest tilt its strata use, 1.7-2.9 RMS slopes), and the head-room of a free roughness over its
# start (at least _ROUGH_FREE_MIN_MRAD).
_ROUGH_SAMPLES = 45.0
_ROUGH_MIN_STRATA = 2
_ROUGH_REACH = 3.0
_ROUGH_FREE_MARGIN = 1.5
_ROUGH_FREE_MIN_MRAD = 1.0
# A graded layer's uniform pieces in the step profile: enough that a stair's step in T is
# below accuracy * sqrt(12) (its RMS below the accuracy), at most this many.
_MAX_STEP_PIECES = 64


def quadrature_sizes(accuracy: float, spectrum, distance_mm: float, depth_mm: float,
                     coupled: bool = False, attenuation: float = 0.0) -> tuple[int, int]:
    """(wavelength nodes, depth nodes per smooth piece) for a target RMS error in T.

    Calibrated against the converged model and the exact reference
    (benchmarks/speed_vs_error.py): errors fall roughly like n^-2 in both sizes. Lines
    need fewer wavelength nodes than white beams. The depth integral is split into
    ``_model.DEPTH_PIECES`` pieces on which its integrand is smooth (``_model._kink_aligned_depths``)
    and integrated in the log of the lever; short distances need more nodes (the lever
    runs over a factor (Delta + d/2) / (Delta - d/2) along the depth). The plateaus
    of the step profile have finer wavelength nodes of their own (``_STEP_WAVELENGTHS``),
    so the kernels' wavelength nodes only carry the refraction signal: they are set
    for a third of the error the depth nodes are set for (the depth nodes set the
    largest single-pixel errors at the edges). coupled: the model has coupled thin layers,
    whose white-beam kernels need more wavelength nodes (``_THIN_LAMBDA_FACTOR``).
    attenuation: the largest change of mu x depth across a face (``_face_attenuation``; NaN:
    unknown, counted as none for the absorbers' nodes and as too much for a single node).
    """
    factor = math.sqrt(1e-3 / accuracy)
    band_rel = ((spectrum.lambda_max_A - spectrum.lambda_min_A) / spectrum.mean_wavelength_A
                if isinstance(spectrum, BandSpectrum) and spectrum.table is None else math.inf)
    narrow = isinstance(spectrum, GaussianLine) or band_rel < _NARROW_BAND_REL
    white = 24 * (_THIN_LAMBDA_FACTOR if coupled else 1)
    base_lambda = 4 if band_rel < _BIN_BAND_REL else 8 if narrow else white
    n_lambda = max(4, math.ceil(base_lambda * factor * _LAMBDA_NODES_SCALE))
    log_ratio = math.log((distance_mm + 0.5 * depth_mm) / (distance_mm - 0.5 * depth_mm))
    if (not coupled and factor**2 * log_ratio <= _ONE_NODE_LOG_RATIO
            and factor**2 * attenuation <= _ONE_NODE_ATTENUATION):  # False for a NaN attenuation
        return n_lambda, 1
    absorbing = min(1.0 + np.nan_to_num(attenuation) / _DEPTH_NODES_PER_ATTENUATION, _MAX_ATTENUATION_NODES)
    geometric = factor * (_DEPTH_NODES_BASE + _DEPTH_NODES_PER_LOG * log_ratio)
    n_z = max(1, math.ceil(geometric), math.ceil(factor * absorbing))
    return n_lambda, n_z


def _face_attenuation(scene: Scene, wavelength_A: np.ndarray) -> float:
    """The largest change of mu x depth across a face of the stack (vacuum on both sides) at
    the wavelengths (Å) given, for the layers' start values; NaN where a free mu has none."""
    layers = scene.sample.layers
    left = [np.zeros_like(wavelength_A)] + [layer.mu_per_m_at(wavelength_A) for layer in layers]
    right = [layer.mu_per_m_at(wavelength_A, right=True) for layer in layers] + [np.zeros_like(wavelength_A)]
    contrast = max(float(np.max(np.abs(a - b))) for a, b in zip(left, right))  # NaN if any is
    return contrast * 1e-3 * scene.sample.depth_mm


def fresnel_nodes(accuracy: float, aperture: str) -> int:
    """Gauss nodes of the Fresnel transfer's angular integral (``_kernel.fresnel_transfer``).

    Exact with 2 for the square aperture; for the circle the integrand has a
    (.)^(3/2) end point at the rim: 4 nodes leave ~5e-3, 8 nodes ~3e-4 of the
    transferred intensity (itself at most 1/6 of the totally reflected intensity).
    """
    if aperture == "square":
        return 2
    return max(4, math.ceil(6 * math.sqrt(1e-3 / accuracy)))


def _graded(scene: Scene, free: Collection[str]) -> tuple[bool, ...]:
    """Per layer: whether its SLD or mu varies across it (an end value given or free)."""
    ends = [key for key, q in registry.part("layers").items() if q.uniform_from]
    return tuple(any(not math.isnan(getattr(l, key)) or f"layers.{l.same_as or l.name}.{key}" in free
                     for key in ends) for l in scene.sample.layers)


def _step_pieces(scene: Scene, graded, free: Collection[str], accuracy: float) -> int:
    """Uniform pieces of a graded layer in the step profile, from the largest change of
    exp(-mu depth) across a graded layer (a free end: the whole range, 1)."""
    depth_m = 1e-3 * scene.sample.depth_mm
    change = 0.0
    for layer, is_graded in zip(scene.sample.layers, graded):
        if not is_graded:
            continue
        name = layer.same_as or layer.name
        if any(f"layers.{name}.{key}" in free for key in ("mu_end_per_m", "mu_per_m", "density_scale")):
            change = 1.0
        else:
            ends = layer.density_scale * np.array([layer.mu_per_m, layer_value(layer, "mu_end_per_m")])
            change = max(change, float(np.ptp(np.exp(-ends * depth_m))))
    return min(_MAX_STEP_PIECES, max(1, math.ceil(change / (accuracy * math.sqrt(12.0)))))


def _rough_mrad(scene: Scene, free: Collection[str]) -> tuple[float, ...]:
    """Per face (n_layer+1,) the largest normal RMS slope (mrad) the model must serve."""
    faces = [("sample.left_roughness_mrad", scene.sample.left_roughness_mrad)] + [
        (f"layers.{l.same_as or l.name}.roughness_mrad", l.roughness_mrad) for l in scene.sample.layers]
    return tuple(max(_ROUGH_FREE_MARGIN * value, _ROUGH_FREE_MIN_MRAD) if name in free else value
                 for name, value in faces)


def _unit_gauss(n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Gauss-Legendre nodes and weights on [0, 1] as static tuples; () for n = 0."""
    if n == 0:
        return (), ()
    nodes, weights = np.polynomial.legendre.leggauss(n)
    return tuple(float(v) for v in 0.5 * (nodes + 1)), tuple(float(v) for v in 0.5 * weights)


def initial_params(scene: Scene, dtype=None) -> ModelParams:
    """The scene's values as model parameters (shift 0 for every profile).

    Every value must be given: a start left out for a fit (NaN) is refused here.
    """
    layers = scene.sample.layers
    for layer in layers:
        for key in (key for key, q in registry.part("layers").items() if q.from_data):
            if math.isnan(getattr(layer, key)):
                raise FwdfitError(f"{scene.path}: layer {layer.name!r}: {key} is missing (only a fit "
                                  "may leave out the values it varies)")
    arr = lambda values: to_device(values, dtype)
    return ModelParams(
        **{key: arr([layer_value(l, key) for l in layers])
           for key, q in registry.part("layers").items() if q.model == "params"},
        left_roughness_mrad=arr(scene.sample.left_roughness_mrad),
        tilt_deg=arr(scene.sample.tilt_deg),
        centre_um=arr(scene.sample.centre_um),
        depth_mm=arr(scene.sample.depth_mm),
        distance_mm=arr([p.distance_mm for p in scene.profiles]),
        shift_um=arr([p.shift_um + scene.sample.drift_um_per_mm * p.distance_mm for p in scene.profiles]),
    )


def _interfaces(scene: Scene, free: Collection[str], thin: tuple[ThinLayer, ...] = ()) -> tuple[Interface, ...]:
    """Interfaces that need a kernel, skipping zero-thickness layers whose thickness is fixed
    and the faces of coupled thin layers (``thin``), which have kernels of their own.

    A face compares the right-hand values of the medium on its left with the left-hand
    ones of the medium on its right; it is rough where ``_rough_mrad`` is not 0.
    """
    layers = scene.sample.layers
    vacuum = dict(sld_e6_per_A2=0.0, mu_per_m=0.0, mu_per_m_per_A=0.0, table=None)
    media = [vacuum] + [dict(sld_e6_per_A2=l.density_scale * l.sld_e6_per_A2,
                             mu_per_m=l.density_scale * l.mu_per_m,
                             mu_per_m_per_A=l.density_scale * l.mu_per_m_per_A,
                             table=l.material.mu_table if l.material else None) for l in layers] + [vacuum]
    ends = [vacuum] + [media[i + 1] | dict(sld_e6_per_A2=l.density_scale * layer_value(l, "sld_end_e6_per_A2"),
                                           mu_per_m=l.density_scale * layer_value(l, "mu_end_per_m"))
                       for i, l in enumerate(layers)] + [vacuum]
    rough = _rough_mrad(scene, free)

    def name(layer):  # free parameters of tied layers (same_as) carry the first one's name
        return layer.same_as or layer.name

    def is_free(medium, key):  # a free density scale changes every constant of its layer
        end = {"sld_e6_per_A2": "sld_end_e6_per_A2", "mu_per_m": "mu_end_per_m"}.get(key, key)
        return 0 < medium <= len(layers) and any(f"layers.{name(layers[medium - 1])}.{k}" in free
                                                 for k in (key, end, "density_scale"))

    kept = _kept_media(scene, free)
    faces = []
    coupled = {layer.layer for layer in thin}
    behind = dict(_vanishing(scene, free))  # a vanished layer's right face is its neighbours' interface
    for left, right in zip(kept[:-1], kept[1:]):
        if left in coupled or right in coupled:
            continue
        sources = (left, behind[left]) if left in behind else (left,)
        refracting = any(ends[source]["sld_e6_per_A2"] != media[right]["sld_e6_per_A2"]
                         or is_free(source, "sld_e6_per_A2") for source in sources) or is_free(right, "sld_e6_per_A2")
        attenuating = any(ends[source][key] != media[right][key] or is_free(source, key) or is_free(right, key)
                          or media[source]["table"] is not media[right]["table"]
                          for source in sources for key in ("mu_per_m", "mu_per_m_per_A"))
        if refracting or attenuating:
            faces.append(Interface(position=right - 1, left=left, right=right, refracting=refracting,
                                   rough=refracting and rough[right - 1] > 0))
    return tuple(faces)


def thin_layers(scene: Scene, free: Collection[str], tilt_range_deg: tuple[float, float]) -> tuple[ThinLayer, ...]:
    """Layers whose two faces are coupled (``_thin``): thinner than the sideways drift.

    The drift is depth x the steepest grazing angle (half-divergence, tilt range and the
    largest critical angle); the thickness is the scene's (a fit's start), so a free layer
    that starts thick, or at 0 (read off the data), keeps independent faces. A coupled layer
    needs thick neighbours: of two adjacent candidates only one is coupled (interior layers
    first, then the thinnest).
    Not coupled (independent faces, as for thick layers): with rough faces or graded media at
    the layer (not combined yet). Every thin layer left with independent faces is reported
    with a ``ModelWarning``.
    """
    layers = scene.sample.layers
    depth_um = scene.sample.depth_mm * 1e3
    slds = [0.0] + [l.density_scale * l.sld_e6_per_A2 for l in layers]
    angle = max(0.5 * scene.instruments[p.instrument].aperture_mm / (scene.instruments[p.instrument]
                                                                      .aperture_distance_m * 1e3)
                + math.sqrt(scene.spectra[p.spectrum].support_A[1] ** 2 * (max(slds) - min(slds)) * 1e-6 / math.pi)
                for p in scene.profiles) + math.tan(math.radians(max(map(abs, tilt_range_deg))))
    drift_um = depth_um * angle
    rough = _rough_mrad(scene, free)  # per face: 0 left of layer 1, i right of layer i
    graded = (False,) + _graded(scene, free) + (False,)  # per medium

    def missing(a, b, c):  # what the coupled kernels do not model yet at layer b
        return [what for what, present in (("a rough face", rough[b - 1] != 0 or rough[b] != 0),
                                           ("a graded medium", graded[a] or graded[b] or graded[c])) if present]

    kept = _kept_media(scene, free)
    thin = {c: missing(*c) for c in zip(kept, kept[1:], kept[2:])  # in the stack's order
            if 0 < layers[c[1] - 1].thickness_um < drift_um}
    candidates = sorted((c for c, gaps in thin.items() if not gaps),
                        key=lambda c: (c[0] == 0 or c[2] == len(layers) + 1, layers[c[1] - 1].thickness_um))
    chosen: list[tuple[int, int, int]] = []
    for candidate in candidates:
        if all(candidate[1] not in (other[0], other[2]) for other in chosen):
            chosen.append(candidate)
    for (a, b, c), why in thin.items():
        if (a, b, c) not in chosen:
            reason = (f"with {' and '.join(why)} (not combined yet)" if why
                      else "next to another thin layer (only one of two neighbours is coupled)")
            warnings.warn(f"layer {layers[b - 1].name!r} ({layers[b - 1].thickness_um:g} µm) is thinner than the "
                          f"rays' sideways drift ({drift_um:.0f} µm) but its faces are modelled independently, "
                          f"{reason}: T near it may be off by more than the accuracy (0.01-0.03 RMS for the 2-4 µm "
                          f"layers measured)", ModelWarning, stacklevel=3)
    return tuple(ThinLayer(left=a, layer=b, right=c) for a, b, c in sorted(chosen, key=lambda c: c[1]))


def _vanishing(scene: Scene, free: Collection[str]) -> tuple[tuple[int, int], ...]:
    """(layer, left neighbour) media indices of the layers whose thickness is free: a fit can
    take them to 0, where ``_model._vanishing`` makes them transparent. The left neighbour
    skips fixed zero-thickness layers (they have no faces)."""
    kept = _kept_media(scene, free)[:-1]
    return tuple((b, a) for a, b in zip(kept[:-1], kept[1:]) if _free_thickness(scene, free)[b - 1])


def _free_thickness(scene: Scene, free: Collection[str]) -> list[bool]:
    """Per layer: whether its thickness is a fitted parameter."""
    return [f"layers.{l.same_as or l.name}.thickness_um" in free for l in scene.sample.layers]


def _kept_media(scene: Scene, free: Collection[str]) -> list[int]:
    """Media indices in order (0 and n_layer+1 the vacuum) without the fixed zero-thickness
    layers, which have no faces."""
    layers = scene.sample.layers
    return [0] + [i + 1 for i, (l, free_thickness) in enumerate(zip(layers, _free_thickness(scene, free)))
                  if l.thickness_um > 0 or free_thickness] + [len(layers) + 1]


def _crossing_fans(scene: Scene, instrument, spectrum, profile, tilt_range_deg: tuple[float, float]):
    """Every grazing offset (n, 1) of the aperture centre that the profile's positions and
    ``tilt_range_deg`` (low, high) allow, both crossing directions; the aperture's half-angle
    (rad); and the largest SLD contrast k at the longest wavelength entering or leaving."""
    distance_um, depth_um = profile.distance_mm * 1e3, scene.sample.depth_mm * 1e3
    to_sample_um = instrument.aperture_distance_m * 1e6 - distance_um
    half_angle = 0.5 * instrument.aperture_mm * 1e3 / (to_sample_um - 0.5 * depth_um)
    direction = np.array([profile.x_um[0], profile.x_um[-1]]) / to_sample_um
    slope = np.tan(np.radians(tilt_range_deg))
    offsets = np.linspace(direction.min() - slope.max(), direction.max() - slope.min(), _OFFSET_GRID)
    slds = [0.0] + [l.density_scale * layer_value(l, key) for l in scene.sample.layers
                    for key in ("sld_e6_per_A2", "sld_end_e6_per_A2")]
    k_max = spectrum.support_A[1] ** 2 * (max(slds) - min(slds)) * 1e-6 / math.pi
    return np.concatenate([offsets, -offsets])[:, None], half_angle, k_max


def _window_um(scene: Scene, instrument, spectrum, profile, margin: float,
               tilt_range_deg: tuple[float, float], tilt_max_rad: float) -> float:
    """Half-width (µm) around a side's landing centre (``_model``) that its kernel reaches.

    The largest over the crossing fans of ``_crossing_fans`` and the largest SLD contrast; with
    rough faces, for normals tilted by up to tilt_max_rad (``landing_range``'s ``tilt``), whose
    reflected rays leave up to 2 tilt_max_rad further out on one side only.
    """
    distance_um, depth_um = profile.distance_mm * 1e3, scene.sample.depth_mm * 1e3
    offsets, half_angle, k_max = _crossing_fans(scene, instrument, spectrum, profile, tilt_range_deg)
    lo, hi = landing_range(offsets, half_angle, np.array([k_max, -k_max]), instrument.fresnel, xp=np,
                           tilt=tilt_max_rad if tilt_max_rad > 0 else None)
    spread = 0.5 * (hi - lo) * (distance_um + 0.5 * depth_um)  # about the centre
    depth_drift = np.maximum(np.abs(lo), np.abs(hi)) * 0.5 * depth_um  # lever change along the depth
    return margin * float(np.max(spread + depth_drift))


def _window_bins(scene: Scene, instrument, spectrum, profile, margin: float, tilt_range_deg, rough_rad: float,
                 bin_um: float, most: int, reach: float) -> int:
    """Kernel window half-width in sub-bins of ``bin_um`` (at most ``most``) for rough faces whose
    normals tilt up to ``reach`` x ``rough_rad`` (``_window_um``)."""
    window_um = _window_um(scene, instrument, spectrum, profile, margin, tilt_range_deg, reach * rough_rad)
    return min(math.ceil(window_um / bin_um) + 2, most)


def _sub_window_edges(scene: Scene, instrument, spectrum, profile, margin: float, tilt_range_deg, rough_rad: float,
                      bin_um: float, reach: float) -> tuple[int, int, int]:
    """Edges of the sub-windows on which the kernels are evaluated (``_model._sub_windows``):
    each (tilt, wavelength) sample's deflected rays left and right of its facet's projection, and
    the straight rays. The widest ``_kernel.landing_regions`` over the crossing fans of
    ``_crossing_fans``, normals tilted up to ``reach`` x ``rough_rad``, and every contrast up to the
    largest (the right-hand region is widest at k = a'_min^2); and the widest fan. Each seen from
    every depth, with ``margin`` and an edge to spare each side."""
    distance_um, depth_um = profile.distance_mm * 1e3, scene.sample.depth_mm * 1e3
    offsets, half_angle, k_max = _crossing_fans(scene, instrument, spectrum, profile, tilt_range_deg)
    a_min, a_max = np.maximum(offsets - half_angle, 0.0), np.maximum(offsets + half_angle, 0.0)
    stack_um = np.nansum([layer.thickness_um for layer in scene.sample.layers])  # a free one left out: 0
    lever_um = distance_um + 0.5 * depth_um + 0.5 * stack_um * np.sin(np.radians(np.max(np.abs(tilt_range_deg))))
    reach_um = lambda lo, hi: float(np.max((hi - lo) * lever_um + np.maximum(np.abs(lo), np.abs(hi)) * depth_um))
    widest = [0.0, 0.0, reach_um(a_min, a_max)]
    for t in np.linspace(-1.0, 1.0, _TILT_GRID if rough_rad > 0 else 1) * reach * rough_rad:
        critical = np.minimum(np.square(np.maximum(a_min - t, 0.0)), k_max)
        for k in (k_max, -k_max, critical):
            for side, region in enumerate(landing_regions(a_min, a_max, k, t, xp=np)):
                widest[side] = max(widest[side], reach_um(*region))
    return tuple(math.ceil(margin * w / bin_um) + 4 for w in widest)


def _ladder(n: int) -> int:
    """Round up to 16 * 2^(k/2) so that profiles at similar distances share one plan."""
    return int(math.ceil(16 * 2 ** (math.ceil(2 * math.log2(max(n, 16) / 16)) / 2)))


class _PlanKey(NamedTuple):
    """What profiles must share to share a static plan (pixel grid, kernel window, strata)."""

    instrument: str
    n_edges: int
    n_sub: int
    n_pad: int
    strata: int
    window: int


def _split_by_nodes(plans: dict[_PlanKey, list[int]], per_profile) -> list[tuple[_PlanKey, list[int]]]:
    """The groups of every plan: its profiles by wavelength node count, most nodes first, a
    class joining the group above it (padded to that group's node count, ``_padded``) while
    the padding adds at most ``_PAD_BUDGET`` wavelength nodes x kernel window edges. A group
    costs a whole copy of the model's program to compile, a padded node its share of every
    evaluation (time-of-flight bins straddling a Bragg edge have more nodes than the rest)."""
    split = []
    for key, index in plans.items():
        window_edges = 2 * key.window + 1
        counts = {i: len(per_profile[i][1]) for i in index}
        group, top, used = [], None, 0
        for n in sorted(set(counts.values()), reverse=True):
            members = [i for i in index if counts[i] == n]
            extra = 0 if top is None else (top - n) * len(members) * window_edges
            if top is not None and used + extra > _PAD_BUDGET:
                split.append((key, sorted(group)))
                group, top, used, extra = [], None, 0, 0
            group, top, used = group + members, n if top is None else top, used + extra
        split.append((key, sorted(group)))
    return split


def _padded(rows: list[np.ndarray], k: int) -> list[np.ndarray]:
    """Rows of field k of ``per_profile`` padded along the wavelength axis to the longest:
    the last node repeated with weight 0 (fields 2 and 5 are weights), so nothing changes."""
    if k == 0:
        return rows
    n = max(len(r) for r in rows)
    pad = lambda r: np.concatenate([r, np.zeros((n - len(r),) + r.shape[1:]) if k in (2, 5)
                                    else np.repeat(r[-1:], n - len(r), axis=0)])
    return [pad(r) for r in rows]


def build_model(scene: Scene, accuracy: float | None = None, free: Collection[str] = (),
                tilt_range_deg: tuple[float, float] | None = None) -> ForwardModel:
    """The forward model for every profile of ``scene``.

    accuracy: target RMS error in T (default: the scene's ``[model] accuracy``).
    free: parameter names (as in ``[fit] vary``) that may change, so that no
    interface whose contrast could appear is pruned. tilt_range_deg: (low, high)
    tilts the model must serve (default: the scene's tilt, or ±MAX_TILT_DEG when
    ``sample.tilt_deg`` is free); kernel windows are sized for it.
    """
    accuracy = scene.accuracy if accuracy is None else check_domain("accuracy", accuracy, "accuracy")
    if tilt_range_deg is None:
        tilt = scene.sample.tilt_deg
        tilt_range_deg = (-MAX_TILT_DEG, MAX_TILT_DEG) if "sample.tilt_deg" in free else (tilt, tilt)
    rough_mrad = max(_rough_mrad(scene, free))
    graded = _graded(scene, free)
    thin = thin_layers(scene, free, tilt_range_deg)
    interfaces = _interfaces(scene, free, thin)
    any_rough = any(face.rough for face in interfaces)
    plans: dict[_PlanKey, list[int]] = {}
    per_profile = []
    depth_nodes, window_bins, sub_edges, sub_edges_by_geometry = {}, {}, {}, {}
    breaks_A = bragg_breaks_A(scene, accuracy, 1e-3 * scene.sample.depth_mm)
    attenuation = {name: _face_attenuation(scene, wavelength_quadrature(scene.spectra[name], _STEP_WAVELENGTHS,
                                                                        breaks_A)[0])
                   for name in {profile.spectrum for profile in scene.profiles}}  # per spectrum, not per profile
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        spectrum = scene.spectra[profile.spectrum]
        if profile.distance_mm <= 0.5 * scene.sample.depth_mm:
            raise FwdfitError(f"profile {profile.name!r}: distance_mm = {profile.distance_mm} puts the "
                              f"detector inside the sample (depth_mm = {scene.sample.depth_mm})")
        check_pixels(profile.x_um, instrument.pixel_um, f"profile {profile.name!r}")
        sigma = instrument.psf_fwhm_um / _FWHM_PER_SIGMA
        n_sub = 1 if sigma == 0 else min(8, math.ceil(1.5 * instrument.pixel_um / sigma))
        bin_um = instrument.pixel_um / n_sub
        n_pad = math.ceil(_PSF_TRUNCATION_SIGMAS * sigma / bin_um)
        n_edges = len(profile.x_um) * n_sub + 2 * n_pad + 1
        margin = _WINDOW_MARGIN_FREE if free else _WINDOW_MARGIN
        # kernel window half-width (sub-bins) for rough faces' normals tilted up to ``reach`` RMS slopes
        rough_rad = 1e-3 * rough_mrad if any_rough else 0.0
        window_bins[i] = functools.partial(_window_bins, scene, instrument, spectrum, profile, margin, tilt_range_deg,
                                           rough_rad, bin_um, (n_edges - 1) // 2)
        # profiles alike (an image's rows) share one evaluation: on rough faces it takes tens of ms
        geometry = (profile.instrument, profile.spectrum, profile.distance_mm, profile.x_um[0], profile.x_um[-1])
        sub_edges[i] = sub_edges_by_geometry.setdefault(geometry, functools.cache(functools.partial(
            _sub_window_edges, scene, instrument, spectrum, profile, margin, tilt_range_deg, rough_rad, bin_um)))
        window = min(_ladder(window_bins[i](_ROUGH_REACH)), (n_edges - 1) // 2)  # the plan's class
        n_lambda, n_z = quadrature_sizes(accuracy, spectrum, profile.distance_mm, scene.sample.depth_mm,
                                         coupled=bool(thin), attenuation=attenuation[profile.spectrum])
        lam, weight = wavelength_quadrature(spectrum, n_lambda, breaks_A)
        first_edge = profile.x_um[0] - 0.5 * instrument.pixel_um - n_pad * bin_um
        strata = 0
        if any_rough:
            samples = _ROUGH_SAMPLES * math.sqrt(rough_mrad) * 1e-3 / accuracy
            strata = max(_ROUGH_MIN_STRATA, math.ceil(samples / len(lam) - 1e-9))
        key = _PlanKey(profile.instrument, n_edges, n_sub, n_pad, strata, window)
        plans.setdefault(key, []).append(i)
        depth_nodes[i] = n_z
        fine_lam, fine_weight = wavelength_quadrature(spectrum, max(_STEP_WAVELENGTHS, 4 * len(lam)), breaks_A)
        per_profile.append((first_edge, lam, weight, _mu_tables(scene, lam), fine_lam, fine_weight,
                            _mu_tables(scene, fine_lam)))
    groups = []
    for (instrument_name, n_edges, n_sub, n_pad, strata, _), index in _split_by_nodes(plans, per_profile):
        instrument = scene.instruments[instrument_name]
        thin_nodes, thin_weights = _unit_gauss(0 if not thin else _THIN_FRESNEL_ANGLE_NODES if instrument.fresnel
                                               else _THIN_ANGLE_NODES)
        z_nodes, z_weights = _unit_gauss(max(depth_nodes[i] for i in index))
        thin_z_nodes, thin_z_weights = _unit_gauss(_THIN_DEPTH_FACTOR * len(z_nodes) if thin else 0)
        angle_nodes, angle_weights = _unit_gauss(fresnel_nodes(accuracy, instrument.aperture)
                                                 if instrument.fresnel else 0)
        stack = lambda k: to_device(np.stack(_padded([per_profile[i][k] for i in index], k)))
        wavelength_A = stack(1)
        reach = largest_tilt(strata, wavelength_A.shape[1])
        window = max(window_bins[i](reach) for i in index)
        *sub_window, straight_window = (max(edges) for edges in zip(*(sub_edges[i](reach) for i in index)))
        n_window = 2 * window + 1
        groups.append(ProfileGroup(
            index=tuple(index), aperture=instrument.aperture,
            aperture_um=instrument.aperture_mm * 1e3,
            aperture_distance_um=instrument.aperture_distance_m * 1e6,
            psf_sigma_um=instrument.psf_fwhm_um / _FWHM_PER_SIGMA, bin_um=instrument.pixel_um / n_sub,
            n_edges=n_edges, n_sub=n_sub, n_pad=n_pad, window=window,
            z_nodes=z_nodes, z_weights=z_weights, thin_nodes=thin_nodes, thin_weights=thin_weights,
            guided_cells=_GUIDED_CELLS if thin else 0, thin_z_nodes=thin_z_nodes, thin_z_weights=thin_z_weights,
            fresnel_nodes=angle_nodes, fresnel_weights=angle_weights,
            rough_strata=strata,
            sub_window=tuple(sub_window) if sum(sub_window) <= n_window else (),  # no more edges than the window
            straight_window=straight_window if straight_window < n_window else 0,
            first_edge_um=stack(0), wavelength_A=wavelength_A, wavelength_weight=stack(2),
            mu_table_per_m=stack(3), step_wavelength_A=stack(4), step_weight=stack(5),
            step_mu_table_per_m=stack(6)))
    return ForwardModel(groups=tuple(groups), interfaces=interfaces, n_profiles=len(scene.profiles),
                        graded=graded, step_pieces=_step_pieces(scene, graded, free, accuracy), thin=thin,
                        vanishing=_vanishing(scene, free))
