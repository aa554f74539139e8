"""Fit a whole normalised image row by row: material shared by all rows, geometry per row.

A curved or drifting edge moves the stack's centre from row to row; everything else
(thicknesses, SLDs, attenuation, tilt) is the sample's and shared. The fit, in rounds:

1. each row's centre from the faces of the stack it shows, found by matching the model's
   own profile around each face against the rows (``_edges``: the refraction of a weak
   absorber, the step of a strong one); rows without a face, or mostly masked, are
   flagged and left out; a row whose faces are implausibly far apart starts from its
   neighbours' centres instead;
2. the shared parameters from a joint fit (``Fitter``) of a few averaged profiles: the
   rows, shifted by whole pixels onto a common centre, are averaged in ``_BINS`` bins of
   their sub-pixel offset, each bin a profile whose sample sits at the bin's offset, so
   the average blurs nothing the model does not know of;
3. each row's centre (and the [fit] per_row parameters) with the shared values fixed: one
   compiled program (``Predictor``) for every row, Levenberg-Marquardt over all rows of a
   chunk at once (``levenberg_marquardt(..., independent=True)``);
4. step 2 again with the fitted centres (no recompilation), then step 3 again;
5. the edge's line: the weighted least-squares line through the rows' centres, its
   slope the in-plane rotation (``sample.rotation_deg``, when [fit] vary names it; else
   the scene's rotation, the line's centre alone fitted). With each row's centre free,
   this is the joint fit of rotation and rows to first order (the rows are independent);
   what the line leaves is each row's own centre relative to it (a curved edge).

T_att of a row is the model's attenuation-only profile at that row's centre, and
T_corrected = T - (T_model - T_att), as in the profile fit. Units: µm, as the scene keys.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .._errors import FwdfitError
from ..inference._fit import FitResult, Fitter
from ..inference._least_squares import levenberg_marquardt
from ..inference._parameters import assembler, free_parameters
from ..inference._geometry import geometry_of
from ..inference._predict import Predictor
from .._progress import Progress, as_progress
from ..scene._scene import ImageLayout, Profile, Scene, load_scene
from ..inference._starts import noise_sigma
from ._edges import Faces, check_determined, find_faces, in_view

CENTRE = "sample.centre_um"
ROTATION = "sample.rotation_deg"
_BINS = 4  # sub-pixel offset bins of the averaged profiles (a quarter pixel each)
_MAX_MASKED = 0.5  # a row with more of its pixels masked is not fitted
_WIDTH_TOLERANCE = 0.1  # a row whose edges are this much (relative) off the median width has no edge
_ROUNDS = 2  # shared fit + per-row fit, repeated with the fitted centres
_CHUNK_ROWS = 64  # rows solved together (one progress line each)
_ROW_STEPS = 30  # solver steps per row
_ROW_TOLERANCE = 1e-2  # stop when a step moves the centre by less than this many standard errors
_TYPICAL_STEPS = 5.0  # largest solver step of a per-row value, in its typical steps (1 µm for the centre)
_POOR_LIMIT = 2.0  # a row's fit is poor when chi2/pixel exceeds this ...
_POOR_SIGNIFICANCE = 5.0  # ... by this many standard deviations of chi-square
_MAX_POOR_ROWS = 0.05  # the image rejects the fit when more of the fitted rows fit poorly
_NO_WEIGHT = 1e5  # an averaged profile's pixel with a larger T_err holds no data (no row covers it)

# rows.csv flags (sums of): the row was not fitted, or its fit is not to be trusted
FLAG_NO_EDGE = 1
FLAG_MASKED = 2
FLAG_POOR_FIT = 4
FLAG_NOT_CONVERGED = 8
_UNFITTED = FLAG_NO_EDGE | FLAG_MASKED


@dataclasses.dataclass(frozen=True)
class EdgeLine:
    """The straight line through the fitted rows' centres: its centre ``centre_um`` at the
    middle profile, its rotation (deg; centre in profile r moved by tan(rotation) *
    (r - middle) * pixel_um), their errors (inflated by sqrt(chi2/dof) of the rows about
    the line where that exceeds 1: a curved edge), whether the rotation was fitted, and
    ``deviation_um`` (rows,): each row's centre less the line's there (NaN: not fitted)."""

    centre_um: float
    centre_err_um: float
    rotation_deg: float
    rotation_err_deg: float
    rotation_fitted: bool
    deviation_um: np.ndarray
    chi2_reduced: float  # of the rows' centres about the line


def edge_line(centres_um: np.ndarray, errors_um: np.ndarray, use: np.ndarray, pixel_um: float,
              rotation_deg: float, fit_rotation: bool, where: str = "image") -> EdgeLine:
    """The line through the centres (rows,) µm with errors (rows,) of the rows ``use``: weighted
    least squares of centre against (r - middle) * pixel_um; the slope fixed at
    tan(rotation_deg) unless ``fit_rotation``."""
    n = len(centres_um)
    along = (np.arange(n) - 0.5 * (n - 1)) * pixel_um
    rows = use & np.isfinite(centres_um) & np.isfinite(errors_um) & (errors_um > 0)
    if fit_rotation and rows.sum() < 3:
        raise FwdfitError(f"{where}: {ROTATION}: {int(rows.sum())} fitted rows, too few for the edge's line "
                          "(at least 3)")
    if not rows.any():
        return EdgeLine(math.nan, math.nan, rotation_deg, math.nan, fit_rotation, np.full(n, np.nan), math.nan)
    w, c, x = 1.0 / errors_um[rows] ** 2, centres_um[rows], along[rows]
    design = np.stack([np.ones_like(x), x], axis=1) if fit_rotation else np.ones((len(x), 1))
    target = c if fit_rotation else c - math.tan(math.radians(rotation_deg)) * x
    covariance = np.linalg.inv(design.T @ (w[:, None] * design))
    beta = covariance @ (design.T @ (w * target))
    dof = max(int(rows.sum()) - design.shape[1], 1)
    chi2 = float(np.sum(w * (target - design @ beta) ** 2)) / dof
    scale = math.sqrt(max(chi2, 1.0))
    slope = float(beta[1]) if fit_rotation else math.tan(math.radians(rotation_deg))
    angle = math.degrees(math.atan(slope)) if fit_rotation else rotation_deg
    angle_err = (math.degrees(scale * math.sqrt(covariance[1, 1]) / (1.0 + slope ** 2)) if fit_rotation
                 else 0.0)
    deviation = np.where(use, centres_um - (beta[0] + slope * along), np.nan)
    return EdgeLine(float(beta[0]), scale * math.sqrt(covariance[0, 0]), angle, angle_err, fit_rotation,
                    deviation, chi2)


@dataclasses.dataclass(frozen=True)
class ImageFit:
    """The fit of one image's profiles (rows, n; ``layout`` says where they lie in the file): shared values from ``shared`` (a FitResult of the
    averaged profiles); per row the values and errors (rows, n_per_row) of the parameters
    ``per_row`` (the centre first; NaN: not fitted), chi-square, fitted pixels and flags
    (rows,); images (rows, n) of the data, model, T_att and T_corrected (NaN where masked,
    and T_att in rows not fitted)."""

    name: str
    x_um: np.ndarray
    shared: FitResult
    per_row: tuple[str, ...]
    row_values: np.ndarray
    row_errors: np.ndarray
    edge_centre_um: np.ndarray  # from the edges, the fit's start (NaN: no edge)
    chi2: np.ndarray
    n_pixels: np.ndarray
    steps: np.ndarray
    flags: np.ndarray
    T: np.ndarray
    sigma: np.ndarray
    T_model: np.ndarray
    T_att: np.ndarray
    T_corrected: np.ndarray
    sigma_from_data: bool
    n_masked: int
    compile_time_s: float
    wall_time_s: float  # after compilation
    row_time_s: float  # the per-row fits of the last round alone
    rounds: int
    layout: ImageLayout | None = None  # where the rows lie in the image file (None: the whole file, by rows)
    line: EdgeLine | None = None  # the straight line through the rows' centres (rotation_deg)
    shared_dof: int = 0  # the shared fit's pixels that hold data, less its free parameters

    @property
    def centre_um(self) -> np.ndarray:
        return self.row_values[:, 0]

    @property
    def centre_err_um(self) -> np.ndarray:
        return self.row_errors[:, 0]

    @property
    def fitted(self) -> np.ndarray:
        return (self.flags & _UNFITTED) == 0

    @property
    def good(self) -> np.ndarray:
        return self.flags == 0

    @property
    def chi2_total(self) -> float:
        """Chi-square summed over every fitted row."""
        return float(self.chi2[self.fitted].sum())

    @property
    def dof(self) -> int:
        """Fitted pixels of every fitted row, less the per-row and shared parameters."""
        rows = self.fitted
        return int(self.n_pixels[rows].sum()) - int(rows.sum()) * len(self.per_row) - len(self.shared.names)

    @property
    def chi2_reduced(self) -> float:
        """Over every fitted row: chi-square per degree of freedom."""
        return self.chi2_total / max(self.dof, 1)

    @property
    def shared_chi2_reduced(self) -> float:
        """The shared fit's chi-square per degree of freedom, over the averaged profiles'
        pixels that hold data (pixels no row covers, and bins whose rows were all left out,
        stay in the profiles with no weight; they are no degrees of freedom)."""
        return self.shared.chi2 / max(self.shared_dof, 1)

    @property
    def centre_rows(self) -> np.ndarray:
        """The rows the centre's mean and spread are taken over: those fitted well, else every fitted one."""
        return self.good if self.good.any() else self.fitted

    @property
    def centre_mean_um(self) -> float:
        return float(np.mean(self.centre_um[self.centre_rows]))

    @property
    def centre_spread_um(self) -> float:
        """The standard deviation of the rows' centres (an edge's curvature and rotation, and noise)."""
        return float(np.std(self.centre_um[self.centre_rows]))

    @property
    def accepted(self) -> bool:
        """The shared fit converged and at most 5 % of the fitted rows fit poorly. (The shared
        fit's own quality gate judges the averaged rows, whose noise is far below a row's:
        its verdict is a note, ``shared.quality``.)"""
        poor = np.count_nonzero(self.flags & FLAG_POOR_FIT)
        return bool(self.shared.converged and poor <= _MAX_POOR_ROWS * max(int(self.fitted.sum()), 1))

    @property
    def rows_per_s(self) -> float:
        return float(self.fitted.sum()) / max(self.row_time_s, 1e-9)

    def summary(self) -> str:
        flagged = int((self.flags != 0).sum())
        return (f"{self.name}: {int(self.fitted.sum())} of {len(self.flags)} rows fitted, {flagged} flagged; "
                f"{self.n_masked} masked pixels; chi2/dof {self.chi2_reduced:.4g}; "
                f"rows {self.rows_per_s:.1f}/s")

    def table(self) -> str:
        """The parameter table as text: the shared values (from the averaged rows), the rows'
        centre (mean ± spread), the edge's rotation, and one chi-square over every fitted row."""
        entries = [(n, f"{v:>14.6g} ± {e:<10.3g}") for n, v, e in zip(self.shared.names, self.shared.values,
                                                                        self.shared.errors) if n != CENTRE]
        entries.append((CENTRE, f"{self.centre_mean_um:>14.6g} ± {self.centre_spread_um:<10.3g}"
                                f"(mean ± spread of {int(self.centre_rows.sum())} rows)"))
        if self.line is not None and self.line.rotation_fitted:
            entries.append((ROTATION, f"{self.line.rotation_deg:>14.6g} ± {self.line.rotation_err_deg:<10.3g}"
                                      f"(the line through the rows' centres)"))
        width = max(len(n) for n, _ in entries)
        lines = [f"{n:<{width}}  {text}".rstrip() for n, text in entries]
        lines.append(f"chi2_reduced = {self.chi2_reduced:.4g} (dof {self.dof}) over {int(self.fitted.sum())} "
                     f"fitted rows; shared fit of the averaged rows {self.shared_chi2_reduced:.4g} "
                     f"(dof {self.shared_dof}), converged {self.shared.converged}")
        return "\n".join(lines)


