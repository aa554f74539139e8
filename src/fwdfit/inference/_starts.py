"""Starting values read off the measured profiles, whatever the scene says.

What the profiles show directly, without a model of refraction:

- the outer edges of the stack (half-way crossings of the smoothed profile between
  the open beam and the first plateau inside), hence the centre and the projected
  width; the width is t / cos(tilt), so thicknesses are scaled per trial tilt;
- interior interfaces where neighbouring layers differ in attenuation (a least-squares
  segmentation of the sharpest profile into as many plateaus as the scene has layers);
- each layer's attenuation from its plateau level, inverting the spectrum-weighted
  Beer-Lambert law with the model's own wavelength nodes;
- the open-beam level (norm) and the per-profile sideways shifts (shift, drift).

A profile narrower than the stack's known width (the sum of the thicknesses the scene
gives; ``narrow_profiles``) shows one interface at most (``one_edge``): the scene's face
nearest to it places the stack, and the thicknesses are the scene's.

Tilt and SLD are not read off here: the global search (``_search``) scans them.
Units: µm, mm, 1/m, as in the scene keys.
"""

from __future__ import annotations

import math

import numpy as np

from .._errors import FwdfitError
from ..model.block._model import ForwardModel
from ..model._geometry import Estimate as Estimate
from ..scene._scene import Scene

# SLDs the global search (_search) tries where the scene gives none: kept here, below the
# search, because the starts size the refraction reach with the largest
_SLD_VALUES = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0)
SLD_VALUE_MAX = max(_SLD_VALUES)  # model windows are sized for this where the scene gives no SLD
_MEDIAN_NOISE = 1.25  # noise of a running median over that of a running mean
_PLATEAU_SIGNIFICANCE = 8.0  # the plateau inside an edge, in the filtered noise: half of it is 4 sigma clear
_MIN_RUN_UM = 12.0  # a stretch below the open beam this long marks the sample
_SPIKE_SIGNIFICANCE = 8.0  # refraction spikes that mark the edges of a nearly transparent sample ...
_SPIKE_PAIR_UM = 30.0  # ... the gain and loss beside one edge lie this close ...
_TRANSPARENT = 30.0  # ... and give the edges where they exceed the plateau's drop this many times
_PLATEAU_UM = 20.0  # stretch inside an edge whose median gives the plateau level
_REFRACTION_MARGIN_UM = 8.0  # refraction fringes beside an edge, beyond the penumbra
_SEGMENT_BIN_UM = 4.0  # bin width of the segmentation ...
_DESPIKE_UM = 25.0  # ... after a running median this wide removes the refraction spikes (loss and gain
# beside an interface at short distances reach 20 µm together; at 15 µm the oxide's o1 | Al fringe took a
# plateau of its own)
_STEP_SIGNIFICANCE = 5.0  # a segmented step counts when the plateaus differ by this many sigma
_SHARP_BLUR_FACTOR = 4.0  # profiles blurred at most this much more than the sharpest give the edges
_FALLBACK_MU_PER_M = 10.0  # start of a free attenuation that no plateau shows
_REACH_MARGIN = 1.25  # the window of the intensity balance at an edge: this much beyond the reach
_BALANCE_SIGNIFICANCE = 4.0  # balanced edges replace the crossings when the widths differ by this many sigma
_PINNED_FIELDS = ("centre_um", "shift_um", "drift_um_per_mm", "thickness_um", "norm", "mu_per_m")


