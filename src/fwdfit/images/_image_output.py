"""Image-fit results to files: T_att.tif, T_corrected.tif, residual.tif (float32, the
input's shape), rows.csv, result.json and overview.png, all or nothing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._errors import FwdfitError
from ..outputs._fit_output import result_dict, spectrum_label
from ._image_fit import (FLAG_MASKED, FLAG_NO_EDGE, FLAG_NOT_CONVERGED, FLAG_POOR_FIT, ImageFit)
from ..io._tables import staged_folder, write_columns

FLAG_NAMES = {FLAG_NO_EDGE: "no_edge", FLAG_MASKED: "masked", FLAG_POOR_FIT: "poor_fit",
              FLAG_NOT_CONVERGED: "not_converged"}


def image_result_dict(result: ImageFit) -> dict:
    """result.json: the shared parameters (as ``fwdfit fit`` writes them, from the fit of the
    averaged rows), chi-square over every fitted row, the rows' flags, masked pixels, timings."""
    summary = result_dict(result.shared)
    summary["shared_fit_chi2_reduced"] = summary.pop("chi2_reduced")
    for key in ("chi2", "dof", "chi2_per_start"):
        summary.pop(key)
    counts = {name: int(np.count_nonzero(result.flags & flag)) for flag, name in FLAG_NAMES.items()}
    summary.update({
        "chi2_reduced": result.chi2_reduced,
        "accepted": result.accepted,
        "rows": {"total": len(result.flags), "fitted": int(result.fitted.sum()),
                 "flagged": int(np.count_nonzero(result.flags)), "flags": counts},
        "masked_pixels": result.n_masked,
        "sigma_from_data": result.sigma_from_data,
        "rounds": result.rounds,
        "per_row": list(result.per_row),
        "compile_time_s": result.compile_time_s,
        "solve_time_s": result.wall_time_s,
        "wall_time_s": result.compile_time_s + result.wall_time_s,
        "rows_per_s": result.rows_per_s,
    })
    return summary


def _column(name: str) -> str:
    """rows.csv column of a per-row parameter: tilt_deg, norm, Al.thickness_um, ..."""
    parts = name.split(".")
    return ".".join(parts[1:]) if parts[0] == "layers" else parts[-1]


def overview_title(result: ImageFit) -> str:
    """Two lines: the image's distance and wavelength or band; its rows, chi2/dof and the verdict."""
    scene = result.shared.scene
    profile = scene.profiles[0]
    verdict = "accepted" if result.accepted else "rejected"
    return (f"distance {profile.distance_mm:g} mm, {spectrum_label(scene.spectra[profile.spectrum])}\n"
            f"{result.summary()}: {verdict}")


def plot_overview(path: Path, result: ImageFit):
    """The data, T_corrected and the normalised residuals as images, and the centre per row;
    written to ``path`` (PNG), the ``Figure`` returned.

    Drawn on a ``Figure`` of its own: pyplot's state and backend are left alone."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7))
    axes = fig.subplots(2, 2)
    extent = (result.x_um[0], result.x_um[-1], len(result.flags) - 0.5, -0.5)
    low, high = np.nanpercentile(result.T, [1, 99])
    residual = (result.T - result.T_model) / result.sigma
    for ax, image, title, limits, cmap in (
            (axes[0, 0], result.T, "measured T", (low, high), "gray"),
            (axes[0, 1], result.T_corrected, "T_corrected (refraction removed)", (low, high), "gray"),
            (axes[1, 0], residual, "(T - T_model) / σ", (-4, 4), "coolwarm")):
        shown = ax.imshow(image, aspect="auto", extent=extent, vmin=limits[0], vmax=limits[1], cmap=cmap,
                          interpolation="nearest")
        fig.colorbar(shown, ax=ax)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("row")
    ax = axes[1, 1]
    rows = np.arange(len(result.flags))
    ax.errorbar(rows, result.centre_um, result.centre_err_um, fmt=".", ms=3, color="C0", label="fitted centre")
    ax.plot(rows, result.edge_centre_um, "-", lw=0.8, color="0.6", label="from the edges (start)")
    flagged = result.flags != 0
    ax.plot(rows[flagged], np.where(np.isfinite(result.centre_um), result.centre_um,
                                    np.nanmedian(result.centre_um))[flagged], "x", color="C3", label="flagged")
    ax.set_xlabel("row")
    ax.set_ylabel("centre (µm)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    ax.set_title("centre per row, ±1σ", fontsize=9)
    fig.suptitle(overview_title(result), fontsize=9, x=0.07, ha="left",
                 color="black" if result.accepted else "tab:red")
    fig.subplots_adjust(left=0.07, right=0.85, top=0.9, bottom=0.08, hspace=0.35, wspace=0.2)
    fig.savefig(path, dpi=90)
    return fig


def write_image_fit(result: ImageFit, out_dir: Path) -> None:
    """Write T_att.tif, T_corrected.tif, residual.tif, rows.csv, result.json and overview.png.

    The images have the input file's shape and orientation, NaN outside the region (roi);
    masked pixels are NaN, and rows not fitted are NaN in T_att and residual.tif (their
    T_corrected is the data). rows.csv numbers the profiles as the file does (``row``, or
    ``column`` with profile_along = "columns"). Nothing is written if anything fails.
    """
    import tifffile

    try:
        summary = json.dumps(image_result_dict(result), indent=2, allow_nan=False) + "\n"
    except ValueError:
        raise FwdfitError("result.json: a value is NaN or infinite; nothing written "
                          "(please report this image)") from None
    fitted = result.fitted
    if not np.all(np.isfinite(result.T_att[fitted])):
        raise FwdfitError("T_att is NaN or infinite in a fitted row; nothing written (please report this image)")
    layout = result.layout
    first = 0 if layout is None else layout.first[0]
    columns = {"row" if layout is None or layout.along == "rows" else "column": first + np.arange(len(result.flags))}
    for i, name in enumerate(result.per_row):
        columns[_column(name)] = result.row_values[:, i]
        columns[_column(name) + "_err"] = result.row_errors[:, i]
    columns.update({"edge_centre_um": result.edge_centre_um, "chi2": result.chi2, "n_pixels": result.n_pixels,
                    "chi2_reduced": result.chi2 / np.maximum(result.n_pixels - len(result.per_row), 1),
                    "steps": result.steps, "flag": result.flags})
    with staged_folder(Path(out_dir)) as staging:
        (staging / "result.json").write_text(summary)
        write_columns(staging / "rows.csv", columns, allow_nan=True)
        for name, image in (("T_att", result.T_att), ("T_corrected", result.T_corrected),
                            ("residual", (result.T - result.T_model) / result.sigma)):
            image = image if layout is None else layout.image(image)  # the input's shape and orientation
            tifffile.imwrite(staging / f"{name}.tif", image.astype(np.float32))
        plot_overview(staging / "overview.png", result)
