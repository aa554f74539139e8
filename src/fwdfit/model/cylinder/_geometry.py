"""The cylinder behind the fit's seam (``model._geometry.Geometry``): concentric shells
about an axis along the detector's columns.

Where a circle of radius r lands: X = M (c ± r), M = L / (L - Delta), c the axis
(centre + shift + drift x distance). The starts read the outer rim off the sharpest
profile (the nearest: its rim peak and dip lie within a penumbra of the rim): the
outermost steep flanks of the smoothed profile on both sides give the centre (their
midpoint, on every profile alike) and the radius; a shell without a thickness is placed
at the strongest feature inside the rim that no earlier circle explains; an unknown
attenuation comes from the profile's level at the axis.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..._errors import FwdfitError
from ...scene import _registry as registry
from ...scene._scene import CORE_VACUUM
from .._geometry import Estimate, edge_half_width_um
from ._plan import build_model, initial_params

_OPEN_FRACTION = 0.08  # each end of a profile taken as open beam for its level
_FEATURE_FRACTION = 0.3  # a rim's flank: where the deviation first reaches this fraction of its largest
_FALLBACK_MU_PER_M = 10.0
_MIN_SMOOTH_PIXELS = 5  # the rim is found on a running mean of at least this many pixels ...
_NOISE_FACTOR = 5.0  # ... where the departure exceeds this many times the open beam's scatter


def _magnification(scene, profile) -> float:
    L = scene.instruments[profile.instrument].aperture_distance_m * 1e6
    return L / (L - 1e3 * profile.distance_mm)


def _axis_um(scene, profile, centre_um: float) -> float:
    """Where the axis lies in the sample plane for one profile."""
    return centre_um + profile.shift_um + scene.sample.drift_um_per_mm * profile.distance_mm


def _penumbra_um(scene, profile) -> float:
    """The penumbra's width (µm) on the detector."""
    instrument = scene.instruments[profile.instrument]
    return profile.distance_mm * instrument.aperture_mm / instrument.aperture_distance_m


