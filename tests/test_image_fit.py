"""``fwdfit fit-image``: a whole normalised image fitted row by row, and its bad input.

The image is made with the exact Monte Carlo reference (``fwdfit.trace_reference_rows``),
independent of the model: one trace of the Al block (1000 µm x 2 mm, tilt 0.24°, ICON
geometry, 2.7 Å line, 8.5 mm) on bins of an eighth of a pixel, from which each row's
pixels are summed with the stack's centre moved by a whole number of bins (0.3 µm), so
every row is the exact reference at its own centre: a 20 µm peak-to-peak sinusoid plus a
parabola across 40 rows of 600 pixels. 1 % Gaussian noise is added (no error image: the
fit estimates the noise). One row has no sample in it (open beam), one is mostly
masked, and 30 scattered pixels are NaN.

Runtime on two cores: the trace ~9 s, the fit ~25 s (two compilations, cached for the
second CLI call). Bad input fails before anything is compiled.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

import fwdfit
from fwdfit.inference import levenberg_marquardt
from fwdfit.cli import main
from helpers import gaussian_line_table, image_scene, read_table, rms

AL = fwdfit.constants_from_formula("Al", 2.70)
PIXEL_UM, SUB = 2.4, 8  # detector pixel, reference bins per pixel
N_ROWS, N_COLS, X0_UM = 40, 600, -720.0
NOISE = 0.01
OPEN_ROW, MASKED_ROW = 17, 25

IMAGE_KEYS = 'image = "T.tif"\nx0_um = -720.0'


def _scene(folder: Path, data: str | None = None, *, image_err: bool = False, per_row=()) -> Path:
    """``helpers.image_scene`` (start 1100 µm, T.tif from -720 µm; T_err.tif too if
    ``image_err``) saved in ``folder``; ``data``: TOML lines that replace the image keys."""
    scene = image_scene(folder / "T.tif", thickness_um=1100.0, x0_um=X0_UM, n_cols=N_COLS,
                        image_err_file=folder / "T_err.tif" if image_err else None, per_row=per_row)
    path = fwdfit.save_scene(scene, folder / "scene.toml")
    if data is not None:
        path.write_text(path.read_text().replace(IMAGE_KEYS, data))
    return path


TRACE = dict(depth_mm=2.0, tilt_deg=0.24, aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5,
             distance_mm=8.5)


def _al():
    return [fwdfit.ReferenceLayer(1000.0, AL.sld_e6_per_A2, AL.mu_per_m, AL.mu_per_m_per_A)]


@pytest.fixture(scope="module")
def truth():
    """Rows of the exact reference (T, T_att (N_ROWS, N_COLS)) at centres (N_ROWS,) µm."""
    lam, weight = gaussian_line_table(2.7, 0.15)
    rows = np.arange(N_ROWS)
    wanted = 3.0 + 10.0 * np.sin(2 * np.pi * rows / N_ROWS) + 8.0 * (rows / N_ROWS - 0.5) ** 2
    reference = fwdfit.trace_reference_rows(
        _al(), centres_um=wanted, x0_um=X0_UM, pixel_um=PIXEL_UM, n_pixels=N_COLS, sub=SUB,
        spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=8_000_000, seed=3, **TRACE)
    assert np.all(np.abs(reference.centres_um - wanted) <= 0.5 * PIXEL_UM / SUB + 1e-9)
    return reference.centres_um, reference.T, reference.T_att


def test_reference_rows_are_the_reference_at_each_centre():
    """A row of trace_reference_rows against trace_reference with the stack at that row's centre."""
    lam, weight = gaussian_line_table(2.7, 0.15)
    common = dict(spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=1_000_000, **TRACE)
    rows = fwdfit.trace_reference_rows(_al(), centres_um=np.array([-9.0, 0.0, 14.1]), x0_um=-600.0,
                                       pixel_um=PIXEL_UM, n_pixels=500, sub=SUB, **common)
    centre = rows.centres_um[2]
    direct = fwdfit.trace_reference(_al(), centre_um=centre, pixel_edges_um=-600.0 + PIXEL_UM * np.arange(501),
                                    seed=11, **common)
    assert abs(centre - 14.1) <= 0.15
    assert rms(rows.T_att[2] - direct.T_att) < 2e-4
    assert rms(rows.T[2] - direct.T) < 3 * rms(np.hypot(rows.T_err[2], direct.T_err))
    # the stack moves with the centre: the rows' left edges (half-way down) lie as far apart
    x = -600.0 + PIXEL_UM * (np.arange(500) + 0.5)

    def left_edge(T_att):
        left = x < 0
        half = 0.5 * (T_att[left].max() + T_att[left].min())
        return np.interp(half, T_att[left][::-1], x[left][::-1])

    moved = left_edge(rows.T_att[2]) - left_edge(rows.T_att[0])
    assert abs(moved - (rows.centres_um[2] - rows.centres_um[0])) < 0.3


