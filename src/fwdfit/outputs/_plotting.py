"""Plot helpers shared by every figure fwdfit writes (matplotlib, drawn by the caller)."""

from __future__ import annotations

import numpy as np

MIN_BAND_PX = 2.0  # a ±1σ band thinner than this hides under its 1 pt line (1.4 px at 100 dpi)


def draw_error_band(axes, line, err: np.ndarray, name: str) -> None:
    """Label ``line`` (on ``axes``, its limits set) ``name`` and shade its ±``err`` band, or,
    where the band would be thinner than ``MIN_BAND_PX``, give its size in the label instead."""
    x, y = line.get_data()
    err_max = float(np.nanmax(err))
    low, high = axes.get_ylim()
    band_px = 2.0 * err_max / abs(high - low) * axes.get_window_extent().height
    if not band_px >= MIN_BAND_PX:
        line.set_label(f"{name}\n±1σ ≤ {err_max:.1g}, thinner than the line")
        return
    line.set_label(name)
    axes.fill_between(x, y - err, y + err, color=line.get_color(), alpha=0.3, lw=0, label=f"±1σ of {name}")