def _smooth(T: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return np.asarray(T, float)
    padded = np.pad(np.asarray(T, float), n, mode="edge")
    return np.convolve(padded, np.ones(n) / n, mode="same")[n:-n]


def _smoothed_with_open_ends(T: np.ndarray, pixels: int) -> tuple[np.ndarray, int]:
    """The profile's running mean (``_rim``'s smoothing) and how many points at each end are
    taken as open beam."""
    s = _smooth(T, max(pixels, _MIN_SMOOTH_PIXELS))
    return s, max(3, int(_OPEN_FRACTION * len(s)))


def _departures(s: np.ndarray, open_beam: np.ndarray) -> tuple[float, np.ndarray]:
    """(open level, indices): where the smoothed profile ``s`` departs from the median of
    ``open_beam`` by ``_FEATURE_FRACTION`` of its largest departure and by more than
    ``_NOISE_FACTOR`` times the open beam's scatter."""
    level = float(np.median(open_beam))
    deviation = np.abs(s - level)
    threshold = max(_FEATURE_FRACTION * deviation.max(), _NOISE_FACTOR * float(np.std(open_beam)))
    return level, np.nonzero(deviation >= threshold)[0]


def _rim(x: np.ndarray, T: np.ndarray, pixels: int) -> tuple[float, float, float] | None:
    """(left, right, open level): the outermost points where the smoothed profile departs
    from its open level by ``_FEATURE_FRACTION`` of its largest departure; None where the
    profile shows no rim on a side."""
    s, n_open = _smoothed_with_open_ends(T, pixels)
    open_beam = np.concatenate([s[:n_open], s[-n_open:]])
    level, inside = _departures(s, open_beam)
    if len(inside) < 2 or inside[0] < n_open or inside[-1] >= len(s) - n_open:
        return None
    # the ends must be open beam: flat within their noise (inside a sample the chord changes),
    # and at one level (a weak absorber's inside is flat too, but below the open beam)
    pixel_noise = float(np.std(np.diff(T))) / math.sqrt(2.0)
    half = n_open // 2
    ends = (np.asarray(T[:n_open], float), np.asarray(T[-n_open:], float))
    for end in ends:
        if abs(end[:half].mean() - end[half:].mean()) > 4.0 * pixel_noise / math.sqrt(half) + 1e-5:
            return None
    if abs(ends[0].mean() - ends[1].mean()) > 4.0 * pixel_noise * math.sqrt(2.0 / n_open) + 1e-5:
        return None
    return float(x[inside[0]]), float(x[inside[-1]]), level


def _one_rim(x: np.ndarray, T: np.ndarray, pixels: int) -> tuple[float, float] | None:
    """(where the rim lies, side): a profile that shows one rim, its open beam at the end with
    the higher level (side +1: open on the right, the sample to the left of the rim; -1 the
    other way); the rim is the outermost point, seen from the open end, where the smoothed
    profile departs from the open level by ``_FEATURE_FRACTION`` of its largest departure.
    None where nothing departs beyond the open beam's scatter."""
    s, n_open = _smoothed_with_open_ends(T, pixels)
    side = 1.0 if np.median(s[-n_open:]) >= np.median(s[:n_open]) else -1.0
    _, inside = _departures(s, s[-n_open:] if side > 0 else s[:n_open])
    if len(inside) == 0:
        return None
    return float(x[inside[-1]] if side > 0 else x[inside[0]]), side


def _refined_rim(x: np.ndarray, T: np.ndarray, rim: tuple[float, float, float], pixels: int,
                 reach_um: float) -> tuple[float, float]:
    """The rim's two sides where the lightly smoothed profile rises most steeply outwards
    (from the loss dip or the attenuated inside to the reflected peak or the open beam),
    searched from ``reach_um`` inside the smoothed flanks of ``_rim`` to half its smoothing
    window outside. The flanks alone lie outside the rim by up to half the running mean
    (25 µm wide on 5 µm pixels) plus the reflected rays' spread (up to 2 theta_c Delta): an
    Al rod's radius came out 14 µm large in 4 Å bins at 5 mm, outside the fit's basin of a
    weak absorber."""
    return (_steepest_flank(x, T, rim[0], -1.0, pixels, reach_um),
            _steepest_flank(x, T, rim[1], 1.0, pixels, reach_um))


def _steepest_flank(x: np.ndarray, T: np.ndarray, edge_um: float, outwards: float, pixels: int,
                    reach_um: float) -> float:
    """One side of ``_refined_rim``: where the lightly smoothed profile rises most steeply
    towards ``outwards`` (+1: increasing x), from ``reach_um`` inside the smoothed flank at
    ``edge_um`` to half the smoothing window outside it; the flank itself where too few points
    lie there."""
    slope = np.gradient(_smooth(T, pixels), x)
    half = 0.5 * max(pixels, _MIN_SMOOTH_PIXELS) * float(np.median(np.diff(x)))
    near = (outwards * (x - edge_um) <= half) & (outwards * (x - edge_um) >= -(reach_um + half))
    return float(x[near][np.argmax(outwards * slope[near])]) if near.sum() >= 3 else edge_um


class Cylinder:
    """Concentric shells, listed outside in; a rod's innermost layer fills the core."""

    def initial_params(self, scene, dtype=None):
        return initial_params(scene, dtype)

    def plan_scene(self, scene, free):
        """Unknown values filled for the plan: the radius at half the widest profile's
        width in the sample plane (the ray grids then cover any radius it shows), the centre
        at 0, a thickness at 0, any other at 1."""
        sample = scene.sample
        radius = sample.outer_radius_um
        if math.isnan(radius):
            radius = max(0.5 * (p.x_um[-1] - p.x_um[0]) / _magnification(scene, p) for p in scene.profiles)
        layers = []
        for layer in sample.layers:
            changes = {key: (0.0 if key == "thickness_um" else 1.0)
                       for key in registry.part("layers", "cylinder") if math.isnan(getattr(layer, key))}
            layers.append(dataclasses.replace(layer, **changes))
        centre = 0.0 if math.isnan(sample.centre_um) else sample.centre_um
        return dataclasses.replace(scene, sample=dataclasses.replace(
            sample, outer_radius_um=radius, centre_um=centre, depth_mm=2e-3 * radius, layers=tuple(layers)))

    def build_model(self, scene, accuracy, free, tilt_range_deg):
        return build_model(scene, accuracy, free, tilt_range_deg)

    def check_data(self, scene, T):
        """A radius without a start needs a profile that shows both rims; a centre without a
        start one rim at least (with the radius given)."""
        sample = scene.sample
        if math.isfinite(sample.outer_radius_um) and math.isfinite(sample.centre_um):
            return
        if any(_rim(p.x_um, t, self._pixels(scene, p)) for p, t in zip(scene.profiles, T)):
            return
        if math.isnan(sample.outer_radius_um):
            raise FwdfitError(f"{scene.path}: no profile shows both rims of the cylinder, so the radius cannot "
                              "be read off the data: give sample.outer_radius_um a start value")
        if not any(_one_rim(p.x_um, t, self._pixels(scene, p)) for p, t in zip(scene.profiles, T)):
            raise FwdfitError(f"{scene.path}: no profile shows a rim of the cylinder: give sample.centre_um "
                              "a start value")

    @staticmethod
    def _pixels(scene, profile) -> int:
        pixel = scene.instruments[profile.instrument].pixel_um
        return max(1, int(0.25 * _penumbra_um(scene, profile) / pixel))

    def estimate(self, scene, free, T, model):
        sample = scene.sample
        values = {p.name: p.value for p in free}
        rims = {i: _rim(p.x_um, t, self._pixels(scene, p)) for i, (p, t) in enumerate(zip(scene.profiles, T))}
        usable = [i for i, r in rims.items() if r is not None]
        by_name = {p.target[0]: p for p in free if not p.target[1]}
        centre, radius = sample.centre_um, sample.outer_radius_um
        if usable:
            sharpest = min(usable, key=lambda i: scene.profiles[i].distance_mm)
            p = scene.profiles[sharpest]
            reach = edge_half_width_um(p.distance_mm, _penumbra_um(scene, p),
                                       scene.instruments[p.instrument].psf_fwhm_um, 0.0)
            left, right = _refined_rim(p.x_um, T[sharpest], rims[sharpest], self._pixels(scene, p), reach)
            M = _magnification(scene, p)
            centres = [0.5 * (rims[i][0] + rims[i][1]) / _magnification(scene, scene.profiles[i])
                       - _axis_um(scene, scene.profiles[i], 0.0) for i in usable]
            if "centre_um" in by_name:
                centre = values[by_name["centre_um"].name] = float(np.median(centres))
            if "outer_radius_um" in by_name:
                radius = values[by_name["outer_radius_um"].name] = 0.5 * (right - left) / M
        elif "centre_um" in by_name and math.isnan(centre) and math.isfinite(radius):
            centre = values[by_name["centre_um"].name] = self._centre_from_one_rim(scene, T, radius)
        pinned = [by_name[k].name for k in ("centre_um", "outer_radius_um") if k in by_name]
        thickness_names = []
        for p in free:
            field, index = p.target
            if field == "thickness_um":
                thickness_names.append(p.name)
                if math.isnan(values[p.name]):
                    values[p.name] = self._shell(scene, T, usable, centre, radius, index[0])
                    pinned.append(p.name)
            elif field == "mu_per_m" and math.isnan(values[p.name]):
                values[p.name] = self._mu(scene, T, usable, centre, radius, index[0], model)
            elif field in ("background", "mu_per_m_per_A") and math.isnan(values[p.name]):
                values[p.name] = 0.0
            elif field == "norm" and index[0] in usable:
                values[p.name] = rims[index[0]][2]
            elif field in ("shift_um", "density_scale", "norm") and math.isnan(values[p.name]):
                values[p.name] = registry.BY_KEY[field].default
        return Estimate(values, tuple(thickness_names), (), tuple(pinned))

    def _centre_from_one_rim(self, scene, T, radius: float) -> float:
        """The axis from the rim of the nearest profile that shows one (a window over one side
        of the sample) and the radius: the rim's steepest flank, r from it towards the sample."""
        shown = [(i, rim) for i, (p, t) in enumerate(zip(scene.profiles, T))
                 if (rim := _one_rim(p.x_um, t, self._pixels(scene, p))) is not None]
        i, (edge, side) = min(shown, key=lambda item: scene.profiles[item[0]].distance_mm)
        p = scene.profiles[i]
        reach = edge_half_width_um(p.distance_mm, _penumbra_um(scene, p),
                                   scene.instruments[p.instrument].psf_fwhm_um, 0.0)
        rim = _steepest_flank(p.x_um, T[i], edge, side, self._pixels(scene, p), reach)
        return rim / _magnification(scene, p) - _axis_um(scene, p, 0.0) - side * radius

    def _shell(self, scene, T, usable, centre, radius, layer) -> float:
        """A shell's thickness from the strongest slope of the sharpest profile inside the
        circles already placed (the scene's thicknesses outside it), else a tenth of the radius."""
        known = sum(l.thickness_um for l in scene.sample.layers[:layer] if math.isfinite(l.thickness_um))
        outer = radius - known
        if not usable or not math.isfinite(outer):
            return 0.1 * radius
        i = min(usable, key=lambda k: scene.profiles[k].distance_mm)
        p = scene.profiles[i]
        M = _magnification(scene, p)
        axis = M * _axis_um(scene, p, centre)
        s = _smooth(T[i], self._pixels(scene, p))
        slope = np.abs(np.gradient(s, p.x_um))
        r = np.abs(p.x_um - axis) / M
        guard = edge_half_width_um(p.distance_mm, _penumbra_um(scene, p),
                                   scene.instruments[p.instrument].psf_fwhm_um, 0.0) / M
        inside = (r < outer - guard) & (r > 0.1 * outer)
        if not inside.any():
            return 0.1 * radius
        return float(outer - r[inside][np.argmax(slope[inside])])

    def _mu(self, scene, T, usable, centre, radius, layer, model) -> float:
        """mu (1/m) of a rod's core from the level at the axis (a straight chord 2 R through
        the core only: a start, the fit refines it), else the fallback."""
        sample = scene.sample
        if not usable or layer != len(sample.layers) - 1 or sample.core == CORE_VACUUM or len(sample.layers) > 1:
            return _FALLBACK_MU_PER_M
        i = usable[0]
        p = scene.profiles[i]
        axis = _magnification(scene, p) * _axis_um(scene, p, centre)
        near = np.abs(p.x_um - axis) < 0.2 * radius
        if near.sum() < 3:
            return _FALLBACK_MU_PER_M
        s = _smooth(T[i], self._pixels(scene, p))
        n_open = max(3, int(_OPEN_FRACTION * len(s)))
        level = float(np.median(np.concatenate([s[:n_open], s[-n_open:]])))
        ratio = float(np.median(T[i][near])) / level
        return max(-math.log(min(max(ratio, 1e-6), 1.0)) / (2e-6 * radius), 0.0)

    def at_tilts(self, free, estimate, row, tilts_deg):
        """A cylinder has no tilt: the row as it is."""
        return np.repeat(row[None], len(tilts_deg), axis=0)

    def plateau(self, scene, profile):
        """Pixels about the axis, inside the innermost circle (the core of a rod, the bore of a
        tube): within half its radius and farther from it than the rim's reach, 2 theta_c Delta
        (rays totally reflected at the longest wavelength), half the penumbra and three blur
        sigmas."""
        sample, instrument = scene.sample, scene.instruments[profile.instrument]
        M = _magnification(scene, profile)
        shells = sample.layers if sample.core == CORE_VACUUM else sample.layers[:-1]
        inner = sample.outer_radius_um - sum(l.thickness_um for l in shells)
        sld = max(abs(l.density_scale * l.sld_e6_per_A2) for l in sample.layers)
        critical_rad = scene.spectra[profile.spectrum].support_A[1] * math.sqrt(sld * 1e-6 / math.pi)
        reach = (2.0 * critical_rad * 1e3 * profile.distance_mm + 0.5 * _penumbra_um(scene, profile)
                 + 3.0 * instrument.psf_fwhm_um / (2.0 * math.sqrt(2.0 * math.log(2.0))))
        half = min(0.5 * M * inner, M * inner - reach)
        return np.abs(profile.x_um - M * _axis_um(scene, profile, sample.centre_um)) < half

    def interfaces(self, scene, profile):
        """Each circle's two faces on the detector, X = M (c ± r), outside in, and the edge
        half width from the penumbra and the blur."""
        sample, instrument = scene.sample, scene.instruments[profile.instrument]
        M = _magnification(scene, profile)
        axis = _axis_um(scene, profile, sample.centre_um)
        shells = sample.layers if sample.core == CORE_VACUUM else sample.layers[:-1]
        radii = sample.outer_radius_um - np.concatenate([[0.0], np.cumsum([l.thickness_um for l in shells])])
        media = ["vacuum"] + [l.name for l in sample.layers] + (["vacuum"] if sample.core == CORE_VACUUM else [])
        faces = []
        for k, r in enumerate(radii):
            if r <= 0:
                continue
            faces += [(M * (axis - r),) * 2 + (f"{media[k + 1]} | {media[k]}, left",),
                      (M * (axis + r),) * 2 + (f"{media[k]} | {media[k + 1]}, right",)]
        faces.sort(key=lambda face: face[0])
        return faces, edge_half_width_um(profile.distance_mm, _penumbra_um(scene, profile), instrument.psf_fwhm_um,
                                         0.0)

    def sized_for(self, scene, width_um):
        """An unknown radius at a quarter of the window, an unknown shell at a tenth of the radius."""
        sample = scene.sample
        radius = 0.25 * width_um if math.isnan(sample.outer_radius_um) else sample.outer_radius_um
        layers = tuple(dataclasses.replace(l, thickness_um=0.1 * radius) if math.isnan(l.thickness_um) else l
                       for l in sample.layers)
        return dataclasses.replace(scene, sample=dataclasses.replace(sample, outer_radius_um=radius,
                                                                     layers=layers))

    def undetermined(self, scene, names, in_view):
        """Circle i (0: the rim; each layer's outer circle, a tube's bore the last) shows as
        faces i and 2 n - 1 - i. The radius needs one circle's two faces (the axis) and a
        face of the rim; a shell's thickness a face of each of its circles on one side; a
        layer's SLD a face of one of its circles. One wall in view leaves the radius
        undetermined: the per-row centre and the radius move its faces alike."""
        sample = scene.sample
        n = len(in_view) // 2
        left, right = np.asarray(in_view[:n], bool), np.asarray(in_view[::-1][:n], bool)
        seen = left | right
        out = []
        for name in names:
            parts = name.split(".")
            if name == "sample.outer_radius_um":
                ok = bool((left & right).any() and seen[0])
            elif parts[0] == "layers":
                j = next((i for i, layer in enumerate(sample.layers) if layer.name == parts[1]), None)
                if j is None:
                    continue
                circles = [c for c in (j, j + 1) if c < n]
                if parts[-1] == "thickness_um":
                    ok = len(circles) == 2 and bool((left[j] and left[j + 1]) or (right[j] and right[j + 1]))
                elif parts[-1] in ("sld_e6_per_A2", "sld_end_e6_per_A2", "roughness_mrad"):
                    ok = any(seen[c] for c in circles)
                else:
                    continue
            else:
                continue
            if not ok:
                out.append(name)
        return out