@pytest.fixture(scope="module")
def fitted(truth, tmp_path_factory):
    """``fwdfit fit-image`` on the noisy image: (output folder, exit status)."""
    centres, T, _ = truth
    folder = tmp_path_factory.mktemp("image")
    rng = np.random.default_rng(7)
    image = T + NOISE * rng.standard_normal(T.shape)
    image[OPEN_ROW] = 1.0 + NOISE * rng.standard_normal(N_COLS)  # no sample in this row
    image[MASKED_ROW, : int(0.6 * N_COLS)] = np.nan
    image[rng.integers(0, N_ROWS, 30), rng.integers(0, N_COLS, 30)] = np.nan
    tifffile.imwrite(folder / "T.tif", image.astype(np.float32))
    scene = _scene(folder)
    status = main(["fit-image", str(scene), "--out", str(folder / "out"), "--quiet"])
    return folder / "out", status, image


def test_fit_image_follows_a_curved_edge(truth, fitted):
    centres, _, T_att_true = truth
    out, status, image = fitted
    assert status == 0
    rows = read_table(out / "rows.csv")
    flags = rows["flag"].astype(int)
    good = flags == 0
    # the open-beam row has no edge, the masked row is left out; every other row is fitted
    assert flags[OPEN_ROW] & 1 and flags[MASKED_ROW] & 2
    assert good.sum() >= N_ROWS - 3
    miss = np.abs(rows["centre_um"][good] - centres[good])
    assert np.mean(miss < 1.0) >= 0.95, miss
    T_att = tifffile.imread(out / "T_att.tif")
    assert T_att.dtype == np.float32 and T_att.shape == (N_ROWS, N_COLS)
    assert rms(T_att[good] - T_att_true[good]) < 0.003
    result = json.loads((out / "result.json").read_text())
    thickness = result["parameters"]["layers.Al.thickness_um"]["value"]
    sld = result["parameters"]["layers.Al.sld_e6_per_A2"]["value"]
    assert abs(thickness - 1000.0) < 2.0
    assert abs(sld / AL.sld_e6_per_A2 - 1) < 0.05
    # NaN pixels are masked and counted; they stay NaN in T_corrected
    n_nan = int(np.isnan(image).sum())
    assert result["masked_pixels"] == n_nan
    T_corrected = tifffile.imread(out / "T_corrected.tif")
    assert np.array_equal(np.isnan(T_corrected), np.isnan(image))
    # T_corrected = T - (T_model - T_att): refraction removed, attenuation kept
    assert rms(np.nan_to_num(T_corrected[good] - T_att_true[good])) < 1.5 * NOISE
    assert (out / "overview.png").stat().st_size > 0


def test_fit_image_rows_carry_honest_errors(truth, fitted):
    """The centres' errors describe their scatter about the truth (pull sd ~ 1)."""
    centres, _, _ = truth
    rows = read_table(fitted[0] / "rows.csv")
    good = rows["flag"] == 0
    pull = (rows["centre_um"][good] - centres[good]) / rows["centre_um_err"][good]
    assert 0.6 < np.std(pull) < 1.6, pull


def test_rows_the_model_cannot_fit_are_flagged_and_left_out(truth, tmp_path, capsys):
    """A feature the model lacks (a 0.08 bump over 40 pixels inside the sample) in every
    fifth row: those rows are flagged poor (4), more than 5 % of the rows fit poorly, so
    the exit status is 3 with every result written; the shared fit, without them, still
    finds the thickness. (Same geometry as the main case: the compiled programs are cached.)"""
    centres, T, _ = truth
    image = T + NOISE * np.random.default_rng(8).standard_normal(T.shape)
    bad = np.arange(0, N_ROWS, 5)
    image[bad, 280:320] += 0.08
    scene = _image_folder(tmp_path, image)
    out = tmp_path / "out"
    assert main(["fit-image", str(scene), "--out", str(out), "--quiet"]) == 3
    assert "poor fit" in capsys.readouterr().err
    rows = read_table(out / "rows.csv")
    flags = rows["flag"].astype(int)
    assert np.all(flags[bad] & 4) and np.all(flags[np.setdiff1d(np.arange(N_ROWS), bad)] == 0)
    result = json.loads((out / "result.json").read_text())
    assert result["rows"]["flags"]["poor_fit"] == len(bad) and not result["accepted"]
    assert abs(result["parameters"]["layers.Al.thickness_um"]["value"] - 1000.0) < 2.0


