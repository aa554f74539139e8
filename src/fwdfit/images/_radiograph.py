"""Measured radiographs to 1-D profiles: TIFF stacks -> normalised radiograph -> ROI average.

The flow: expand each of sample, open beam and dark (a file, a folder or a glob) into
TIFF files; combine each stack into one image, streaming over blocks of rows so that
memory holds one block of every frame (never the stack); normalise
``T = (I - D) / (O - D)``; optionally correct the dose and straighten the region of
interest (ROI) so that the interfaces run along its columns; average along the rows.

Units: images are in detector counts (any scale), positions in pixels unless the name
says ``_um``. Images are ``(row, column)`` arrays; rows run down the detector, columns
across the beam (the profile's x).
"""

from __future__ import annotations

import dataclasses
import functools
import glob
import logging
import math
import os
import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np
import tifffile

from .._errors import FwdfitError
from ..io._tables import check_finite
from ..outputs._plotting import draw_error_band

TIFF_SUFFIXES = (".tif", ".tiff")
COMBINE_METHODS = ("median", "mean")
# Default k of the white-spot (gamma) test: a pixel further than k robust standard
# deviations above its local median is a spot. At k = 5 a 2048 x 2048 frame of pure
# Gaussian noise loses a handful of pixels to their local median (harmless), while a
# gamma hit (hundreds to thousands of counts) is far above the limit.
SPOT_THRESHOLD = 5.0
# The local median runs along the column, over 2 * 3 + 1 = 7 pixels, not over a square:
# the interfaces to be measured run along the columns and their refraction peaks are
# one or two pixels wide, so a 3 x 3 or 5 x 5 median would remove them as spots. A
# spot (or cluster) up to 3 pixels tall is removed.
SPOT_HALF_WINDOW_ROWS = 3
MAD_TO_SIGMA = 1.4826  # standard deviation / median absolute deviation, Gaussian noise
# Memory for one block of rows of every frame (float32); the combination needs about
# three times this, plus a few full frames.
BLOCK_BYTES = 64 * 2**20
MAX_EDGE_ANGLE_DEG = 5.0  # the edge search reaches this far from the columns
EDGE_SMOOTH_ROWS = 5  # rows averaged before locating the edge in each row


class Roi(NamedTuple):
    """Half-open pixel rectangle: rows ``row_start:row_stop``, columns ``col_start:col_stop``."""

    row_start: int
    row_stop: int
    col_start: int
    col_stop: int

    @property
    def slices(self) -> tuple[slice, slice]:
        """``(rows, columns)`` slices that cut the region out of an image."""
        return slice(self.row_start, self.row_stop), slice(self.col_start, self.col_stop)

    def __str__(self) -> str:
        return (f"rows {self.row_start}:{self.row_stop}, "
                f"columns {self.col_start}:{self.col_stop}")


@dataclasses.dataclass(frozen=True)
class RadiographProfile:
    """A profile measured from radiographs, with the images it came from.

    Attributes:
        x_um: ``(n_cols,)`` pixel centres, ``x_um[j] = j * pixel_um`` for ROI column
            ``col_start + j`` (x measured from the ROI's first column); times
            ``cos(angle_deg)`` when rotated, the spacing across the edges.
        T: ``(n_cols,)`` transmission averaged over the ROI rows.
        T_err: ``(n_cols,)`` 1-sigma uncertainty of ``T``: standard deviation over the
            rows (``ddof=1``) divided by the square root of the number of rows.
        image: ``(n_rows, n_cols)`` of the detector: normalised (and dose-corrected)
            transmission, NaN where the open beam is not brighter than the dark.
        roi_image: ``(roi rows, roi columns)`` the ROI that was averaged, straightened
            when rotated (NaN where a row moved off the image).
        roi: the region of interest.
        angle_deg: angle of the edges from the columns taken out, degrees (0 without
            ``rotate``): their column grows by ``tan(angle)`` per row down the detector.
    """

    x_um: np.ndarray
    T: np.ndarray
    T_err: np.ndarray
    image: np.ndarray
    roi_image: np.ndarray
    roi: Roi
    angle_deg: float


# ----------------------------------------------------------------------------- reading