def _image_profile(scene: Scene) -> Profile:
    images = [p for p in scene.profiles if p.image is not None]
    if len(scene.profiles) != 1 or len(images) != 1:
        raise FwdfitError(f"{scene.path}: fit-image needs exactly one profile, with image = ..., "
                          f"got {len(scene.profiles)} profile(s), {len(images)} of them image(s)")
    return images[0]


@dataclasses.dataclass(frozen=True)
class _Names:
    """The free parameters of the shared fit (of the averaged profiles, ``shared``) and of
    the per-row fits (``rows``; ``per_row`` among them, the centre first). A profile key
    named in [fit] per_row is one parameter per averaged profile in the shared fit."""

    shared: tuple[str, ...]
    rows: tuple[str, ...]
    per_row: tuple[str, ...]
    bounds_shared: dict
    bounds_rows: dict
    rotation: bool = False  # sample.rotation_deg in [fit] vary: the line through the rows' centres


def _names(scene: Scene, profile: Profile) -> _Names:
    """[fit] vary and per_row split into the shared and the per-row fits' parameters
    (``sample.rotation_deg`` is neither: the line through the rows' centres)."""
    vary, per_row = tuple(scene.fit.vary), tuple(scene.fit.per_row)
    rotation = ROTATION in vary
    if ROTATION in per_row:
        raise FwdfitError(f"{scene.path}: fit.per_row: {ROTATION!r} is the edge's, one for the image "
                          "(name it in fit.vary)")
    if ROTATION in scene.fit.bounds:
        raise FwdfitError(f"{scene.path}: fit.bounds.{ROTATION}: the rotation is the line through the rows' "
                          "centres, which takes no bounds")
    vary = tuple(n for n in vary if n != ROTATION)

    def key(name):  # a profile key of the image ("profiles.NAME.norm", "profiles.*.norm"), else None
        parts = name.split(".")
        owner = ".".join(parts[1:-1])
        return parts[-1] if parts[0] == "profiles" and len(parts) >= 3 and owner in ("*", profile.name) else None

    for name in vary:
        if name.startswith("profiles.") and name not in per_row:
            raise FwdfitError(f"{scene.path}: fit.vary: {name!r}: fit-image fits profile keys per row "
                              "only (name it in fit.per_row)")
    for name in per_row:
        if name.startswith("profiles.") and key(name) is None:
            raise FwdfitError(f"{scene.path}: fit.per_row: {name!r} names no key of the image profile "
                              f"{profile.name!r}")
    per_row = tuple(dict.fromkeys((CENTRE,) + per_row))
    every = tuple(dict.fromkeys(vary + per_row))
    shared = tuple(f"profiles.*.{key(n)}" if key(n) else n for n in every)
    rows = tuple(f"profiles.{profile.name}.{key(n)}" if key(n) else n for n in every)
    per_row = tuple(f"profiles.{profile.name}.{key(n)}" if key(n) else n for n in per_row)
    rename = lambda bounds, form: {(form.format(key(n)) if key(n) else n): b for n, b in bounds.items()}  # noqa: E731
    names = _Names(shared, rows, per_row, rename(scene.fit.bounds, "profiles.*.{}"),
                   rename(scene.fit.bounds, f"profiles.{profile.name}.{{}}"), rotation)
    free_parameters(scene, vary=names.rows, bounds=names.bounds_rows)  # every name and bound exists
    return names