def test_edge_centres_find_rows_and_flag_the_rest(tmp_path):
    """Step rows 1000 µm wide centred at 0.1 r µm: centres from the edges within a pixel;
    an open-beam row has no edge (flag 1), a mostly masked row is flagged 2, and a row
    whose edges are 300 µm closer than the others' gets no centre (fitted from its
    neighbours) and no flag."""
    from fwdfit.images import FLAG_MASKED, FLAG_NO_EDGE, edge_centres

    x = X0_UM + PIXEL_UM * (np.arange(N_COLS) + 0.5)
    rng = np.random.default_rng(2)
    true = 0.1 * np.arange(12)
    image = np.where(np.abs(x[None, :] - true[:, None]) < 500, 0.95, 1.0) + 0.003 * rng.standard_normal((12, N_COLS))
    image[3] = 1.0 + 0.003 * rng.standard_normal(N_COLS)
    image[5, :400] = np.nan
    image[8] = np.where(np.abs(x - true[8]) < 350, 0.95, 1.0)
    scene = fwdfit.load_scene(_image_folder(tmp_path, image))
    centres, flags = edge_centres(scene, scene.profiles[0])
    assert flags[3] == FLAG_NO_EDGE and flags[5] == FLAG_MASKED and flags[8] == 0
    assert np.isnan(centres[[3, 5, 8]]).all()
    good = np.setdiff1d(np.arange(12), [3, 5, 8])
    assert np.all(flags[good] == 0) and np.all(np.abs(centres[good] - true[good]) < PIXEL_UM)


def test_levenberg_marquardt_solves_independent_problems():
    """Forty exponential decays, each with data of its own (rates 0.5 to 2.5, two nearly
    equal), solved at once: each reaches its own rate, none is merged into a neighbour or
    abandoned for a far worse chi-square (its data are not the others')."""
    t = np.linspace(0.0, 4.0, 50)
    rates = np.concatenate([np.linspace(0.5, 2.5, 39), [1.0001]])
    data = 3.0 * np.exp(-rates[:, None] * t) + 0.5 * np.arange(40)[:, None]  # offsets: chi-squares differ

    def residuals(rows, problems):
        return 3.0 * np.exp(-rows[:, :1] * t) + 0.5 * problems[:, None] - data[problems]

    solution = levenberg_marquardt(residuals, np.full((40, 1), 1.0), np.ones(1), tolerance=1e-8,
                                   max_steps=100, independent=True)
    assert solution.converged.all()
    np.testing.assert_allclose(solution.u[:, 0], rates, rtol=1e-7)


def _image_folder(tmp_path: Path, image: np.ndarray, err: np.ndarray | None = None, data=None) -> Path:
    tifffile.imwrite(tmp_path / "T.tif", image.astype(np.float32))
    if err is not None:
        tifffile.imwrite(tmp_path / "T_err.tif", err.astype(np.float32))
    return _scene(tmp_path, data, image_err=err is not None)