def tiff_files(spec: str | os.PathLike) -> list[Path]:
    """Expand a TIFF file, a folder of TIFFs (``.tif``/``.tiff``) or a glob into sorted files."""
    text = os.path.expanduser(os.fspath(spec))
    if any(char in text for char in "*?["):
        files = sorted(Path(p) for p in glob.glob(text) if Path(p).is_file())
        if not files:
            raise FwdfitError(f"no files match {text}")
        return files
    path = Path(text)
    if path.is_dir():
        files = sorted(p for p in path.iterdir()
                       if p.is_file() and p.suffix.lower() in TIFF_SUFFIXES)
        if not files:
            raise FwdfitError(f"no TIFF files (.tif, .tiff) in folder {path}")
        return files
    if path.is_file():
        return [path]
    raise FwdfitError(f"no such file or folder: {path}")


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message, for one-line errors."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


@contextmanager
def _open_tiff(path: Path) -> Iterator[tifffile.TiffFile]:
    """Open a TIFF file, turning read errors into a FwdfitError that names it.

    tifffile's own log (e.g. "invalid page offset" in a file cut short) is kept off the
    terminal meanwhile: :func:`_check_complete` reports such files in one line.
    """
    quiet = logging.NullHandler()
    logging.getLogger("tifffile").addHandler(quiet)
    try:
        try:
            tif = tifffile.TiffFile(path)
        except Exception as exc:  # tifffile raises many types (OSError, struct.error, ...)
            raise FwdfitError(f"cannot read TIFF file {path}: {_first_line(exc)}") from None
        with tif:
            yield tif
    finally:
        logging.getLogger("tifffile").removeHandler(quiet)


def _declared_frames(tif: tifffile.TiffFile, first: tifffile.TiffPage) -> int | None:
    """Frames (pages like ``first``) the file's metadata declares (ImageJ ``images=``,
    tifffile's shapes), if it declares any."""
    try:
        if tif.imagej_metadata and "images" in tif.imagej_metadata:
            return int(tif.imagej_metadata["images"])
        shapes = [m["shape"] for m in tif.shaped_metadata or () if "shape" in m]
        return sum(math.prod(shape) for shape in shapes) // first.size if shapes else None
    except Exception:  # unreadable metadata declares nothing
        return None


def _chain_continues(tif: tifffile.TiffFile) -> bool:
    """Whether the last page read points to a further page (one beyond the file's end)."""
    handle = tif.filehandle
    try:
        handle.seek(tif.pages.next_page_offset)
        pointer = struct.unpack(tif.tiff.offsetformat, handle.read(tif.tiff.offsetsize))[0]
    except (struct.error, OSError, TypeError, tifffile.TiffFileError):  # pointer cut off
        return True
    return pointer != 0


def _check_complete(tif: tifffile.TiffFile, path: Path) -> None:
    """FwdfitError if the file ends before its frames do, saying how many are complete.

    A multi-page file cut short loses its last pages silently in tifffile (the page
    chain points past the end, or into a page's cut-off header); a page cut short has
    data past the end. The frames expected are the pages chained (plus the missing
    one) or the frames the metadata declares, whichever is more.
    """
    size = tif.filehandle.size
    pages, cut = [], False
    try:
        for page in tif.pages:
            pages.append(page)
    except Exception:  # tifffile: "corrupted IFD structure" and the like
        cut = True
    complete = sum(max((o + n for o, n in zip(page.dataoffsets, page.databytecounts)),
                       default=size + 1) <= size for page in pages)
    broken = cut or _chain_continues(tif)
    chained = len(pages) + broken
    declared = (_declared_frames(tif, pages[0]) if pages else None) or 0
    expected = max(chained, declared)
    if complete < expected:
        least = "at least " if broken and chained >= declared else ""
        raise FwdfitError(f"TIFF file {path} is cut short or corrupt: {complete} of "
                          f"{least}{expected} frames complete ({size} bytes); refusing to "
                          "use fewer frames")


def _page_shape(page: tifffile.TiffPage, path: Path, index: int) -> tuple[int, int]:
    """``(rows, columns)`` of a single-channel page; FwdfitError for anything else."""
    if len(page.shape) != 2:
        raise FwdfitError(f"page {index} of {path} is not a single-channel image "
                          f"(shape {page.shape})")
    return page.shape


