"""Posterior draws to files: chains.csv, posterior.json and corner.png."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._errors import FwdfitError
from ..inference._sample import Posterior
from ..io._tables import staged_folder, write_columns

_BINS = 30  # histogram bins per axis of the corner plot


def plot_corner(path: Path, posterior: Posterior) -> None:
    """Corner plot: 1-D histograms on the diagonal, 2-D histograms below it, the
    least-squares value and its ±1σ covariance error marked. A ``Figure`` of its own."""
    from matplotlib.figure import Figure

    flat = posterior.draws.reshape(-1, len(posterior.names))
    n = flat.shape[1]
    fig = Figure(figsize=(2.0 * n + 1, 2.0 * n + 1))
    axes = np.atleast_2d(fig.subplots(n, n, squeeze=False))
    fig.subplots_adjust(left=0.1, right=0.98, top=0.98, bottom=0.1, wspace=0.08, hspace=0.08)
    best, error = posterior.fit.values, posterior.fit.errors
    for i in range(n):
        for j in range(n):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            ax.ticklabel_format(useOffset=False)  # values as written, no "+1e3" beside the axis
            if i == j:
                ax.hist(flat[:, i], bins=_BINS, color="C0", histtype="stepfilled", alpha=0.6)
                ax.axvline(best[i], color="C3", lw=1)
                ax.axvspan(best[i] - error[i], best[i] + error[i], color="C3", alpha=0.15, lw=0)
                ax.set_yticks([])
            else:
                ax.hist2d(flat[:, j], flat[:, i], bins=_BINS, cmap="Blues")
                ax.plot(best[j], best[i], "+", color="C3", ms=8)
            if i == n - 1:
                ax.set_xlabel(posterior.names[j], fontsize=7)
                ax.tick_params(axis="x", labelsize=6, labelrotation=45)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(posterior.names[i], fontsize=7)
                ax.tick_params(axis="y", labelsize=6)
            elif i != j:
                ax.set_yticklabels([])
    fig.savefig(path, dpi=90)


def write_posterior(posterior: Posterior, out_dir: Path) -> None:
    """Write chains.csv (chain, draw, one column per free parameter), posterior.json and
    corner.png into out_dir, all or nothing (staged like the fit's files)."""
    try:
        summary = json.dumps(posterior.summary(), indent=2, allow_nan=False) + "\n"
    except ValueError:
        raise FwdfitError("posterior.json: a value is NaN or infinite; nothing written") from None
    chains, draws, _ = posterior.draws.shape
    columns = {"chain": np.repeat(np.arange(chains), draws), "draw": np.tile(np.arange(draws), chains)}
    columns.update({name: posterior.draws[:, :, j].ravel() for j, name in enumerate(posterior.names)})
    with staged_folder(Path(out_dir), add=True) as staging:
        write_columns(staging / "chains.csv", columns)
        (staging / "posterior.json").write_text(summary)
        plot_corner(staging / "corner.png", posterior)
