"""Time-of-flight stacks to one transmission profile per wavelength bin.

Per bin (after summing ``rebin`` adjacent bins of every stack): ``T = (S - D) / (O - D)``
over the region of interest, averaged along its rows as :func:`fwdfit._radiograph.average_rows`
does for one image. Bins stream one at a time: memory holds the rows of interest of
one bin, never the stack. Wavelengths from the time of flight ``t`` over the flight
path ``L``: ``lambda = (h / m_n) t / L`` (de Broglie), ``h / m_n = 3956.034 m Å / s``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from .._errors import FwdfitError
from ..images._radiograph import (Roi, average_rows, check_roi, dose_correct, edge_angle_deg,
                          normalise, sheared_roi)
from ..io._tof_read import TofStack, check_same_bins

H_OVER_NEUTRON_MASS_M_A_PER_S = 3956.034  # h / m_n in m Å / s
ERROR_MODES = ("rows", "counts")


@dataclasses.dataclass(frozen=True)
class TofProfiles:
    """Profiles of every (rebinned) wavelength bin of one region of interest.

    Attributes:
        x_um: ``(n_cols,)`` pixel centres from the ROI's first column (times
            ``cos(angle_deg)`` when rotated), as for one radiograph.
        T, T_err: ``(n_bins, n_cols)`` transmission and its 1-sigma error per bin.
        tof_edges_s: ``(n_bins + 1,)`` bin edges, seconds, the offset applied.
        wavelength_edges_A: ``(n_bins + 1,)`` the same edges as wavelengths, Å.
        angle_deg: the angle taken out with ``rotate`` (0 without), degrees.
    """

    x_um: np.ndarray
    T: np.ndarray
    T_err: np.ndarray
    tof_edges_s: np.ndarray
    wavelength_edges_A: np.ndarray
    angle_deg: float


def wavelength_A(tof_s: np.ndarray, flight_path_m: float) -> np.ndarray:
    """de Broglie wavelength (Å) of neutrons that fly ``flight_path_m`` in ``tof_s``."""
    return H_OVER_NEUTRON_MASS_M_A_PER_S * np.asarray(tof_s, dtype=np.float64) / flight_path_m


def rebin_groups(n_bins: int, rebin: int) -> list[tuple[int, int]]:
    """``(start, stop)`` of each group of ``rebin`` adjacent bins; the last holds the rest."""
    if not (isinstance(rebin, int) and rebin >= 1):
        raise FwdfitError(f"--rebin must be a positive integer, got {rebin!r}")
    return [(start, min(start + rebin, n_bins)) for start in range(0, n_bins, rebin)]


def _summed_rows(stack: TofStack | None, group: tuple[int, int], rows: slice,
                 n_cols: int, check_counts: bool) -> np.ndarray:
    """Rows ``rows`` of a stack summed over the bins of ``group`` (zeros for no stack)."""
    total = np.zeros((rows.stop - rows.start, n_cols))
    if stack is None:
        return total
    for index in range(*group):
        values = stack.read_rows(index, rows.start, rows.stop)
        if check_counts and not (np.all(values >= 0) and np.all(values == np.round(values))):
            raise FwdfitError(f"{stack.source}: bin {index} holds values that are not counts "
                              "(negative or fractional); --errors counts needs counts")
        total += values
    return total


def _counts_variance(sample: np.ndarray, open_beam: np.ndarray, dark: np.ndarray) -> np.ndarray:
    """Poisson variance of ``T = (S - D) / (O - D)`` from the counts (first order)."""
    beam = open_beam - dark
    return (sample + dark) / beam**2 + (sample - dark) ** 2 * (open_beam + dark) / beam**4


def tof_profiles(sample: TofStack, open_beam: TofStack, dark: TofStack | None,
                 roi: Sequence[int], pixel_um: float, flight_path_m: float, *,
                 tof_offset_us: float = 0.0, rebin: int = 1, rotate: bool = False,
                 dose_roi: Sequence[int] | None = None, errors: str = "rows") -> TofProfiles:
    """One profile per (rebinned) time bin from sample, open-beam and optional dark stacks.

    Args:
        sample, open_beam, dark: stacks with the same bins and image shape (dark may
            be None: no dark counts).
        roi: ``(R0, R1, C0, C1)`` half-open pixel indices, at least 2 rows.
        pixel_um: pixel pitch, um.
        flight_path_m: source (moderator) to detector, m.
        tof_offset_us: added to every recorded time (us): the delay of the recording's
            start after the neutron pulse (may be negative).
        rebin: sum this many adjacent bins of every stack before normalising.
        rotate: straighten the ROI by the angle of its strongest edge, found once in
            the transmission summed over all bins and applied to every bin.
        dose_roi: a sample-free region: each bin's T is divided by its mean there.
        errors: ``"rows"``: spread over the ROI rows, as for one radiograph;
            ``"counts"``: Poisson errors of the counts (integer data, not with rotate).
    """
    if not (math.isfinite(flight_path_m) and flight_path_m > 0):
        raise FwdfitError(f"--flight-path-m must be a positive length in m, got {flight_path_m}")
    if not math.isfinite(tof_offset_us):
        raise FwdfitError(f"--tof-offset-us must be finite, got {tof_offset_us}")
    if not (math.isfinite(pixel_um) and pixel_um > 0):
        raise FwdfitError(f"pixel_um must be positive, got {pixel_um}")
    if errors not in ERROR_MODES:
        raise FwdfitError(f"errors must be one of {', '.join(ERROR_MODES)}, got {errors!r}")
    if errors == "counts" and rotate:
        raise FwdfitError("--errors counts cannot be used with --rotate (interpolated pixels "
                          "share counts); use --errors rows")
    stacks = {"sample": sample, "open beam": open_beam}
    if dark is not None:
        stacks["dark"] = dark
    check_same_bins(stacks)
    if errors == "counts":
        not_counts = [name for name, stack in stacks.items() if not stack.integer_valued]
        if not_counts:
            raise FwdfitError(f"--errors counts needs integer counts; {not_counts[0]} "
                              f"({stacks[not_counts[0]].source}) stores floating-point values")
    tof_edges_s = sample.tof_edges_s + tof_offset_us * 1e-6
    if tof_edges_s[0] <= 0:
        raise FwdfitError(f"the first bin starts at time of flight {tof_edges_s[0]:g} s, not "
                          "after the pulse: check --tof-offset-us")
    groups = rebin_groups(sample.n_bins, rebin)
    edges_s = np.array([tof_edges_s[start] for start, _ in groups] + [tof_edges_s[-1]])
    region = check_roi(roi, sample.shape)
    if region.row_stop - region.row_start < 2:
        raise FwdfitError(f"ROI ({region}) needs at least 2 rows for T_err")
    if rotate and region.col_stop - region.col_start < 4:
        raise FwdfitError(f"ROI ({region}) needs at least 4 columns to find an edge to rotate")
    dose_region = None if dose_roi is None else check_roi(dose_roi, sample.shape, "dose ROI")
    # Only the rows of the ROI and dose region are read; regions shift into them.
    used = [r for r in (region, dose_region) if r is not None]
    rows = slice(min(r.row_start for r in used), max(r.row_stop for r in used))
    local = [Roi(r.row_start - rows.start, r.row_stop - rows.start, r.col_start, r.col_stop)
             for r in used]
    n_cols = sample.shape[1]

    def bin_image(group):
        counts = [_summed_rows(stack, group, rows, n_cols, errors == "counts")
                  for stack in (sample, open_beam, dark)]
        return counts, normalise(*counts, local)

    angle_deg = 0.0
    if rotate:
        _, white = bin_image((0, sample.n_bins))
        if dose_region is not None:
            white = dose_correct(white, local[1])
        angle_deg = edge_angle_deg(white, local[0])
    tilt = math.tan(math.radians(angle_deg))
    column_spacing_um = pixel_um * math.cos(math.radians(angle_deg))
    T, T_err = [], []
    for index, group in enumerate(groups):
        try:
            counts, image = bin_image(group)
            variance = _counts_variance(*counts) if errors == "counts" else None
            if dose_region is not None:
                scale = float(np.mean(image[local[1].slices]))
                image = dose_correct(image, local[1])
                variance = None if variance is None else variance / scale**2
            roi_image = sheared_roi(image, local[0], tilt) if rotate else image[local[0].slices]
            x_um, T_bin, T_err_bin = average_rows(roi_image, column_spacing_um)
        except FwdfitError as error:
            raise FwdfitError(f"bin {index} ({wavelength_A(edges_s[index], flight_path_m):.4g}"
                              f"-{wavelength_A(edges_s[index + 1], flight_path_m):.4g} A): "
                              f"{error} (--rebin sums bins)") from None
        if variance is not None:
            T_err_bin = np.sqrt(variance[local[0].slices].sum(axis=0)) / roi_image.shape[0]
        T.append(T_bin)
        T_err.append(T_err_bin)
    return TofProfiles(x_um=x_um, T=np.array(T), T_err=np.array(T_err), tof_edges_s=edges_s,
                       wavelength_edges_A=wavelength_A(edges_s, flight_path_m),
                       angle_deg=angle_deg)