def frame_layout(files: Sequence[Path]) -> tuple[int, tuple[int, int]]:
    """Count the frames (pages) in ``files`` and check they share one shape.

    Returns:
        ``(n_frames, (n_rows, n_cols))``. Reads headers only.
    """
    n_frames, shape, first = 0, None, None
    for path in files:
        with _open_tiff(path) as tif:
            _check_complete(tif, path)
            for index, page in enumerate(tif.pages):
                page_shape = _page_shape(page, path, index)
                if shape is None:
                    shape, first = page_shape, path
                elif page_shape != shape:
                    raise FwdfitError(
                        f"frames differ in shape: {path} (page {index}) is "
                        f"{page_shape[0]}x{page_shape[1]}, {first} is {shape[0]}x{shape[1]}")
                n_frames += 1
    return n_frames, shape


def _read_page_rows(tif: tifffile.TiffFile, page: tifffile.TiffPage,
                    start: int, stop: int) -> np.ndarray:
    """Rows ``start:stop`` of a page, ``(stop - start, n_cols)`` in the file's dtype.

    Uncompressed pages stored row after row (the usual camera output) are read from
    the file for just these rows; others are decoded whole and sliced.
    """
    if not (page.is_final and page.dtype is not None):
        return page.asarray()[start:stop]
    n_cols = page.shape[1]
    dtype = np.dtype(page.dtype).newbyteorder(tif.byteorder)
    tif.filehandle.seek(page.dataoffsets[0] + start * n_cols * dtype.itemsize)
    return tif.filehandle.read_array(dtype, (stop - start) * n_cols).reshape(-1, n_cols)


def iter_frame_rows(files: Sequence[Path], start: int, stop: int) -> Iterator[np.ndarray]:
    """Yield rows ``start:stop`` of every frame in ``files``, one frame at a time.

    Yields:
        ``(stop - start, n_cols)`` float32 arrays, counts; files in order, pages in order.
    """
    for path in files:
        with _open_tiff(path) as tif:
            for index, page in enumerate(tif.pages):
                try:
                    rows = _read_page_rows(tif, page, start, stop)
                except Exception as exc:  # and its codecs more (zlib.error, ...) on bad data
                    raise FwdfitError(f"cannot read page {index} of {path}: "
                                      f"{_first_line(exc)}") from None
                yield rows.astype(np.float32)


# ----------------------------------------------------------------------- white spots


def pixel_noise(image: np.ndarray) -> float:
    """Robust standard deviation of the pixel noise, from differences down the columns.

    ``image``: ``(n_rows, n_cols)``, ``n_rows >= 2``. Rows are taken in disjoint pairs
    (independent differences). Structure that runs along the columns cancels in the
    differences; spots and edges only touch a few of them, which the median ignores.
    Where more than half the differences are zero (coarsely quantised, low counts), the
    mean absolute difference is used instead.
    """
    differences = np.abs(image[1::2] - image[0:-1:2])
    median = float(np.median(differences))
    if median > 0:
        return MAD_TO_SIGMA * median / math.sqrt(2.0)
    return math.sqrt(math.pi) / 2.0 * float(differences.mean())


def remove_spots(padded: np.ndarray, spot_threshold: float) -> np.ndarray:
    """Replace white spots (gamma hits) by the local median along the column.

    A pixel is a spot when it exceeds the median of the ``2h + 1`` pixels centred on it
    in its column (``h = SPOT_HALF_WINDOW_ROWS``) by more than ``spot_threshold`` times
    :func:`pixel_noise`. Lines along the columns (the interfaces) are kept.

    Args:
        padded: ``(n_rows + 2h, n_cols)`` counts: the rows to clean with ``h`` rows of
            context above and below.
        spot_threshold: k, in robust standard deviations.

    Returns:
        ``(n_rows, n_cols)`` the cleaned rows (a new array).
    """
    h = SPOT_HALF_WINDOW_ROWS
    n_rows = padded.shape[0] - 2 * h
    cleaned = padded[h:h + n_rows].copy()
    limit = spot_threshold * pixel_noise(padded)
    # A spot exceeds its window's minimum by more than the limit, since the median is
    # at least the minimum: a cheap test leaves few pixels for the exact median.
    window_min = functools.reduce(np.minimum, (padded[i:i + n_rows] for i in range(2 * h + 1)))
    candidates = np.nonzero(cleaned - window_min > limit)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * h + 1, axis=0)
    local_median = np.median(windows[candidates], axis=-1)
    is_spot = cleaned[candidates] - local_median > limit
    cleaned[candidates[0][is_spot], candidates[1][is_spot]] = local_median[is_spot]
    return cleaned