def _smooth(values: np.ndarray, n: int) -> np.ndarray:
    """Running mean over n pixels, edges padded with the end values."""
    if n <= 1:
        return values
    padded = np.pad(values, (n // 2, n - 1 - n // 2), mode="edge")
    return np.convolve(padded, np.ones(n) / n, mode="valid")


def noise_sigma(T: np.ndarray) -> float:
    """Noise of a profile from the scatter of neighbouring-pixel differences (robust)."""
    differences = np.diff(T)
    return float(np.median(np.abs(differences - np.median(differences))) / (0.6745 * math.sqrt(2.0)))


def _open_level(T: np.ndarray) -> float:
    """Open-beam level: the brighter of the two ends' medians (a tenth of the profile each)."""
    n = max(3, len(T) // 10)
    return float(max(np.median(T[:n]), np.median(T[-n:])))


def _blur_um(scene: Scene, profile) -> float:
    """Width (µm) over which an edge is spread: penumbra plus detector blur."""
    instrument = scene.instruments[profile.instrument]
    penumbra = profile.distance_mm * instrument.aperture_mm / instrument.aperture_distance_m
    return penumbra + instrument.psf_fwhm_um + instrument.pixel_um


def _walk_out(x, drop, half: float, start: int, step: int) -> float:
    """x where ``drop`` first falls to ``half`` walking from index ``start`` by ``step`` (+-1)."""
    i = start
    while 0 <= i + step < len(drop) and drop[i + step] > half:
        i += step
    if not 0 <= i + step < len(drop) or drop[i] <= drop[i + step]:
        return float(x[i])  # the end, or a start already at half the drop
    fraction = (drop[i] - half) / (drop[i] - drop[i + step])
    return float(x[i] + fraction * (x[i + step] - x[i]))


def outer_edges(x_um, T, blur_um: float, pixel_um: float) -> tuple[float, float, float] | None:
    """(left, right) outer edges (µm) and the open-beam level of one profile; None if no sample.

    A running median (which keeps a step where it is and removes the narrow refraction
    spikes beside it) is widened until the outermost stretches below the open beam
    stand clear of the noise: their plateau at least _PLATEAU_SIGNIFICANCE of its noise
    deep. Each edge is where the filtered profile, walking out from that plateau, falls
    to half its drop.
    """
    level = _open_level(T)
    noise = max(noise_sigma(T), 1e-6)
    run = max(3, int(round(_MIN_RUN_UM / pixel_um)))
    width = max(5, int(round(0.5 * blur_um / pixel_um)))
    span = max(3, int(round(_PLATEAU_UM / pixel_um)))
    while width <= len(T) // 8:
        drop = level - running_median(T, width)
        noise_filtered = _MEDIAN_NOISE * noise / math.sqrt(width)
        inside = drop > 0.5 * _PLATEAU_SIGNIFICANCE * noise_filtered
        inside[:width // 2] = inside[len(T) - width // 2:] = False  # padded ends
        counts = np.convolve(inside.astype(int), np.ones(run, int), mode="valid")
        full = np.flatnonzero(counts == run)
        if len(full):
            first, last = full[0], full[-1] + run - 1
            gap = int(math.ceil((blur_um + _REFRACTION_MARGIN_UM) / pixel_um)) + width // 2
            a, b = min(first + gap, len(T) - 1), max(last - gap, 0)
            left_level = np.median(drop[a:a + span]) if a < b else drop[first]
            right_level = np.median(drop[max(b - span, 0):b + 1]) if a < b else drop[last]
            if min(left_level, right_level) > _PLATEAU_SIGNIFICANCE * noise_filtered:
                left = _walk_out(x_um, drop, 0.5 * left_level, a, -1)
                right = _walk_out(x_um, drop, 0.5 * right_level, b, +1)
                if right > left:
                    spikes = refraction_edges(x_um, T, level, noise)
                    transparent = (spikes is not None and np.max(np.abs(T - level))
                                   > _TRANSPARENT * min(left_level, right_level))
                    return spikes if transparent else (left, right, level)
        width = 2 * width + 1
    return None


def refraction_edges(x_um, T, level: float, noise: float) -> tuple[float, float, float] | None:
    """Outer edges of a sample too transparent to show its plateau, from its outermost
    refraction spikes (a 3-pixel median _SPIKE_SIGNIFICANCE noise off the open level): each
    edge half-way between the gain outside it and the loss inside it, the extremes within
    _SPIKE_PAIR_UM of the outermost spike; None without spikes on two sides."""
    deviation = running_median(T, 3) - level
    strong = np.flatnonzero(np.abs(deviation) > _SPIKE_SIGNIFICANCE * noise)
    if len(strong) < 2 or x_um[strong[-1]] - x_um[strong[0]] < 2 * _SPIKE_PAIR_UM:
        return None

    def edge(near: np.ndarray) -> float:
        return 0.5 * float(x_um[near[np.argmax(deviation[near])]] + x_um[near[np.argmin(deviation[near])]])

    return (edge(strong[x_um[strong] < x_um[strong[0]] + _SPIKE_PAIR_UM]),
            edge(strong[x_um[strong] > x_um[strong[-1]] - _SPIKE_PAIR_UM]), level)


def one_edge(x_um, T, blur_um: float, pixel_um: float) -> tuple[float, bool, float] | None:
    """The one interface a profile shows, for a stack wider than the profile: (x_um of it,
    whether the darker side is to its right, the brighter side's level); None where the
    profile shows none.

    Where the least-squares split of the profile into two plateaus differs by
    _STEP_SIGNIFICANCE, the interface is where the running median, walking out from the
    darker end, falls to half the drop. Else (a nearly transparent sample) it shows by
    its refraction spikes: half-way between the strongest gain and loss.
    """
    noise = max(noise_sigma(T), 1e-6)
    margin = blur_um + _REFRACTION_MARGIN_UM
    split = x_um[int(segment(running_median(T, max(1, int(round(_DESPIKE_UM / pixel_um)))), 2)[0])]
    sides = T[x_um < split - margin], T[x_um > split + margin]
    if min(len(sides[0]), len(sides[1])) >= 3:
        left_level, right_level = (float(np.median(side)) for side in sides)
        step_noise = _MEDIAN_NOISE * noise * math.sqrt(1 / len(sides[0]) + 1 / len(sides[1]))
    else:
        left_level = right_level = step_noise = 0.0
    if abs(left_level - right_level) > _STEP_SIGNIFICANCE * step_noise:
        sample_right = right_level < left_level
        level = max(left_level, right_level)
        edge = _walk_out(x_um, level - running_median(T, max(5, int(round(0.5 * blur_um / pixel_um)))),
                         0.5 * abs(left_level - right_level), len(T) - 1 if sample_right else 0,
                         -1 if sample_right else +1)
    else:
        deviation = running_median(T, 3) - float(np.median(T))
        if np.max(np.abs(deviation)) < _SPIKE_SIGNIFICANCE * noise:
            return None
        edge = 0.5 * float(x_um[np.argmax(deviation)] + x_um[np.argmin(deviation)])
        sides = T[x_um < edge - margin], T[x_um > edge + margin]
        sample_right = bool(min(len(sides[0]), len(sides[1])) and np.median(sides[1]) < np.median(sides[0]))
        level = float(np.median(T[x_um < edge] if sample_right else T[x_um > edge]))
    return edge, sample_right, level


def balanced_edges(x_um, T, edges, reach_um: float, pixel_um: float
                   ) -> tuple[tuple[float, float, float], float] | None:
    """Outer edges (left, right, open level) refined by the intensity balance, and their variance (µm^2).

    Refraction and reflection move intensity across an edge without removing it, so over
    a window of ``reach_um`` either side of it the data hold as much as a sharp step between
    the open level and the plateau inside: the step's position follows from the window's
    sum, whatever the fringes look like (their extremes lie off the edge by up to the reach
    at long wavelengths). The open level is the mean outside both windows, each plateau
    the mean over ``reach_um`` inside its window, which must be flat (its halves within
    _STEP_SIGNIFICANCE). ``edges``: first guesses (``outer_edges``). None when the sample
    is too narrow for that, its outer layer too thin, or the open beam too short.
    """
    left, right = edges[0], edges[1]
    if right - left < 4 * reach_um:
        return None
    outside = (x_um < left - reach_um) | (x_um > right + reach_um)
    if outside.sum() < 3:
        return None
    noise = max(noise_sigma(T), 1e-6)
    level = float(np.mean(T[outside]))
    refined, variance = [], 0.0
    for edge, outward in ((left, -1), (right, +1)):
        window = np.abs(x_um - edge) <= reach_um
        inner = (np.abs(x_um - (edge - 2 * outward * reach_um)) < reach_um) & ~window
        halves = np.array_split(T[inner], 2)
        if abs(halves[0].mean() - halves[1].mean()) > _STEP_SIGNIFICANCE * noise * math.sqrt(
                1 / halves[0].size + 1 / halves[1].size):
            return None  # no plateau there: the outer layer is thinner than the windows
        plateau = float(np.mean(T[inner]))
        drop = level - plateau
        if not drop > 0:
            return None
        x = x_um[window]
        a, b = x[0] - 0.5 * pixel_um, x[-1] + 0.5 * pixel_um
        total = float(np.sum(T[window])) * pixel_um
        if outward < 0:  # open on [a, e], plateau on [e, b]
            refined.append((total + level * a - plateau * b) / drop)
        else:  # plateau on [a, e], open on [e, b]
            refined.append((level * b - plateau * a - total) / drop)
        levels_variance = noise**2 * (1 / outside.sum() + 1 / inner.sum())
        variance += (noise**2 * pixel_um**2 * window.sum() + (b - a) ** 2 * levels_variance) / drop**2
    if not refined[0] < refined[1]:
        return None
    return (refined[0], refined[1], level), variance


def refraction_reach_um(scene: Scene, profile) -> float:
    """How far (µm) from an outer edge refraction and reflection move intensity, plus the blur.

    Rays grazing an outer face below the critical angle of the longest wavelength land
    at most that angle x the lever (distance + depth / 2) beyond the face; outer layers
    whose SLD is left out count as the largest SLD the global scan tries.
    """
    layers = scene.sample.layers
    sld = max(abs(l.density_scale * (SLD_VALUE_MAX if math.isnan(l.sld_e6_per_A2) else l.sld_e6_per_A2))
              for l in (layers[0], layers[-1]))
    critical_rad = scene.spectra[profile.spectrum].support_A[1] * math.sqrt(sld * 1e-6 / math.pi)
    lever_um = 1e3 * (profile.distance_mm + 0.5 * scene.sample.depth_mm)
    return _REACH_MARGIN * (critical_rad * lever_um + _blur_um(scene, profile))


def _weighted_median(values, weights) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(np.asarray(weights, float)[order])
    return float(np.asarray(values)[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def running_median(values: np.ndarray, n: int) -> np.ndarray:
    """Running median over n pixels (odd), ends padded with the end values."""
    if n <= 1:
        return values
    padded = np.pad(values, n // 2, mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, 2 * (n // 2) + 1), axis=1)


def segment(values: np.ndarray, k: int) -> np.ndarray:
    """Boundaries (k - 1,) (indices) of the least-squares split of values (n,) into k plateaus."""
    n = len(values)
    cs, cs2 = np.concatenate([[0], np.cumsum(values)]), np.concatenate([[0], np.cumsum(values ** 2)])
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    length = np.maximum(j - i, 1)
    cost = np.where(j > i, cs2[j] - cs2[i] - (cs[j] - cs[i]) ** 2 / length, np.inf)  # cost[i, j]: values[i:j]
    best = cost[0].copy()  # best[j]: values[:j] in one plateau
    choices = []
    for _ in range(k - 1):
        total = best[:, None] + cost  # split at i
        choice = np.argmin(total, axis=0)
        best = total[choice, np.arange(n + 1)]
        choices.append(choice)
    bounds, end = [], n
    for choice in reversed(choices):
        end = choice[end]
        bounds.append(end)
    return np.array(bounds[::-1], int)


def attenuation_from_plateau(plateau: float, weight, path_um: float, offsets_per_m) -> float:
    """mu (1/m) with sum(weight exp(-(mu + offsets) path)) = plateau (weights sum to 1)."""
    if not 0 < plateau < 1:
        return 0.0 if plateau >= 1 else math.inf
    path_m = path_um * 1e-6
    mu = -math.log(plateau) / path_m - float(np.dot(weight, offsets_per_m))
    for _ in range(30):  # Newton: the left side is convex and decreasing in mu
        terms = weight * np.exp(-(mu + offsets_per_m) * path_m)
        value, slope = terms.sum() - plateau, -path_m * terms.sum()
        mu -= value / slope
    return max(mu, 0.0)


def _wavelengths(model: ForwardModel, index: int):
    """(wavelength nodes (l,), weights (l,), tabulated mu (l, n_layer) 1/m) of one profile."""
    for group in model.groups:
        if index in group.index:
            row = group.index.index(index)  # rows of NumPy copies: indexing the JAX arrays compiles
            return tuple(np.asarray(values)[row] for values in
                         (group.step_wavelength_A, group.step_weight, group.step_mu_table_per_m))
    raise KeyError(index)


def estimate(scene: Scene, free: tuple, T: list[np.ndarray],
             model: ForwardModel) -> Estimate:
    """Starting values for the free parameters read off the profiles T (one array per profile).

    Values the data do not show (tilt, SLD, depth, distances, absorption slope) are the
    scene's, or NaN where the scene gives none.
    """
    values = {p.name: p.value for p in free}
    profiles = scene.profiles
    sample = scene.sample
    one_sided = narrow_profiles(scene, T)
    found = []
    for i, p in enumerate(profiles):
        pixel, blur = scene.instruments[p.instrument].pixel_um, _blur_um(scene, p)
        found.append(_placed_stack(scene, p, one_edge(p.x_um, T[i], blur, pixel)) if i in one_sided
                     else outer_edges(p.x_um, T[i], blur, pixel))
    usable = [i for i, e in enumerate(found) if e is not None]
    if not usable and not one_sided:  # a sample too transparent to show its plateau in any profile
        found = [refraction_edges(p.x_um, T[i], _open_level(T[i]), max(noise_sigma(T[i]), 1e-6))
                 for i, p in enumerate(profiles)]
        usable = [i for i, e in enumerate(found) if e is not None]
    if not usable:
        return Estimate(values, ())
    balanced = {}  # profiles whose edges the intensity balance refined: (edges, variance µm^2)
    for i in (i for i in usable if i not in one_sided):
        p = profiles[i]
        refined = balanced_edges(p.x_um, T[i], found[i], refraction_reach_um(scene, p),
                                 scene.instruments[p.instrument].pixel_um)
        if refined is not None:
            balanced[i] = refined
    sharpest = min(usable, key=lambda i: _blur_um(scene, profiles[i]))
    offset = lambda i: profiles[i].shift_um + sample.drift_um_per_mm * profiles[i].distance_mm
    centres = {i: 0.5 * (found[i][0] + found[i][1]) for i in usable}
    # The stack's centre and width: the median over the sharp profiles (far ones are washed
    # out and widened by their fringes), each edge found to a few µm in noisy data.
    sharp = [i for i in usable if _blur_um(scene, profiles[i]) <= _SHARP_BLUR_FACTOR * _blur_um(scene, profiles[sharpest])]
    centre_found = float(np.median([centres[i] - offset(i) for i in sharp]))
    width = float(np.median([found[i][1] - found[i][0] for i in sharp]))
    # The balanced edges, weighted by their precision (a time-of-flight stack's bins differ
    # mostly in how clearly their plateau shows), replace the crossings where the two widths
    # differ significantly: the fringes have pulled the crossings off the faces.
    weighted = [i for i in sharp if i in balanced]
    if weighted:
        weights = [1.0 / balanced[i][1] for i in weighted]
        balanced_width = _weighted_median([balanced[i][0][1] - balanced[i][0][0] for i in weighted], weights)
        if abs(balanced_width - width) > _BALANCE_SIGNIFICANCE / math.sqrt(sum(weights)):
            width = balanced_width
            centre_found = _weighted_median([0.5 * (balanced[i][0][0] + balanced[i][0][1]) - offset(i)
                                             for i in weighted], weights)
    left = centre_found + offset(sharpest) - 0.5 * width  # on the sharpest profile
    for p in free:
        field, index = p.target
        if field == "centre_um":
            values[p.name] = centre_found
        elif field == "norm" and index[0] in usable:
            values[p.name] = found[index[0]][2]
        elif field == "background" and math.isnan(p.value):
            values[p.name] = 0.0
        elif field == "mu_per_m_per_A" and math.isnan(p.value):
            values[p.name] = 0.0
    centre = values.get("sample.centre_um", sample.centre_um)
    for p in free:
        field, index = p.target
        if field == "shift_um" and index[0] in usable:
            values[p.name] = centres[index[0]] - centre - sample.drift_um_per_mm * profiles[index[0]].distance_mm
    if "sample.drift_um_per_mm" in values and len({profiles[i].distance_mm for i in usable}) > 1:
        distance = np.array([profiles[i].distance_mm for i in usable])
        shift = np.array([centres[i] - centre - profiles[i].shift_um for i in usable])
        values["sample.drift_um_per_mm"] = float(np.polyfit(distance, shift, 1)[0])
    thickness, seen = _layer_thicknesses(scene, free, T[sharpest], profiles[sharpest], left, width,
                                         segmented=sharpest not in one_sided)
    names, held = [], []
    for p in free:
        field, index = p.target
        if field == "thickness_um":
            values[p.name] = float(thickness[index[0]])
            names.append(p.name)
            if len(thickness) > 1 and seen[list(index)].all() and np.max(thickness) not in thickness[list(index)]:
                held.append(p.name)
    # Every profile sees the same stack, shifted by its own offset: its plateaus are placed
    # with the sharpest profile's edges (the far profiles' edges are washed out).
    placed = {i: (left + offset(i) - offset(sharpest), found[i][2]) for i in usable}
    _attenuations(scene, free, T, placed, thickness, model, values)
    pinned = tuple(p.name for p in free if p.target[0] in _PINNED_FIELDS and p.name not in held)
    return Estimate(values, tuple(names), tuple(held), pinned)


def narrow_profiles(scene: Scene, T: list[np.ndarray]) -> set[int]:
    """Indices of the profiles that show part of the stack only: narrower than the sum of the
    scene's thicknesses, without two outer edges (``outer_edges``) half that apart. Raises
    FwdfitError where such a profile meets a layer without a thickness (nothing to place it by)."""
    known_width = sum(l.thickness_um for l in scene.sample.layers if math.isfinite(l.thickness_um))
    narrow = set()
    for i, p in enumerate(scene.profiles):
        if known_width > p.x_um[-1] - p.x_um[0]:
            blur = _blur_um(scene, p)
            if not _both_edges(outer_edges(p.x_um, T[i], blur, scene.instruments[p.instrument].pixel_um),
                               p.x_um, known_width, blur):
                narrow.add(i)
    unknown = [l.name for l in scene.sample.layers if not math.isfinite(l.thickness_um)]
    if narrow and unknown:
        raise FwdfitError(f"{scene.path}: profile {scene.profiles[min(narrow)].name!r} is narrower than the sample: "
                          f"give layer {unknown[0]!r} a start thickness_um")
    return narrow


def _both_edges(edges, x_um, width_um: float, blur_um: float) -> bool:
    """Whether ``outer_edges`` found a stack's two edges in a profile narrower than the scene's
    ``width_um``: at least half that width apart, neither at an end of the profile."""
    if edges is None:
        return False
    margin = blur_um + _REFRACTION_MARGIN_UM
    return (edges[1] - edges[0] >= 0.5 * width_um and edges[0] > x_um[0] + margin
            and edges[1] < x_um[-1] - margin)


def _placed_stack(scene: Scene, profile, interface: tuple[float, bool, float] | None
                  ) -> tuple[float, float, float] | None:
    """(left, right outer edge µm, open level) of a stack wider than the profile, from the one
    interface it shows (``one_edge``): the scene's interface nearest to it where the scene
    gives a centre, else the outer edge on the brighter side. The thicknesses are the scene's."""
    sample = scene.sample
    if interface is None:
        return None
    x, sample_right, level = interface
    faces = np.concatenate([[0.0], np.cumsum([l.thickness_um for l in sample.layers])])  # from the left edge
    if math.isfinite(sample.centre_um):
        centre = sample.centre_um + profile.shift_um + sample.drift_um_per_mm * profile.distance_mm
        left = x - faces[np.argmin(np.abs(centre - 0.5 * faces[-1] + faces - x))]
    else:
        left = x if sample_right else x - faces[-1]
    return left, left + faces[-1], level


def _layer_thicknesses(scene: Scene, free, T, profile, left: float, width: float, segmented: bool = True
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Thickness of every layer (n_layer,) µm at tilt 0, summing to the projected width, and
    whether the segmentation saw it (n_layer,) bool.

    Free thicknesses come from the segmentation (unless ``segmented`` is False: the profile
    shows part of the stack) where its steps are significant, else from the scene's value,
    else an equal share of what the fixed layers leave.
    """
    layers = scene.sample.layers
    free_thickness = {i for p in free if p.target[0] == "thickness_um" for i in p.target[1]}
    given = np.array([l.thickness_um for l in layers], float)
    if len(layers) == 1:
        return np.array([width]), np.array([True])
    pixel = scene.instruments[profile.instrument].pixel_um
    inside = (profile.x_um > left) & (profile.x_um < left + width)
    per_bin = max(1, int(round(_SEGMENT_BIN_UM / pixel)))
    despiked = running_median(T, max(1, int(round(_DESPIKE_UM / pixel))))[inside]
    binned = despiked[: (len(despiked) // per_bin) * per_bin].reshape(-1, per_bin).mean(axis=1)
    present = [i for i, l in enumerate(layers) if l.thickness_um > 0 or i in free_thickness
               or math.isnan(l.thickness_um)]
    found = np.full(len(layers), np.nan)
    if segmented and len(binned) > 2 * len(present):
        bounds = segment(binned, len(present))
        edges = np.concatenate([[0], bounds, [len(binned)]])
        levels = [binned[a:b].mean() for a, b in zip(edges[:-1], edges[1:])]
        noise = _MEDIAN_NOISE * noise_sigma(T) / math.sqrt(per_bin)  # of one bin
        counts = np.diff(edges)
        for n, i in enumerate(present):
            # each step against the noise of the difference of the two plateaus' means
            steps = [abs(levels[n] - levels[m]) / (noise * math.sqrt(1 / counts[n] + 1 / counts[m]))
                     for m in (n - 1, n + 1) if 0 <= m < len(levels)]
            if min(steps, default=0) > _STEP_SIGNIFICANCE:
                found[i] = counts[n] * per_bin * pixel
    # Tied layers (same_as) share one thickness: the mean of the sides where it was found.
    roots = [l.same_as or l.name for l in layers]
    for root in set(roots):
        tied = [i for i, r in enumerate(roots) if r == root]
        seen = found[tied][np.isfinite(found[tied])]
        if len(seen):
            found[tied] = seen.mean()
    thickness = np.where(np.isin(np.arange(len(layers)), list(free_thickness)),
                         np.where(np.isfinite(found), found, given), given)
    unknown = ~np.isfinite(thickness)
    known = thickness[~unknown].sum()
    if unknown.any():
        thickness[unknown] = max(width - known, 0.0) / unknown.sum()
    adjustable = np.array([i in free_thickness for i in range(len(layers))])
    rest = width - thickness[~adjustable].sum()
    if adjustable.any() and thickness[adjustable].sum() > 0 and rest > 0:
        thickness[adjustable] *= rest / thickness[adjustable].sum()
    return thickness, np.isfinite(found)


def _attenuations(scene: Scene, free, T, placed, thickness, model: ForwardModel, values) -> None:
    """Free mu_per_m from each layer's plateau (median over the profiles), into ``values``.

    placed: profile index -> (left outer edge µm, open-beam level) of the profiles used.
    """
    layers = scene.sample.layers
    depth_um = scene.sample.depth_mm * 1e3
    for p in free:
        field, index = p.target
        if field != "mu_per_m":
            continue
        layer = index[0]
        estimates = []
        for i, (left, level) in placed.items():
            profile = scene.profiles[i]
            start = left + thickness[:layer].sum()
            stop = start + thickness[layer]
            margin = _blur_um(scene, profile) + _REFRACTION_MARGIN_UM
            plateau = (profile.x_um > start + margin) & (profile.x_um < stop - margin)
            if plateau.sum() < 3:
                continue
            lam, weight, table = _wavelengths(model, i)
            slope = layers[layer].mu_per_m_per_A
            slope = 0.0 if math.isnan(slope) else slope
            scale = layers[layer].density_scale  # mu = scale (mu_per_m + slope lambda + table)
            estimates.append(attenuation_from_plateau(float(np.median(T[i][plateau])) / level, weight, depth_um,
                                          scale * (slope * lam + table[:, layer])) / scale)
        finite = [e for e in estimates if math.isfinite(e)]
        if finite:
            values[p.name] = float(np.median(finite))
        elif math.isnan(values[p.name]):
            values[p.name] = _FALLBACK_MU_PER_M