def _row_sigma(profile: Profile) -> tuple[np.ndarray, bool]:
    """Per-pixel errors (rows, n), inf where masked; from the image's noise if not given."""
    masked = np.isnan(profile.image)
    if profile.image_err is not None:
        return np.where(masked, np.inf, profile.image_err), False
    noise = [noise_sigma(row[np.isfinite(row)]) for row in profile.image if np.isfinite(row).sum() > 2]
    sigma = float(np.median(noise)) if noise else 0.0
    if not sigma > 0:
        raise FwdfitError(f"{profile.image_file}: no image_err and no noise in the image to estimate it from")
    return np.where(masked, np.inf, sigma), True


def _filled(row: np.ndarray) -> np.ndarray:
    """A row with its masked (NaN) pixels linearly interpolated from their neighbours."""
    good = np.isfinite(row)
    if good.all():
        return row
    index = np.arange(len(row))
    return np.interp(index, index[good], row[good])


def edge_centres(scene: Scene, profile: Profile, accuracy: float | None = None,
                 faces: Faces | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each row's centre (rows,) µm from the faces of the stack it shows (``_edges``), and
    the flags (rows,): NaN where the row shows no face (FLAG_NO_EDGE), is mostly masked
    (FLAG_MASKED), or its outermost faces found lie more than 10 % further apart or closer
    than the median row's (no flag: it is fitted from its neighbours' centres). A row
    with one face found takes the centre the scene's thicknesses put beside it, moved by
    that face's median offset in the rows that show more."""
    image = profile.image
    flags = np.where(np.isnan(image).mean(axis=1) > _MAX_MASKED, FLAG_MASKED, 0)
    if faces is None:
        faces = find_faces(scene, profile, image, flags == 0, accuracy)
    estimate = faces.centres_um()  # the centre each face puts the stack at
    found = np.isfinite(estimate)
    count = found.sum(axis=1)
    flags[(flags == 0) & (count == 0)] = FLAG_NO_EDGE
    rows = np.arange(len(image))
    first = np.argmax(found, axis=1)
    last = found.shape[1] - 1 - np.argmax(found[:, ::-1], axis=1)
    centres = np.full(len(image), np.nan)
    several = count >= 2
    centres[several] = 0.5 * (estimate[rows, first] + estimate[rows, last])[several]
    for j in range(found.shape[1]):  # rows with one face: that face's centre, less its bias
        alone = (count == 1) & found[:, j]
        bias = estimate[several & found[:, j], j] - centres[several & found[:, j]]
        centres[alone] = estimate[alone, j] - (np.median(bias) if bias.size else 0.0)
    if several.any():
        width = faces.position_um[rows, last] - faces.position_um[rows, first]
        pairs = first * found.shape[1] + last
        common = np.bincount(pairs[several]).argmax()
        usual = several & (pairs == common)
        typical = np.median(width[usual])
        off = usual & (np.abs(width - typical) > _WIDTH_TOLERANCE * max(typical, 1e-9))
        centres[off] = np.nan
    if not np.isfinite(centres).any():
        raise FwdfitError(f"{profile.image_file}: no sample edge found in any of its {len(image)} rows "
                          f"({int(np.count_nonzero(flags == FLAG_MASKED))} of them mostly masked)")
    return centres, flags