def _padded_rows(rows: np.ndarray, missing_above: int, missing_below: int) -> np.ndarray:
    """Mirror rows at the image's top and bottom so every pixel has a full window."""
    if missing_above == missing_below == 0:
        return rows
    return np.pad(rows, ((missing_above, missing_below), (0, 0)), mode="reflect")


# ------------------------------------------------------------------------- combining


def median_frames(stack: np.ndarray) -> np.ndarray:
    """Per-pixel median over frames: ``(n_rows, n_cols, n_frames)`` -> ``(n_rows, n_cols)``.

    Frames last, so each pixel's values are contiguous. Overwrites ``stack``.
    """
    return np.median(stack, axis=-1, overwrite_input=True)


def clipped_mean_frames(stack: np.ndarray, spot_threshold: float) -> np.ndarray:
    """Per-pixel mean over frames without temporal outliers.

    A value is left out when it lies more than ``spot_threshold`` robust standard
    deviations (``MAD_TO_SIGMA`` times the median absolute deviation over the frames,
    per pixel) from the pixel's median over the frames.

    Args:
        stack: ``(n_rows, n_cols, n_frames)`` counts, frames last.
        spot_threshold: k, at least 1 (so at least one value per pixel is kept).

    Returns:
        ``(n_rows, n_cols)`` float32.
    """
    centre = np.median(stack, axis=-1, keepdims=True)
    deviation = np.abs(stack - centre)
    limit = spot_threshold * MAD_TO_SIGMA * np.median(deviation, axis=-1, keepdims=True)
    keep = deviation <= limit
    del deviation
    total = np.where(keep, stack, 0.0).sum(axis=-1, dtype=np.float64)
    return (total / keep.sum(axis=-1)).astype(np.float32)