def _run_fails(capsys, scene: Path, out: Path, *words: str) -> None:
    assert main(["fit-image", str(scene), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("fwdfit: error:"), err
    for word in words:
        assert word in err, err
    assert not out.exists()


def test_image_and_error_image_of_different_shapes_are_refused(tmp_path, capsys):
    scene = _image_folder(tmp_path, np.ones((10, 100)), np.full((10, 99), 0.01))
    _run_fails(capsys, scene, tmp_path / "out", "image_err", "10 x 99", "10 x 100")


def test_image_without_an_edge_is_refused(tmp_path, capsys):
    rng = np.random.default_rng(0)
    scene = _image_folder(tmp_path, 1.0 + 0.01 * rng.standard_normal((8, 200)))
    _run_fails(capsys, scene, tmp_path / "out", "no sample edge")


@pytest.mark.parametrize("data, words", [
    ('image = "T.tif"\nfile = "T.csv"', ["image", "file", "not both"]),
    ('file = "T.csv"\nx0_um = 0.0', ["x0_um"]),
    ('image = "T.tif"\nimage_error = "T_err.tif"', ["image_error", "unknown key"]),
    ('image = "missing.tif"', ["missing.tif", "not found"]),
    ('image = "scene.toml"', ["scene.toml", "TIFF"]),
])
def test_bad_image_keys_are_refused(tmp_path, capsys, data, words):
    (tmp_path / "T.csv").write_text("x_um,T\n0,1\n2.4,1\n")
    scene = _image_folder(tmp_path, np.ones((4, 50)), data=data)
    _run_fails(capsys, scene, tmp_path / "out", *words)


def test_an_image_of_raw_counts_is_refused(tmp_path, capsys):
    tifffile.imwrite(tmp_path / "T.tif", np.full((4, 50), 1000, np.uint16))
    _run_fails(capsys, _scene(tmp_path), tmp_path / "out", "uint16", "float")


def test_fit_refuses_an_image_profile(tmp_path, capsys):
    scene = _image_folder(tmp_path, np.ones((4, 50)))
    assert main(["fit", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert "fit-image" in capsys.readouterr().err


@pytest.mark.parametrize("fit_lines, words", [
    ('per_row = ["profiles.other.norm"]', ["fit.per_row", "profiles.other.norm"]),
    ('bounds."profiles.radiograph.norm" = [0.5, 1.5]\n'
     'vary = ["sample.centre_um", "profiles.radiograph.norm"]', ["fit.vary", "per_row"]),
    ('per_row = "norm"', ["fit.per_row", "list"]),
    ('per_row = ["sample.tilt"]', ["sample.tilt", "unknown parameter"]),
])
def test_bad_per_row_parameters_are_refused(tmp_path, capsys, fit_lines, words):
    x = -720.0 + PIXEL_UM * (np.arange(600) + 0.5)
    image = np.where(np.abs(x) < 500, 0.9, 1.0) + 0.01 * np.random.default_rng(0).standard_normal((6, 600))
    scene = _image_folder(tmp_path, image)
    text = scene.read_text()
    if "vary" in fit_lines:
        text = text[: text.index("vary")]
    scene.write_text(text.replace("[fit]", "[fit]\n" + fit_lines))
    _run_fails(capsys, scene, tmp_path / "out", *words)


def test_fit_refuses_per_row(tmp_path, capsys):
    (tmp_path / "T.csv").write_text("x_um,T\n0,1\n2.4,1\n")
    scene = _scene(tmp_path, 'file = "T.csv"', per_row=["sample.tilt_deg"])
    assert main(["fit", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert "fit.per_row" in capsys.readouterr().err


@pytest.mark.slow
def test_fit_image_fits_a_norm_per_row(tmp_path):
    """The open beam's level changes by 2 % across the rows (norm per row, fit.per_row):
    each row's norm within 3 sigma and 0.002 of the truth, its centre within 1 µm. The
    image is the model itself at accuracy 1e-4 (the fit runs at 1e-3), 1 % noise."""
    from fwdfit.inference import assembler, free_parameters
    from fwdfit.model import build_model
    from fwdfit.inference import Predictor

    n_rows = 24
    tifffile.imwrite(tmp_path / "T.tif", np.ones((n_rows, N_COLS), np.float32))
    scene_path = _scene(tmp_path, per_row=["profiles.radiograph.norm"])
    scene = fwdfit.load_scene(scene_path)
    row = dataclasses.replace(scene.profiles[0], image=None)
    truth_scene = dataclasses.replace(scene, profiles=(row,), fit=fwdfit.FitSpec(),
                                      sample=dataclasses.replace(scene.sample, tilt_deg=0.24,
                                                                 layers=(dataclasses.replace(
                                                                     scene.sample.layers[0], thickness_um=1000.0),)))
    vary = ["sample.centre_um", "profiles.radiograph.norm"]
    free = free_parameters(truth_scene, vary=vary)
    predict = Predictor(build_model(truth_scene, 1e-4, free=vary), assembler(truth_scene, free), 2)
    rows = np.arange(n_rows)
    truth = np.stack([3.0 + 10.0 * np.sin(2 * np.pi * rows / n_rows),
                      1.0 + 0.02 * np.cos(2 * np.pi * rows / n_rows)], axis=1)
    T, _ = predict(truth)
    no_rows = predict(np.zeros((0, 2)))  # a search with no candidate left asks for none
    assert [a.shape for a in no_rows] == [(0, T.shape[1])] * 2
    image = T + NOISE * np.random.default_rng(5).standard_normal(T.shape)
    tifffile.imwrite(tmp_path / "T.tif", image.astype(np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fwdfit.fit_image(scene_path)
    assert result.per_row == ("sample.centre_um", "profiles.radiograph.norm")
    assert result.good.all()
    norm, norm_err = result.row_values[:, 1], result.row_errors[:, 1]
    assert np.all(np.abs(norm - truth[:, 1]) < np.minimum(3 * norm_err, 0.002) + 1e-4), norm - truth[:, 1]
    assert np.all(np.abs(result.centre_um - truth[:, 0]) < 1.0)
