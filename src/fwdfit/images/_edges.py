"""Where the sample's faces lie in each row of an image, from the model's own signature of them.

The attenuation step of a weak absorber (0.3 % for 1 mm of Al) is below a row's noise; the
refraction beside each face (a gain outside, a loss inside, 5-10 %) is not. So every row
is matched against the model's predicted profile around each face of the scene's stack
(``face_templates``): a matched filter, the least-squares amplitude of the template (with
a free level) at every whole-pixel shift, in units of its error (``_scores``). The scores
of a few neighbouring rows are combined (their median) before a face is looked for (an
edge moves little from row to row, the noise averages out); a face is found where that average exceeds
``_DETECT`` standard deviations, and placed in the row's own score near it (a parabola
through three shifts). Strong absorbers match on their step, weak ones on their
refraction, blurred detectors on the blurred template: one rule for all.

Masked pixels (NaN) and the image's ends leave a template's window partly empty: it is
matched over the pixels it shares with the row, as long as they hold half its contrast.
Units: µm; shifts in pixels.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import FwdfitError
from ..inference._geometry import geometry_of
from ..inference._parameters import assembler, free_parameters
from ..inference._starts import _blur_um, noise_sigma, refraction_reach_um
from ..scene._scene import Profile, Scene

_DETECT = 6.0  # a face is found where the rows' median score exceeds this many standard deviations ...
_DETECT_ROW = 3.0  # ... and the row's own score this many, or half the rows' median score if less (so that
                   # a row without the face beside rows with it has none, and noisy rows keep theirs)
_SMOOTH_ROWS = 5  # rows whose scores are averaged to find a face (centred on the row)
_LOCAL_PX = 3  # the row's own score is searched this many pixels either side of the averaged peak
_WINDOW_MARGIN_UM = 10.0  # a face's template reaches this far beyond its refraction reach
_SPACING_TOLERANCE = 0.3  # two faces found lie as far apart as the scene's start puts them, to within this
_IN_VIEW_PX = 4  # a face this far inside the image's ends is in view (its refraction shows)
_SCORE_CHUNK = 32  # rows scored at once (memory: rows x shifts x window)
_SLD_NOMINAL, _MU_NOMINAL = 2.0, 10.0  # a template's SLD and mu where the scene gives none


@dataclasses.dataclass(frozen=True)
class FaceTemplate:
    """The model's profile around one face (or a group of faces closer than two windows):
    ``T`` (n,) on the image's pixel pitch, its first pixel ``start_px`` pixels right of
    the face ``face`` (index into the stack's faces, 0 = leftmost) when that face lies on
    a pixel's left edge. ``faces``: the faces the window holds."""

    face: int
    faces: tuple[int, ...]
    start_px: int
    T: np.ndarray


@dataclasses.dataclass(frozen=True)
class Faces:
    """Faces found in each row: ``position_um`` (rows, n_faces), NaN where not found (only
    the first face of each template's group is placed); the faces' positions with the
    centre at 0 in the templates ``offsets_um`` (n_faces,), how far each moves per µm of the
    centre ``per_centre`` (n_faces,: 1 for a block, the magnification for a cylinder) and the
    window half-width ``reach_um``."""

    position_um: np.ndarray
    offsets_um: np.ndarray
    reach_um: float
    compile_time_s: float = 0.0
    per_centre: np.ndarray | None = None

    def centres_um(self) -> np.ndarray:
        """The centre (rows, n_faces) each face found puts its row at (NaN: not found)."""
        per_centre = np.ones_like(self.offsets_um) if self.per_centre is None else self.per_centre
        return (self.position_um - self.offsets_um[None, :]) / per_centre[None, :]


def _template_scene(scene: Scene, profile: Profile, x_um: np.ndarray) -> Scene:
    """The scene with one plain profile on ``x_um`` and missing start values filled in
    (the sizes by the geometry, ``sized_for``)."""
    width = x_um[-1] - x_um[0]
    scene = geometry_of(scene).sized_for(scene, width)
    filled = []
    for layer in scene.sample.layers:
        changes = {}
        if math.isnan(layer.sld_e6_per_A2):
            changes["sld_e6_per_A2"] = _SLD_NOMINAL
        if math.isnan(layer.mu_per_m):
            changes["mu_per_m"] = _MU_NOMINAL
        filled.append(dataclasses.replace(layer, **changes) if changes else layer)
    sample = dataclasses.replace(scene.sample, layers=tuple(filled), centre_um=0.0)
    if math.isnan(sample.tilt_deg):
        sample = dataclasses.replace(sample, tilt_deg=0.0)
    row = dataclasses.replace(profile, x_um=x_um, image=None, image_err=None, T=None, T_err=None,
                              shift_um=0.0, norm=1.0, background=0.0)
    return dataclasses.replace(scene, sample=sample, profiles=(row,), fit=dataclasses.replace(scene.fit, per_row=()))


def _face_landing(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Where the geometry puts every face on the detector (its ``interfaces``, left to
    right, each face's upstream end) with the centre at 0 (n_faces,) µm, and how far each
    moves per µm of the centre (n_faces,): face j lies at offsets[j] + per_centre[j] * centre."""
    geometry, profile = geometry_of(scene), scene.profiles[0]

    def at(centre):
        moved = dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, centre_um=centre))
        return np.array([face[0] for face in geometry.interfaces(moved, profile)[0]])

    offsets = at(0.0)
    return offsets, at(1.0) - offsets


def face_templates(scene: Scene, profile: Profile, accuracy: float | None = None
                   ) -> tuple[list[FaceTemplate], np.ndarray, np.ndarray, float, float]:
    """The model's profile around each face (faces closer than two reaches share one
    window), the faces' positions at centre 0 and their moves per µm of the centre
    (n_faces,) each (``_face_landing``), the window half-width µm and the compile time s.

    One program, evaluated once per window with the stack placed so that its face lies
    in the middle of a grid as wide as the window.
    """
    pixel = scene.instruments[profile.instrument].pixel_um
    reach = refraction_reach_um(scene, profile) + _WINDOW_MARGIN_UM
    half = int(math.ceil(reach / pixel))
    grid = (np.arange(-half, half) + 0.5) * pixel  # the face at 0, on a pixel's left edge
    template_scene = _template_scene(scene, profile, grid)
    offsets, per_centre = _face_landing(template_scene)
    groups = [[0]]
    for j in range(1, len(offsets)):
        if offsets[j] - offsets[groups[-1][-1]] < 2 * reach:
            groups[-1].append(j)
        else:
            groups.append([j])
    # a group's window runs from its first face - reach to its last face + reach
    spans = [int(round((offsets[g[-1]] - offsets[g[0]]) / pixel)) for g in groups]
    longest = max(spans)
    grid = (np.arange(-half, half + longest) + 0.5) * pixel
    template_scene = _template_scene(scene, profile, grid)
    names = ["sample.centre_um"]
    free = free_parameters(template_scene, vary=names, bounds={})
    model = geometry_of(template_scene).build_model(template_scene, accuracy, names, None)
    assemble = assembler(template_scene, free)
    # a plain jit, not a Predictor: a one-off evaluation, and programs that fwdfit's own
    # store serialised failed to run when loaded in a later process ("Function ... not found")
    begin = time.perf_counter()
    centres = jnp.asarray([[-offsets[g[0]] / per_centre[g[0]]] for g in groups])  # face g[0] at x = 0
    T = np.asarray(jax.jit(jax.vmap(lambda v: model.flat(*assemble(v))[0]))(centres))
    templates = [FaceTemplate(g[0], tuple(g), -half, T[k, : 2 * half + spans[k]]) for k, g in enumerate(groups)]
    return templates, offsets, per_centre, reach, time.perf_counter() - begin


def _scores(rows: np.ndarray, sigma: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Matched-filter score (rows, n + m - 1) of the template (m,) at every shift at which it
    overlaps the rows (rows, n; NaN: masked): the least-squares amplitude of the template
    plus a free level over the pixels it shares with the row, over its error (errors
    sigma (rows,)). Shift k puts the template's first pixel on column k - m + 1. A shift
    whose shared pixels hold less than half the template's contrast scores 0."""
    m = len(template)
    t = template - template.mean()
    full = float(np.sum(t * t))
    out = np.zeros((rows.shape[0], rows.shape[1] + m - 1))
    if not full > 0:
        return out
    padded = np.pad(rows, ((0, 0), (m - 1, m - 1)), constant_values=np.nan)
    for first in range(0, len(rows), _SCORE_CHUNK):
        part = np.lib.stride_tricks.sliding_window_view(padded[first:first + _SCORE_CHUNK], m, axis=1)
        valid = np.isfinite(part)
        data = np.where(valid, part, 0.0)
        w = valid.astype(float)
        n_w, s_t, s_tt = w.sum(axis=2), w @ t, w @ (t * t)
        s_d, s_dt = data.sum(axis=2), data @ t
        with np.errstate(divide="ignore", invalid="ignore"):
            covariance = s_dt - s_d * s_t / n_w
            variance = s_tt - s_t * s_t / n_w
            score = covariance / (sigma[first:first + _SCORE_CHUNK, None] * np.sqrt(variance))
        out[first:first + _SCORE_CHUNK] = np.where((variance >= 0.5 * full) & (n_w >= 2), score, 0.0)
    return out


def _rows_median(score: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's score (rows, k) with its neighbours' (the n rows centred on it, or the n
    nearest at the image's ends): their median, scaled so that a score of noise stays unit
    normal (a median of m normal values has variance pi / 2m), and the plain median
    (rows, k), in a row's units. A median: one row far clearer than its neighbours (or a
    row of another width) does not put its face into theirs."""
    n = min(n, len(score))
    windows = np.lib.stride_tricks.sliding_window_view(score, n, axis=0)  # (rows - n + 1, k, n)
    first = np.clip(np.arange(len(score)) - n // 2, 0, len(score) - n)
    median = np.median(windows, axis=2)[first]
    return median * math.sqrt(2.0 * n / math.pi), median


def _peak(score: np.ndarray, at: int) -> float:
    """Sub-pixel position of the maximum of ``score`` (n,) at index ``at`` (a parabola
    through three values where it is an interior maximum)."""
    if 0 < at < len(score) - 1:
        left, mid, right = score[at - 1], score[at], score[at + 1]
        curvature = left - 2 * mid + right
        if curvature < 0:
            return at + float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
    return float(at)


def find_faces(scene: Scene, profile: Profile, rows: np.ndarray, use: np.ndarray,
               accuracy: float | None = None) -> Faces:
    """The faces of the stack in every row of ``rows`` (rows, n; NaN: masked) that ``use``
    (rows,) marks: per template group the strongest match, where the rows'
    mean score clears ``_DETECT``, placed in the row's own score."""
    pixel = scene.instruments[profile.instrument].pixel_um
    templates, offsets, per_centre, reach, compile_time = face_templates(scene, profile, accuracy)
    n_rows, n = rows.shape
    sigma = np.array([noise_sigma(row[np.isfinite(row)]) if np.isfinite(row).sum() > 2 else 0.0 for row in rows])
    sigma = np.maximum(sigma, 0.1 * np.median(sigma[use]) if use.any() else 0.0) + 1e-12
    position = np.full((n_rows, len(offsets)), np.nan)
    strength = np.full((n_rows, len(offsets)), np.nan)
    for template in templates:
        m = len(template.T)
        score = _scores(rows, sigma, template.T)  # shift k: the template's first pixel on column k - m + 1
        score[~use] = 0.0
        smooth, typical = _rows_median(score, _SMOOTH_ROWS)
        best = np.argmax(smooth, axis=1)
        found, mean = use & (smooth[np.arange(n_rows), best] > _DETECT), typical[np.arange(n_rows), best]
        for r in np.flatnonzero(found):
            lo, hi = max(best[r] - _LOCAL_PX, 0), min(best[r] + _LOCAL_PX + 1, score.shape[1])
            k = lo + int(np.argmax(score[r, lo:hi]))
            if score[r, k] < min(_DETECT_ROW, 0.5 * mean[r]):  # not where its neighbours have it:
                lo, hi = 0, score.shape[1]  # a face of its own, if it is clear alone
                k = int(np.argmax(score[r]))
                if score[r, k] < _DETECT:
                    continue
            shift = lo + _peak(score[r, lo:hi], k - lo)
            # column c's left edge is at x_um[0] - pixel / 2 + c * pixel; the face lies
            # -start_px pixels right of the window's first pixel's left edge
            position[r, template.face] = profile.x_um[0] - 0.5 * pixel + (shift - m + 1 - template.start_px) * pixel
            strength[r, template.face] = score[r, k]
    _keep_consistent(position, strength, offsets, reach)
    return Faces(position, offsets, reach, compile_time, per_centre)


def _keep_consistent(position: np.ndarray, strength: np.ndarray, offsets: np.ndarray, reach: float) -> None:
    """Drop (NaN) the faces of a row that contradict a clearer one: two faces must lie in
    the stack's order, as far apart as the scene puts them to within ``_SPACING_TOLERANCE``
    (plus a window's half-width). A template also matches, more weakly, the face on the
    other side of a layer (the loss inside a left face beside the loss inside a right
    one); in place of a face out of view it would be taken for it."""
    for r in np.flatnonzero(np.isfinite(position).sum(axis=1) > 1):
        kept: list[int] = []
        for j in np.argsort(-np.nan_to_num(strength[r], nan=-np.inf)):
            if not np.isfinite(position[r, j]):
                continue
            if all(abs((position[r, j] - position[r, i]) - (offsets[j] - offsets[i]))
                   <= _SPACING_TOLERANCE * abs(offsets[j] - offsets[i]) + reach for i in kept):
                kept.append(j)
            else:
                position[r, j] = np.nan


def in_view(faces: Faces, centres_um: np.ndarray, x_um: np.ndarray, pixel_um: float) -> np.ndarray:
    """Which faces (n_faces,) lie in the image, ``_IN_VIEW_PX`` pixels inside its ends, in
    at least half the rows with a centre (rows,) µm."""
    known = np.isfinite(centres_um)
    if not known.any():
        return np.zeros(len(faces.offsets_um), bool)
    per_centre = np.ones_like(faces.offsets_um) if faces.per_centre is None else faces.per_centre
    x = faces.offsets_um[None, :] + per_centre[None, :] * centres_um[known, None]
    low, high = x_um[0] + _IN_VIEW_PX * pixel_um, x_um[-1] - _IN_VIEW_PX * pixel_um
    return np.mean((x > low) & (x < high), axis=0) >= 0.5


def check_determined(names, free_faces: np.ndarray, scene: Scene, path) -> None:
    """FwdfitError naming every free parameter the faces in view (n_faces,) cannot fix
    (the geometry's ``undetermined``: for a block a thickness without a face in view on
    each side of its layer, a layer's SLD without either of its faces in view; for a
    cylinder also its radius with one wall in view)."""
    undetermined = geometry_of(scene).undetermined(scene, names, np.asarray(free_faces, bool))
    if undetermined:
        faces = np.flatnonzero(free_faces)
        it = "it" if len(undetermined) == 1 else "them"
        shown = ", ".join(f"{n!r}" for n in undetermined)
        in_sight = ", ".join(str(int(f)) for f in faces) or "none"
        raise FwdfitError(f"{path}: fit.vary: {shown}: the image cannot determine {it} (faces in view: "
                          f"{in_sight} of 0-{len(free_faces) - 1}, left to right); fix {it} "
                          "(leave it out of fit.vary, its value in the scene)")