def _block_rows(n_frames: int, n_cols: int, block_bytes: int) -> int:
    """Rows per block so that one block of every frame (float32) fits ``block_bytes``."""
    return max(1, block_bytes // (n_frames * n_cols * 4))


def _read_block(files: Sequence[Path], layout: tuple[int, tuple[int, int]], start: int,
                stop: int, spot_threshold: float) -> np.ndarray:
    """Rows ``start:stop`` of all frames, spots removed: ``(stop - start, n_cols, n_frames)``."""
    n_frames, (n_rows, n_cols) = layout
    h = SPOT_HALF_WINDOW_ROWS
    read_start, read_stop = max(0, start - h), min(n_rows, stop + h)
    block = np.empty((stop - start, n_cols, n_frames), np.float32)
    for index, rows in enumerate(iter_frame_rows(files, read_start, read_stop)):
        padded = _padded_rows(rows, h - (start - read_start), h - (read_stop - stop))
        block[:, :, index] = remove_spots(padded, spot_threshold)
    return block


def combine_frames(files: Sequence[Path], combine: str = "median", *,
                   spot_threshold: float = SPOT_THRESHOLD,
                   block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """Combine the frames in ``files`` into one image, streaming over blocks of rows.

    White spots are removed from every frame (:func:`remove_spots`), then the frames are
    combined per pixel by ``"median"`` (:func:`median_frames`) or ``"mean"``
    (:func:`clipped_mean_frames`). Memory: about three times ``block_bytes`` plus the
    result, whatever the number of frames.

    Args:
        files: TIFF files, single- or multi-page, all pages ``(n_rows, n_cols)``.
        combine: ``"median"`` or ``"mean"``.
        spot_threshold: k of the white-spot and temporal outlier tests, >= 1.
        block_bytes: memory for one block of rows of every frame.

    Returns:
        ``(n_rows, n_cols)`` float32 counts.
    """
    if combine not in COMBINE_METHODS:
        raise FwdfitError(f"combine must be one of {', '.join(COMBINE_METHODS)}, got {combine!r}")
    if not spot_threshold >= 1:
        raise FwdfitError(f"spot_threshold must be at least 1, got {spot_threshold}")
    layout = frame_layout(files)
    n_frames, (n_rows, n_cols) = layout
    combined = np.empty((n_rows, n_cols), np.float32)
    step = _block_rows(n_frames, n_cols, block_bytes)
    for start in range(0, n_rows, step):
        stop = min(n_rows, start + step)
        block = _read_block(files, layout, start, stop, spot_threshold)
        if combine == "median":
            combined[start:stop] = median_frames(block)
        else:
            combined[start:stop] = clipped_mean_frames(block, spot_threshold)
    return combined


# --------------------------------------------------------------------- normalisation


def check_roi(roi: Sequence[int], shape: tuple[int, int], name: str = "ROI") -> Roi:
    """Check ``(R0, R1, C0, C1)`` (half-open) lies inside an image of ``shape``, non-empty."""
    if len(roi) != 4 or not all(isinstance(v, (int, np.integer)) for v in roi):
        raise FwdfitError(f"{name} must be four integers R0, R1, C0, C1, got {roi!r}")
    region = Roi(*(int(v) for v in roi))
    n_rows, n_cols = shape
    if not (0 <= region.row_start < region.row_stop <= n_rows
            and 0 <= region.col_start < region.col_stop <= n_cols):
        raise FwdfitError(f"{name} ({region}) is empty or outside the image "
                          f"(rows 0:{n_rows}, columns 0:{n_cols})")
    return region


def normalise(sample: np.ndarray, open_beam: np.ndarray, dark: np.ndarray,
              regions: Sequence[Roi]) -> np.ndarray:
    """Transmission ``T = (I - D) / (O - D)``, NaN where the open beam is not above the dark.

    Args:
        sample, open_beam, dark: ``(n_rows, n_cols)`` combined counts I, O, D.
        regions: where T must be defined: FwdfitError if ``O - D <= 0`` at any of their
            pixels.

    Returns:
        ``(n_rows, n_cols)`` float64.
    """
    beam = open_beam.astype(np.float64) - dark
    for region in regions:
        n_bad = int(np.count_nonzero(~(beam[region.slices] > 0)))
        if n_bad:
            raise FwdfitError(f"open beam darker than dark frame at {n_bad} pixels of the "
                              f"region {region}")
    beam[~(beam > 0)] = np.nan
    return (sample - dark) / beam


def dose_correct(transmission: np.ndarray, region: Roi) -> np.ndarray:
    """Divide the transmission by its mean over a sample-free ``region`` (beam dose drift)."""
    mean = float(np.mean(transmission[region.slices]))
    if not (math.isfinite(mean) and mean > 0):
        raise FwdfitError(f"mean transmission over the dose region ({region}) is {mean}, "
                          "not positive")
    return transmission / mean


# --------------------------------------------------------------------------- rotation
#
# The ROI is straightened by a shear along the rows: row r moves along the columns by
# (r - rc) tan(angle), with linear interpolation within the row. For features that run
# along the edge this is the rotation, with the column spacing across the edge equal to
# pixel_um * cos(angle). Unlike a 2-D rotation it never mixes rows, so the spread over
# the rows still gives T_err (rotated rows share source pixels and would make it too
# small).


def _running_mean_rows(image: np.ndarray, n: int) -> np.ndarray:
    """Means of ``n`` consecutive rows: ``(n_rows, n_cols)`` -> ``(n_rows - n + 1, n_cols)``."""
    cumulative = np.cumsum(image, axis=0)
    cumulative = np.concatenate([np.zeros_like(cumulative[:1]), cumulative])
    return (cumulative[n:] - cumulative[:-n]) / n


def _edge_positions(roi_image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel column of the strongest edge in each row of ``roi_image`` (coarse).

    The edge is where the mean gradient along the rows is largest; each row, averaged
    with its neighbours (``EDGE_SMOOTH_ROWS`` in all) against noise, is searched for
    the gradient of that sign only as far from it as ``MAX_EDGE_ANGLE_DEG`` allows,
    and the peak is refined by a parabola through three gradients.

    Args:
        roi_image: ``(n_rows, n_cols)`` transmission, finite; ``n_rows >= 2``,
            ``n_cols >= 4``.

    Returns:
        ``(rows, columns)``: ``(m,)`` row coordinates (centres of the averaged rows) and
        edge columns, pixel centres at integers.
    """
    n_rows = roi_image.shape[0]
    n_smooth = min(EDGE_SMOOTH_ROWS, n_rows - 1)  # keeps at least two rows for a line
    gradient = np.diff(_running_mean_rows(roi_image, n_smooth), axis=1)  # at column j + 0.5
    mean_gradient = gradient.mean(axis=0)
    edge = int(np.argmax(np.abs(mean_gradient)))
    half_width = math.ceil(n_rows * math.tan(math.radians(MAX_EDGE_ANGLE_DEG)) / 2) + 2
    lo, hi = max(0, edge - half_width), min(gradient.shape[1], edge + half_width + 1)
    window = np.sign(mean_gradient[edge]) * gradient[:, lo:hi]
    peak = np.argmax(window, axis=1)
    inner = np.clip(peak, 1, window.shape[1] - 2)
    index = np.arange(window.shape[0])
    left, mid, right = window[index, inner - 1], window[index, inner], window[index, inner + 1]
    curvature = left - 2 * mid + right
    # The vertex of the parabola, where the peak is a strict interior maximum.
    vertex = 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0)
    offset = np.where((peak == inner) & (curvature < 0), np.clip(vertex, -0.5, 0.5), 0.0)
    rows = index + (n_smooth - 1) / 2
    return rows, lo + peak + offset + 0.5


def _coarse_tilt(roi_image: np.ndarray) -> float:
    """``tan(angle)`` of the strongest edge from a line through its per-row positions.

    Fits ``column = a + tan(angle) * row``, then refits once without rows further than
    3 robust standard deviations (at least 0.5 pixel) from the line. Good to about 0.1
    degree: the parabolic peak positions lock towards whole pixels.
    """
    rows, positions = _edge_positions(roi_image)
    slope, intercept = np.polyfit(rows, positions, 1)
    residual = np.abs(positions - (intercept + slope * rows))
    # At least half the rows stay (those within the median residual): two or more.
    inliers = residual <= max(3 * MAD_TO_SIGMA * float(np.median(residual)), 0.5)
    slope, _ = np.polyfit(rows[inliers], positions[inliers], 1)
    return float(slope)


def sheared_roi(image: np.ndarray, roi: Roi, tilt: float) -> np.ndarray:
    """The ROI with row r taken ``(r - rc) * tilt`` columns further along, NaN off the image.

    ``rc`` is the ROI's centre row; values between pixel centres are linearly
    interpolated within the row. An edge whose column moves by ``tilt`` per row comes
    out along one column.

    Args:
        image: ``(n_rows, n_cols)``, ``n_cols >= 2``.
        roi: the region; columns shifted outside it come from the rest of the row.
        tilt: columns per row, ``tan(angle)``.

    Returns:
        ``(roi rows, roi columns)`` float64.
    """
    rows = np.arange(roi.row_start, roi.row_stop)
    centre_row = (roi.row_start + roi.row_stop - 1) / 2
    cols = np.arange(roi.col_start, roi.col_stop) + ((rows - centre_row) * tilt)[:, None]
    n_cols = image.shape[1]
    inside = (cols >= 0) & (cols <= n_cols - 1)
    left = np.minimum(np.floor(np.where(inside, cols, 0)).astype(np.intp), n_cols - 2)
    fraction = cols - left
    row_index = rows[:, None]
    values = image[row_index, left] * (1 - fraction) + image[row_index, left + 1] * fraction
    return np.where(inside, values, np.nan)


def _refined_tilt(image: np.ndarray, roi: Roi, tilt: float) -> float:
    """Refine ``tan(angle)`` by matching every row of the straightened ROI to their mean.

    Gauss-Newton on ``S(r, c) = P(c + (r - rc) * d)``: the residual tilt ``d`` of the
    sheared ROI S is the least-squares slope of ``S - P`` against ``(r - rc) P'(c)``,
    with P the mean over rows. Every row and every feature contributes; stops when the
    ROI's end rows move by less than 1e-3 pixel (at most 20 steps). FwdfitError when
    there is no edge or the angle leaves ``MAX_EDGE_ANGLE_DEG``.
    """
    d_row = np.arange(roi.row_start, roi.row_stop) - (roi.row_start + roi.row_stop - 1) / 2
    no_edge = FwdfitError(f"found no edge within {MAX_EDGE_ANGLE_DEG:g} degrees of the "
                          f"columns to rotate the ROI ({roi}) by")
    for _ in range(20):
        straight = sheared_roi(image, roi, tilt)
        mean_row = np.nanmean(straight, axis=0)
        regressor = d_row[:, None] * np.gradient(mean_row)[None, :]
        residual = straight - mean_row
        valid = np.isfinite(residual) & np.isfinite(regressor)
        curvature = np.sum(regressor[valid] ** 2)
        if not curvature > 0:
            raise no_edge
        step = np.sum(regressor[valid] * residual[valid]) / curvature
        tilt -= step
        if not abs(tilt) <= math.tan(math.radians(MAX_EDGE_ANGLE_DEG)):
            raise no_edge
        if abs(step) * d_row[-1] < 1e-3:
            break
    return float(tilt)


def edge_angle_deg(image: np.ndarray, roi: Roi) -> float:
    """Angle from the columns of the strongest edge in the ROI of ``image``, degrees.

    Positive when the edge's column grows down the detector: it moves by
    ``tan(angle)`` columns per row. A line through the per-row edge positions starts
    :func:`_refined_tilt`, which uses the whole ROI.

    Args:
        image: ``(n_rows, n_cols)`` transmission, finite inside ``roi``.
        roi: at least 2 rows and 4 columns.
    """
    tilt = _refined_tilt(image, roi, _coarse_tilt(image[roi.slices]))
    return math.degrees(math.atan(tilt))


# ---------------------------------------------------------------------------- profile


def average_rows(roi_image: np.ndarray,
                 column_spacing_um: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average a ROI image along its rows into ``(x_um, T, T_err)``, ignoring NaN pixels.

    ``x_um[j] = j * column_spacing_um`` is the centre of ROI column j; ``T_err`` is the
    standard deviation over the rows (``ddof=1``) over the square root of their number.

    Args:
        roi_image: ``(n_rows, n_cols)`` transmission.
        column_spacing_um: distance between column centres across the edges, um.

    Returns:
        Three ``(n_cols,)`` float64 arrays.
    """
    n_valid = np.count_nonzero(np.isfinite(roi_image), axis=0)
    if n_valid.min() < 2:
        column = int(np.argmin(n_valid))
        raise FwdfitError(f"ROI column {column} has {n_valid[column]} valid pixels; "
                          "at least 2 rows are needed for T_err")
    T = np.nanmean(roi_image, axis=0)
    T_err = np.nanstd(roi_image, axis=0, ddof=1) / np.sqrt(n_valid)
    x_um = np.arange(roi_image.shape[1]) * column_spacing_um
    return x_um, T, T_err


def _matching_stacks(sample: str | os.PathLike, open_beam: str | os.PathLike,
                     dark: str | os.PathLike) -> tuple[list[list[Path]], tuple[int, int]]:
    """The files of the three stacks and their common frame shape (from the headers)."""
    stacks = {"sample": tiff_files(sample), "open beam": tiff_files(open_beam),
              "dark": tiff_files(dark)}
    shapes = {name: frame_layout(files)[1] for name, files in stacks.items()}
    if len(set(shapes.values())) > 1:
        described = ", ".join(f"{name} {r}x{c} ({stacks[name][0]})"
                              for name, (r, c) in shapes.items())
        raise FwdfitError(f"sample, open beam and dark frames differ in shape: {described}")
    return list(stacks.values()), shapes["sample"]


def profile_from_stacks(sample: str | os.PathLike, open_beam: str | os.PathLike,
                        dark: str | os.PathLike, roi: Sequence[int], pixel_um: float, *,
                        combine: str = "median", rotate: bool = False,
                        dose_roi: Sequence[int] | None = None,
                        spot_threshold: float = SPOT_THRESHOLD) -> RadiographProfile:
    """Turn sample, open-beam and dark TIFF stacks into a transmission profile.

    Args:
        sample, open_beam, dark: each a TIFF file (single- or multi-page), a folder of
            TIFFs or a glob; uint16 or float32 frames, all of one shape.
        roi: ``(R0, R1, C0, C1)``: rows R0:R1 and columns C0:C1, half-open pixel
            indices; at least 2 rows.
        pixel_um: pixel pitch, um.
        combine: ``"median"`` or ``"mean"`` (outliers rejected) over the frames.
        rotate: straighten the ROI so its strongest edge runs along the columns
            (angle from :func:`edge_angle_deg`, applied by :func:`sheared_roi`).
        dose_roi: ``(R0, R1, C0, C1)`` of a sample-free region: T is divided by its
            mean there.
        spot_threshold: k of the white-spot and outlier tests, robust standard
            deviations (see :func:`combine_frames`).

    Returns:
        The profile, ``x_um`` measured from the ROI's first column (pixel centres).
    """
    if not (math.isfinite(pixel_um) and pixel_um > 0):
        raise FwdfitError(f"pixel_um must be positive, got {pixel_um}")
    stacks, shape = _matching_stacks(sample, open_beam, dark)
    region = check_roi(roi, shape)
    if region.row_stop - region.row_start < 2:
        raise FwdfitError(f"ROI ({region}) needs at least 2 rows for T_err")
    if rotate and region.col_stop - region.col_start < 4:
        raise FwdfitError(f"ROI ({region}) needs at least 4 columns to find an edge to rotate")
    dose_region = None if dose_roi is None else check_roi(dose_roi, shape, "dose ROI")
    images = [combine_frames(files, combine, spot_threshold=spot_threshold) for files in stacks]
    image = normalise(*images, [r for r in (region, dose_region) if r is not None])
    del images
    if dose_region is not None:
        image = dose_correct(image, dose_region)
    angle_deg = edge_angle_deg(image, region) if rotate else 0.0
    angle = math.radians(angle_deg)
    roi_image = sheared_roi(image, region, math.tan(angle)) if rotate else image[region.slices]
    x_um, T, T_err = average_rows(roi_image, pixel_um * math.cos(angle))
    return RadiographProfile(x_um=x_um, T=T, T_err=T_err, image=image, roi_image=roi_image,
                             roi=region, angle_deg=angle_deg)


# ----------------------------------------------------------------------------- output


def write_profile_csv(path: str | os.PathLike, x_um: np.ndarray, T: np.ndarray,
                      T_err: np.ndarray) -> None:
    """Write a profile table with header ``x_um,T,T_err``; arrays ``(n,)``, finite."""
    check_finite({"x_um": x_um, "T": T, "T_err": T_err}, os.fspath(path))
    table = np.column_stack([x_um, T, T_err])
    np.savetxt(path, table, delimiter=",", header="x_um,T,T_err", comments="", fmt="%.10g")


def plot_radiograph_png(path: str | os.PathLike, profile: RadiographProfile):
    """Save the normalised radiograph with the ROI drawn and, beside it, the profile with its
    ±1σ errors as PNG; return the matplotlib ``Figure``.

    Radiograph axes in pixels, colour scale from the 0.5th to the 99.5th percentile of the ROI.
    """
    region = profile.roi
    image = profile.image
    low, high = np.nanpercentile(image[region.slices], [0.5, 99.5])
    n_rows, n_cols = image.shape
    from matplotlib.figure import Figure  # here: importing matplotlib costs 0.3 s
    from matplotlib.patches import Rectangle

    figure = Figure(figsize=(12.0, min(6.0, max(3.0, 5.0 * n_rows / n_cols))), dpi=120)
    radiograph, plot = figure.subplots(1, 2, gridspec_kw={"wspace": 0.35})
    shown = radiograph.imshow(image, cmap="gray", vmin=low, vmax=high)
    radiograph.add_patch(Rectangle((region.col_start - 0.5, region.row_start - 0.5),
                                   region.col_stop - region.col_start,
                                   region.row_stop - region.row_start,
                                   fill=False, edgecolor="tab:red", linewidth=1.2, label="ROI"))
    radiograph.set_xlabel("column (pixel)")
    radiograph.set_ylabel("row (pixel)")
    radiograph.set_title(f"normalised radiograph, ROI {region}", fontsize=9)
    # A colour bar as tall as the image, whatever its shape; "tight" makes room for it.
    figure.colorbar(shown, cax=radiograph.inset_axes([1.02, 0.0, 0.03, 1.0]), label="T")
    (line,) = plot.plot(profile.x_um, profile.T, "-", lw=1, color="C0")
    draw_error_band(plot, line, profile.T_err, "T (mean over the ROI rows)")
    plot.set_xlabel(f"x (µm) from column {region.col_start}")
    plot.set_ylabel("transmission T")
    rotated = f", rotated {profile.angle_deg:.3f}°" if profile.angle_deg else ""
    plot.set_title(f"profile: {len(profile.x_um)} pixels, {region.row_stop - region.row_start} rows{rotated}",
                   fontsize=9)
    plot.legend(loc="upper left", bbox_to_anchor=(0.0, -0.15), fontsize=8, frameon=False)
    figure.savefig(path, format="png", bbox_inches="tight")
    return figure