@dataclasses.dataclass(frozen=True)
class _Binning:
    """Rows shifted by whole pixels onto ``centre_um`` and averaged in sub-pixel offset bins."""

    centre_um: float
    margin: int  # columns cropped on each side (the largest whole-pixel shift, plus two)
    bins: tuple[int, ...]  # the bins that hold rows (fixed after the first round)

    @staticmethod
    def of(centres: np.ndarray, pixel_um: float) -> _Binning:
        centre = float(np.median(centres[np.isfinite(centres)]))
        offsets = (centres[np.isfinite(centres)] - centre) / pixel_um
        whole, fraction = np.round(offsets), offsets - np.round(offsets)
        bins = np.clip(np.floor((fraction + 0.5) * _BINS), 0, _BINS - 1).astype(int)
        return _Binning(centre, int(np.max(np.abs(whole))) + 2, tuple(sorted(set(bins.tolist()))))

    def bin_offset_px(self, k: int) -> float:
        return (k + 0.5) / _BINS - 0.5

    def reference_um(self, centres: np.ndarray, use: np.ndarray, pixel_um: float) -> float:
        """Where the rows are moved to: ``centre_um``, unless a row would need a whole-pixel
        shift past the crop margin; then ``centre_um`` moved by the whole pixels of the rows'
        median offset from it. The first round's centres, from the edges, can all lie off the
        fitted ones (a tube wall whose thickness starts 20 µm off puts them 10 µm off): moved to
        ``centre_um``, the fitted rows would be clipped at the margin and averaged misaligned."""
        offsets = (centres[use] - self.centre_um) / pixel_um
        if offsets.size == 0 or np.max(np.abs(np.round(offsets))) <= self.margin - 1:
            return self.centre_um
        return self.centre_um + float(np.round(np.median(offsets))) * pixel_um

    def assign(self, centres: np.ndarray, pixel_um: float, reference_um: float) -> tuple[np.ndarray, np.ndarray]:
        """Whole-pixel shift (rows,) and bin (rows,) of each row: the existing bin nearest its
        offset from ``reference_um`` (a bin in the next pixel counts, with the whole shift changed)."""
        offsets = (centres - reference_um) / pixel_um
        options = np.array([[self.bin_offset_px(k) + w for w in (-1, 0, 1)] for k in self.bins])  # (B, 3)
        whole = np.round(offsets)
        fraction = offsets - whole
        distance = np.abs(fraction[:, None, None] - options[None])  # (rows, B, 3)
        flat = np.argmin(distance.reshape(len(offsets), -1), axis=1)
        b, w = np.unravel_index(flat, options.shape)
        shift = (whole + np.array([-1, 0, 1])[w]).astype(int)
        shift = np.clip(shift, -(self.margin), self.margin)
        return shift, np.asarray(self.bins)[b]

    def profiles(self, profile: Profile, centres, use, sigma, pixel_um, reference_um: float) -> list[Profile]:
        """One profile per bin (x_um cropped, shift_um at the bin's offset) holding the
        error-weighted mean of its rows (``use``) moved to ``reference_um``, T_err that of the mean."""
        shift, which = self.assign(np.where(use, centres, reference_um), pixel_um, reference_um)
        n = profile.image.shape[1]
        columns = np.arange(self.margin, n - self.margin)
        weight = np.where(np.isfinite(sigma), 1.0 / sigma ** 2, 0.0)
        data = np.where(np.isfinite(profile.image), profile.image, 0.0)
        profiles = []
        for k in self.bins:
            rows = np.flatnonzero(use & (which == k))
            taken = (rows[:, None], columns[None, :] + shift[rows, None])  # (rows_k, n_cropped)
            total = weight[taken].sum(axis=0)
            covered = total > 0
            # a pixel no row covers stays in the table (the model needs its grid) with no weight;
            # a bin whose rows were all left out this round holds no weight at all
            mean = np.where(covered, (weight[taken] * data[taken]).sum(axis=0) / np.where(covered, total, 1), np.nan)
            T = _filled(mean) if covered.any() else np.ones(len(columns))
            T_err = np.where(covered, 1.0 / np.sqrt(np.where(covered, total, 1)), 2 * _NO_WEIGHT)
            profiles.append(dataclasses.replace(
                profile, name=f"{profile.name}.bin{k}", x_um=profile.x_um[columns], T=T, T_err=T_err,
                shift_um=profile.shift_um + self.bin_offset_px(k) * pixel_um, image=None, image_err=None))
        return profiles


