"""Plots a scientist would show: titles that say what was measured and whether the fit is
accepted, legends outside the data, uncertainty bands only where they can be seen, axis
labels that name what is drawn, and ``profile``'s PNG with the profile beside the region.

The plotting functions return their matplotlib ``Figure``; the tests inspect it (no PNG
parsing): ``fwdfit.outputs.ProfilePlot`` and ``fwdfit.images.plot_radiograph_png``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import tifffile
from matplotlib.text import Text

import fwdfit
from fwdfit.outputs import ProfilePlot
from fwdfit.images import plot_radiograph_png
from fwdfit.cli import main
from fwdfit.images import profile_from_stacks
from helpers import small_scene

TRUTH = {"sample.centre_um": 0.0, "layers.Al.thickness_um": 1000.0, "layers.Al.sld_e6_per_A2": 2.08}
NOISE = 0.01


@pytest.fixture(scope="module")
def result():
    """The small scene (1.1 mm, 4.6 Å line) fitted to its own model plus 1 % noise, centre free."""
    scene = small_scene(TRUTH, vary=("sample.centre_um",))
    simulated = fwdfit.simulate(scene)[0]
    T = simulated.T + np.random.default_rng(3).normal(0.0, NOISE, simulated.T.shape)
    profile = dataclasses.replace(scene.profiles[0], T=T, T_err=np.full_like(T, NOISE))
    return fwdfit.fit(dataclasses.replace(scene, profiles=(profile,)))


def _title(axes) -> Text:
    """The axes' title (placed on the left) as its ``Text``."""
    text = axes.get_title(loc="left")
    (title,) = [a for a in axes.get_children() if isinstance(a, Text) and a.get_text() == text]
    return title


def _drawn(figure):
    figure.draw_without_rendering()
    return figure


def test_title_says_distance_wavelength_chi2_and_verdict(result):
    assert result.accepted
    title = _title(ProfilePlot(result).draw(0).axes[0])
    for words in ("line", "1.1 mm", "4.6 Å", f"χ²/dof {result.chi2_reduced:.3f}", f"dof {result.dof}",
                  "accepted"):
        assert words in title.get_text(), (words, title.get_text())
    rejected = _title(ProfilePlot(dataclasses.replace(result, converged=False)).draw(0).axes[0])
    assert "rejected" in rejected.get_text() and "accepted" not in rejected.get_text()
    assert rejected.get_color() != title.get_color()  # a rejected fit does not look like an accepted one


def test_legends_lie_outside_the_data(result):
    figure = _drawn(ProfilePlot(result).draw(0))
    legends = [axes.get_legend() for axes in figure.axes if axes.get_legend() is not None]
    assert len(legends) == 2
    for axes in figure.axes:
        for legend in legends:
            assert not legend.get_window_extent().overlaps(axes.get_window_extent())


def test_axis_labels_name_what_is_drawn(result):
    top, middle, bottom = ProfilePlot(result).draw(0).axes
    assert "T_model" in top.get_ylabel()
    assert "T_model" in middle.get_ylabel() and "σ" in middle.get_ylabel()
    assert "T_corrected" in bottom.get_ylabel() and "T_att" in bottom.get_ylabel()
    assert "µm" in bottom.get_xlabel()


def _legend_texts(axes) -> list[str]:
    return [text.get_text() for text in axes.get_legend().get_texts()]


def test_band_thinner_than_a_pixel_is_not_claimed(result):
    """T_att's error here is ~1e-4 of a 0.2-high axis (~0.1 px): no band, its size in the legend."""
    bottom = ProfilePlot(result).draw(0).axes[2]
    assert np.max(result.profiles[0].T_att_err) < 1e-3
    assert not bottom.collections
    (label,) = [t for t in _legend_texts(bottom) if t.startswith("T_att")]
    assert "±1σ ≤" in label and "thinner than the line" in label


def test_visible_band_is_drawn_and_labelled(result):
    profile = dataclasses.replace(result.profiles[0], T_att_err=np.full_like(result.profiles[0].T, 0.02))
    bottom = ProfilePlot(dataclasses.replace(result, profiles=(profile,))).draw(0).axes[2]
    (band,) = bottom.collections
    assert band.get_label() == "±1σ of T_att (attenuation-only fit)"
    assert band.get_label() in _legend_texts(bottom)
    assert not any("≤" in t for t in _legend_texts(bottom))


def test_a_plot_drawn_again_keeps_one_band(result):
    """ProfilePlot is reused for every profile: the previous profile's band goes."""
    profile = dataclasses.replace(result.profiles[0], T_att_err=np.full_like(result.profiles[0].T, 0.02))
    scene = dataclasses.replace(result.scene, profiles=result.scene.profiles * 2)
    plot = ProfilePlot(dataclasses.replace(result, profiles=(profile, result.profiles[0]), scene=scene))
    plot.draw(0)
    assert len(plot.draw(0).axes[2].collections) == 1
    assert not plot.draw(1).axes[2].collections


# ---------------------------------------------------------------------------- fwdfit profile

N_ROWS, N_COLS, ROI = 12, 40, (2, 10, 5, 35)


@pytest.fixture
def stacks(tmp_path):
    """Sample, open-beam and dark TIFFs (3 frames each): a dip of 0.2 across columns 15-25, 2 % noise."""
    rng = np.random.default_rng(5)
    T = np.where((np.arange(N_COLS) >= 15) & (np.arange(N_COLS) < 25), 0.8, 1.0)
    paths = {}
    for name, level in (("sample", 1000.0 * T), ("open", np.full(N_COLS, 1000.0)), ("dark", np.zeros(N_COLS))):
        frames = level + 100.0 + (20.0 if name != "dark" else 1.0) * rng.standard_normal((3, N_ROWS, N_COLS))
        paths[name] = tmp_path / f"{name}.tif"
        tifffile.imwrite(paths[name], frames.astype(np.float32), photometric="minisblack")
    return paths


def test_profile_png_draws_the_profile_with_its_errors(stacks, tmp_path):
    profile = profile_from_stacks(stacks["sample"], stacks["open"], stacks["dark"], ROI, 2.4)
    figure = plot_radiograph_png(tmp_path / "p.png", profile)
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (plot,) = [axes for axes in figure.axes if axes.get_lines()]
    (line,) = plot.get_lines()
    np.testing.assert_array_equal(line.get_ydata(), profile.T)
    (band,) = plot.collections
    assert "±1σ" in band.get_label()
    assert "µm" in plot.get_xlabel() and "T" in plot.get_ylabel()
    assert any(axes.images for axes in figure.axes)  # the radiograph with its region, beside it


def test_profile_prints_what_it_wrote(stacks, tmp_path, capsys):
    out = tmp_path / "out" / "x.csv"
    assert main(["profile", "--sample", str(stacks["sample"]), "--open", str(stacks["open"]),
                 "--dark", str(stacks["dark"]), "--roi", ",".join(map(str, ROI)), "--pixel-um", "2.4",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.out == f"wrote {out} ({ROI[3] - ROI[2]} pixels), {out.with_suffix('.png')}\n"
    assert captured.err == ""
