"""Time-of-flight fit outputs: the T_att and corrected stacks, and the Bragg-edge spectrum.

Written by ``write_fit`` beside the per-profile files when at least two profiles have
band spectra (wavelength bins): ``tof_stack.csv`` (long format, one row per bin and
pixel), ``spectrum.csv`` and ``spectrum.png`` (the mean over a region inside the sample
away from its faces, the geometry's ``plateau``, data against fit, per bin).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..inference._fit import FitResult
from ..scene._spectrum import BandSpectrum
from ..inference._geometry import geometry_of
from ..io._tables import write_columns


def tof_bins(result: FitResult) -> list[int]:
    """Indices of the profiles whose spectra are bands (time-of-flight bins); [] for fewer than two."""
    scene = result.scene
    bins = [i for i, p in enumerate(scene.profiles) if isinstance(scene.spectra[p.spectrum], BandSpectrum)]
    return bins if len(bins) >= 2 else []


def away_from_edges(scene, index: int) -> np.ndarray:
    """Pixels (bool, (n,)) of profile ``index`` where the spectrum is read: inside the sample,
    away from its faces (the geometry's ``plateau``: a block's thickest layer, a cylinder's
    innermost circle about the axis), in the fitted scene."""
    return geometry_of(scene).plateau(scene, scene.profiles[index])


def spectrum_table(result: FitResult, bins: list[int]) -> dict[str, np.ndarray]:
    """Per bin: wavelength band (Å), the measured mean T and its error, and the fitted T_model and
    T_att means over the region away from the edges (``away_from_edges``); NaN where it is empty."""
    scene = result.scene
    columns = {key: np.full(len(bins), np.nan) for key in
               ("lambda_A", "lambda_min_A", "lambda_max_A", "T", "T_err", "T_model", "T_att", "pixels")}
    for row, i in enumerate(bins):
        band = scene.spectra[scene.profiles[i].spectrum]
        fitted = result.profiles[i]
        region = away_from_edges(scene, i)
        columns["lambda_min_A"][row], columns["lambda_max_A"][row] = band.lambda_min_A, band.lambda_max_A
        columns["lambda_A"][row] = band.mean_wavelength_A
        columns["pixels"][row] = region.sum()
        if region.any():
            columns["T"][row] = fitted.T[region].mean()
            columns["T_err"][row] = math.sqrt(np.sum(fitted.sigma[region] ** 2)) / region.sum()
            columns["T_model"][row] = fitted.T_model[region].mean()
            columns["T_att"][row] = fitted.T_att[region].mean()
    return columns


def plot_spectrum(path: Path, columns) -> None:
    """Measured mean T with error bars against the fitted T_att, per bin (a ``Figure`` of its own)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4))
    axes = fig.subplots()
    axes.errorbar(columns["lambda_A"], columns["T"], yerr=columns["T_err"], fmt=".", color="0.3", ms=4,
                  label="measured T (region away from the edges)")
    axes.step(columns["lambda_A"], columns["T_att"], where="mid", color="C2", label="fit T_att")
    axes.set_xlabel("wavelength (Å)")
    axes.set_ylabel("transmission T")
    axes.legend(loc="best", fontsize=8)
    fig.subplots_adjust(left=0.12, right=0.97, top=0.95, bottom=0.13)
    fig.savefig(path, dpi=100)


def write_tof(result: FitResult, folder: Path) -> None:
    """tof_stack.csv, spectrum.csv and spectrum.png into ``folder`` when the fit has bins."""
    bins = tof_bins(result)
    if not bins:
        return
    scene = result.scene
    stack = [result.profiles[i] for i in bins]
    bands = [scene.spectra[scene.profiles[i].spectrum] for i in bins]
    repeat = lambda values: np.concatenate([np.full(p.x_um.size, v) for p, v in zip(stack, values)])
    write_columns(folder / "tof_stack.csv", {
        "bin": repeat(range(len(bins))),
        "lambda_min_A": repeat([b.lambda_min_A for b in bands]),
        "lambda_max_A": repeat([b.lambda_max_A for b in bands]),
        "x_um": np.concatenate([p.x_um for p in stack]),
        "T_att": np.concatenate([p.T_att for p in stack]),
        "T_att_err": np.concatenate([p.T_att_err for p in stack]),
        "T_corrected": np.concatenate([p.T_corrected for p in stack])})
    columns = spectrum_table(result, bins)
    if np.isfinite(columns["T"]).any():
        write_columns(folder / "spectrum.csv", columns, allow_nan=True)
        plot_spectrum(folder / "spectrum.png", columns)