class _RowSolver:
    """Every row's own parameters with the shared values fixed: one compiled program for all rows."""

    def __init__(self, scene: Scene, profile: Profile, shared: FitResult, fitter: Fitter, names: _Names,
                 accuracy):
        row_profile = dataclasses.replace(profile, image=None, image_err=None, T=None, T_err=None)
        sample = shared.scene.sample
        self.scene = dataclasses.replace(scene, sample=sample, profiles=(row_profile,),
                                         fit=dataclasses.replace(scene.fit, per_row=()))
        self.free = free_parameters(self.scene, vary=names.rows, bounds=names.bounds_rows)
        tilt = next((p for p in fitter.free if p.name == "sample.tilt_deg"), None)
        self.model = geometry_of(self.scene).build_model(self.scene, accuracy, [p.name for p in self.free],
                                                         None if tilt is None else (tilt.low, tilt.high))
        self.predict = Predictor(self.model, assembler(self.scene, self.free), len(self.free))
        self.compile_time_s = self.predict.compile_time_s
        self.names = [p.name for p in self.free]
        self.own = [self.names.index(n) for n in names.per_row]  # the per-row ones, centre first

    def base(self, shared: FitResult) -> np.ndarray:
        """The shared fit's values in this program's order (a per-bin profile key: their mean)."""
        values = dict(zip(shared.names, shared.values))
        out = []
        for name in self.names:
            if name in values:
                out.append(values[name])
            else:
                field = name.rsplit(".", 1)[1]
                out.append(np.mean([v for n, v in values.items() if n.startswith("profiles.") and n.endswith(field)]))
        return np.array(out)

    def values(self, base: np.ndarray, own: np.ndarray) -> np.ndarray:
        """Model rows (k, n_free): ``base`` with the per-row values ``own`` (k, n_own) set."""
        rows = np.tile(base, (len(own), 1))
        rows[:, self.own] = own
        return rows

    def solve(self, base: np.ndarray, data: np.ndarray, sigma: np.ndarray, starts: np.ndarray):
        """Per-row values (k, n_own), their errors (k, n_own), chi-square (k,), steps (k,) and
        converged (k,) of the rows data (k, n) with errors sigma (k, n) (inf: masked), from
        starts (k, n_own)."""
        parameters = [self.free[j] for j in self.own]
        data = np.where(np.isfinite(sigma), data, 0.0)

        def physical(u):
            return np.stack([p.from_unit(u[:, i]) for i, p in enumerate(parameters)], axis=1)

        def residuals(u, problems):
            T_model, _ = self.predict(self.values(base, physical(u)))
            return (T_model - data[problems]) / sigma[problems]

        u0 = np.stack([p.to_unit(starts[:, i]) for i, p in enumerate(parameters)], axis=1)
        typical = np.full(len(parameters), _TYPICAL_STEPS)
        solution = levenberg_marquardt(residuals, u0, typical, tolerance=_ROW_TOLERANCE, max_steps=_ROW_STEPS,
                                       independent=True)
        slope = np.stack([p.value_per_unit(solution.u[:, i]) for i, p in enumerate(parameters)], axis=1)
        curvature = np.einsum("kNi,kNj->kij", solution.jacobian, solution.jacobian)
        variance = np.diagonal(np.linalg.pinv(curvature, hermitian=True), axis1=1, axis2=2)
        errors = slope * np.sqrt(np.clip(variance, 0.0, None))
        return physical(solution.u), errors, solution.chi2, solution.steps, solution.converged


def fit_image(scene: Scene | str, *, accuracy: float | None = None, rounds: int = _ROUNDS,
              progress: bool | Progress = False) -> ImageFit:
    """Fit the one image profile of a scene: shared [fit] vary parameters, and per row the
    centre and the [fit] per_row parameters.

    accuracy: the model's target RMS error in T. rounds: shared fit + per-row fit, each
    round starting from the last one's rows. progress: rows done, rate and time left on
    stderr. Needs float64 (``jax_enable_x64``).
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    if rounds < 1:
        raise FwdfitError(f"rounds must be >= 1, got {rounds}")
    say = as_progress(progress)
    profile = _image_profile(scene)
    names = _names(scene, profile)
    pixel = scene.instruments[profile.instrument].pixel_um
    sigma, sigma_from_data = _row_sigma(profile)
    n_pixels = np.isfinite(sigma).sum(axis=1)
    masked = np.isnan(profile.image)
    begin = time.perf_counter()
    usable = np.isnan(profile.image).mean(axis=1) <= _MAX_MASKED
    with say.ticking("finding the faces in each row"):
        faces = find_faces(scene, profile, profile.image, usable, accuracy)
    edges, flags = edge_centres(scene, profile, accuracy, faces)
    seen = in_view(faces, edges, profile.x_um, pixel)
    check_determined(names.shared, seen, scene, scene.path)
    n_rows, n_own = len(edges), len(names.per_row)
    say(f"{profile.name}: {n_rows} rows x {profile.image.shape[1]} pixels, {int(masked.sum())} masked pixels; "
        f"edges found in {int(np.isfinite(edges).sum())} rows; faces in view: "
        f"{', '.join(str(int(j)) for j in np.flatnonzero(seen))} of 0-{len(seen) - 1}")
    binning = _Binning.of(edges, pixel)
    todo = np.flatnonzero((flags & _UNFITTED) == 0)
    use, centres = np.isfinite(edges), edges.copy()
    fitter = rows = shared = None
    compile_time, row_time = faces.compile_time_s, 0.0
    for round_ in range(rounds):
        reference = binning.reference_um(centres, use, pixel)
        profiles = binning.profiles(profile, centres, use, sigma, pixel, reference)
        weighted = sum(int(np.count_nonzero(p.T_err < _NO_WEIGHT)) for p in profiles)
        if fitter is None:
            say(f"compiling the model for {len(profiles)} averaged profiles, then for one row "
                "(seconds each once cached)")
            bin_scene = dataclasses.replace(
                scene, sample=dataclasses.replace(scene.sample, centre_um=binning.centre_um),
                profiles=tuple(profiles), fit=dataclasses.replace(scene.fit, per_row=()))
            with say.ticking("compiling"):
                fitter = Fitter(bin_scene, vary=names.shared, bounds=names.bounds_shared, accuracy=accuracy)
            compile_time += fitter.compile_time_s
            shared = fitter()
        else:
            # the global scan again (the last values one more candidate): the first round's
            # bins, from the edges' centres, can hold it in a wrong minimum (2 % noise: 17 µm
            # too thick), the fitted centres' bins not
            shared = fitter(T=[p.T for p in profiles], T_err=[p.T_err for p in profiles], start=shared.values)
        shared_dof = weighted - len(shared.names)
        say(f"round {round_ + 1}: shared fit of {int(use.sum())} rows in {len(profiles)} averaged profiles, "
            f"chi2/dof {shared.chi2 / max(shared_dof, 1):.4g}")
        if rows is None:
            with say.ticking("compiling the per-row model"):
                rows = _RowSolver(scene, profile, shared, fitter, names, accuracy)
            compile_time += rows.compile_time_s
        base = rows.base(shared)
        if round_ == 0:  # each row starts where its edges (or its neighbours') put it, moved by their common bias
            values = np.tile(base[rows.own], (n_rows, 1))
            known = np.flatnonzero(np.isfinite(edges))
            values[:, 0] = np.interp(np.arange(n_rows), known, edges[known]) + shared[CENTRE][0] - binning.centre_um
        starts = values
        row_begin = time.perf_counter()
        out = _solve_rows(rows, base, profile.image, sigma, todo, starts, say, round_ + 1)
        row_time = time.perf_counter() - row_begin
        values, errors = np.full((n_rows, n_own), np.nan), np.full((n_rows, n_own), np.nan)
        chi2, steps, converged = np.full(n_rows, np.nan), np.zeros(n_rows, int), np.zeros(n_rows, bool)
        values[todo], errors[todo], chi2[todo], steps[todo], converged[todo] = out
        if sigma_from_data:
            errors *= np.sqrt(chi2 / np.maximum(n_pixels - n_own, 1))[:, None]
        flags = flags & _UNFITTED
        z = (chi2 - n_pixels) / np.sqrt(2.0 * np.maximum(n_pixels, 1))
        poor = (chi2 / np.maximum(n_pixels, 1) > _POOR_LIMIT) & (z > _POOR_SIGNIFICANCE)
        flags[todo] |= np.where(poor[todo], FLAG_POOR_FIT, 0) | np.where(converged[todo], 0, FLAG_NOT_CONVERGED)
        use, centres = flags == 0, values[:, 0]
        if not use.any():
            raise FwdfitError(f"{profile.image_file}: no row is fitted well (every row flagged)")
    T_model, T_att = np.full(profile.image.shape, np.nan), np.full(profile.image.shape, np.nan)
    T_model[todo], T_att[todo] = rows.predict(rows.values(base, values[todo]))
    fitted = (flags & _UNFITTED) == 0
    T_corrected = np.where(fitted[:, None], profile.image - (T_model - T_att), profile.image)
    line = edge_line(values[:, 0], errors[:, 0], flags == 0, pixel, scene.sample.rotation_deg, names.rotation,
                     str(profile.image_file))
    wall = time.perf_counter() - begin - compile_time
    result = ImageFit(profile.name, profile.x_um, shared, names.per_row, values, errors, edges, chi2, n_pixels,
                      steps, flags, profile.image, sigma, T_model, T_att, T_corrected, sigma_from_data,
                      int(masked.sum()), compile_time, wall, row_time, rounds, profile.image_layout, line,
                      shared_dof)
    say(result.summary())
    return result


def _solve_rows(rows: _RowSolver, base, image, sigma, todo, starts, say, round_: int):
    """The per-row solver over the rows ``todo`` in chunks, with a progress line per chunk."""
    parts = []
    begin = time.perf_counter()
    for first in range(0, len(todo), _CHUNK_ROWS):
        chunk = todo[first:first + _CHUNK_ROWS]
        parts.append(rows.solve(base, image[chunk], sigma[chunk], starts[chunk]))
        done = first + len(chunk)
        rate = done / max(time.perf_counter() - begin, 1e-9)
        say(f"round {round_}: rows {done}/{len(todo)}, {rate:.1f} rows/s, "
            f"{(len(todo) - done) / rate:.0f} s left")
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))
