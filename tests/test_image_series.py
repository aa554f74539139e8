"""``fwdfit fit-images``: a series of images fitted with one scene as template, serially or on
a Dask LocalCluster, resumed after an interruption, and its bad input.

The series is made with the exact Monte Carlo reference (``fwdfit.trace_reference_rows``),
independent of the model: one trace of a 400 µm Al block (2 mm deep, tilt 0.24°, ICON
geometry, 2.7 Å line, 8.5 mm), each row the reference at its own centre: image i (2 images
of 12 rows x 300 pixels of 2.4 µm) is shifted by 4.8 i µm, its rows by a 3 µm sinusoid on
top, and 0.3 % Gaussian noise is added (no error image: the fit estimates the noise).
The scene (the template) starts the block at 450 µm, centre 0, tilt 0.15°.

Runtime on two cores: the trace ~2 s, a fit ~5 s per image after one compilation (~10 s,
cached in this process for the images after it): the resume test ~25 s; the Dask
comparison (slow: 2 images serially, then on the cluster) ~1 min.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

import fwdfit
from fwdfit.images import OUTPUT_FILES
from fwdfit.cli import main
from helpers import gaussian_line_table, image_scene

AL = fwdfit.constants_from_formula("Al", 2.70)
N_IMAGES, N_ROWS, N_COLS, PIXEL_UM, X0_UM = 2, 12, 300, 2.4, -360.0
SHIFT_UM = 4.8  # image i is shifted by SHIFT_UM * i (two pixels: every image has the same sub-pixel pattern)
NOISE = 0.003

def series_scene(folder: Path):
    return image_scene(folder / "proj_000.tif", thickness_um=450.0, x0_um=X0_UM, n_cols=N_COLS)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """A folder with scene.toml and proj_000.tif and proj_001.tif; the true row centres
    (N_IMAGES, N_ROWS) µm."""
    folder = tmp_path_factory.mktemp("series")
    lam, weight = gaussian_line_table(2.7, 0.15)
    rows = np.arange(N_ROWS)
    wanted = (SHIFT_UM * np.arange(N_IMAGES)[:, None] + 3.0 * np.sin(2 * np.pi * rows / N_ROWS)[None]).ravel()
    reference = fwdfit.trace_reference_rows(
        [fwdfit.ReferenceLayer(400.0, AL.sld_e6_per_A2, AL.mu_per_m, AL.mu_per_m_per_A)],
        centres_um=wanted, x0_um=X0_UM, pixel_um=PIXEL_UM, n_pixels=N_COLS, sub=8, spectrum_lambda_A=lam,
        spectrum_weight=weight, n_rays=2_000_000, seed=3, depth_mm=2.0, tilt_deg=0.24, aperture="circular",
        aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=8.5)
    noise = NOISE * np.random.default_rng(1).standard_normal((N_IMAGES, N_ROWS, N_COLS))
    images = reference.T.reshape(N_IMAGES, N_ROWS, N_COLS) + noise
    for i, image in enumerate(images):
        tifffile.imwrite(folder / f"proj_{i:03d}.tif", image.astype(np.float32))
    fwdfit.save_scene(series_scene(folder), folder / "scene.toml")
    return folder, reference.centres_um.reshape(N_IMAGES, N_ROWS)


def _rows(folder: Path) -> dict[str, np.ndarray]:
    table = np.genfromtxt(folder / "rows.csv", delimiter=",", names=True)
    return {name: table[name] for name in table.dtype.names}


def _summary(out: Path) -> list[dict]:
    import csv

    with open(out / "summary.csv", encoding="utf-8") as stream:
        return list(csv.DictReader(stream))


def _mtimes(folder: Path) -> dict[str, int]:
    return {name: (folder / name).stat().st_mtime_ns for name in OUTPUT_FILES}


def test_series_resumes_without_refitting_finished_images(series, tmp_path, capsys):
    """One image fitted serially; then a run of three (the second image "killed" half-way: a
    partial output folder and a staged folder left behind; the third with no edge) fits only
    the second, leaves the first's files untouched, and exits 3 for the one that failed."""
    folder, truth = series
    out = tmp_path / "out"
    images = [str(folder / f"proj_{i:03d}.tif") for i in range(N_IMAGES)]
    assert main(["fit-images", str(folder / "scene.toml"), images[0], "--out", str(out), "--workers", "1"]) == 0
    rows = _rows(out / "proj_000")
    assert np.all(rows["flag"] == 0)
    assert np.max(np.abs(rows["centre_um"] - truth[0])) < 0.6  # the reference's row centres
    first = _mtimes(out / "proj_000")
    # a run killed while proj_001 was moved in (one file there) and one killed while staging it
    partial = out / "proj_001"
    partial.mkdir()
    (partial / "rows.csv").write_text("partial\n")
    (partial / ".fwdfit-output").write_text("")  # written by fwdfit, so a new run may replace it
    stale = out / ".proj_001.k1ll3d.tmp"
    stale.mkdir()
    (stale / "result.json").write_text("{}")
    flat = tmp_path / "flat.tif"  # open beam: no edge in any row
    tifffile.imwrite(flat, (1.0 + NOISE * np.random.default_rng(2).standard_normal((N_ROWS, N_COLS)))
                     .astype(np.float32))
    capsys.readouterr()
    status = main(["fit-images", str(folder / "scene.toml"), *images, str(flat), "--out", str(out),
                   "--workers", "1"])
    err = capsys.readouterr().err
    assert status == 3
    assert "3 images: 1 done before (skipped), 2 to fit" in err
    assert "images 3/3" in err and "fwdfit: 1 image(s) not fitted well: flat.tif (failed)" in err
    assert _mtimes(out / "proj_000") == first
    assert not stale.exists() and not (out / "flat").exists()
    assert all((partial / name).is_file() for name in OUTPUT_FILES)
    assert np.max(np.abs(_rows(partial)["centre_um"] - truth[1])) < 0.6
    summary = _summary(out)
    assert [line["image"] for line in summary] == ["proj_000.tif", "proj_001.tif", "flat.tif"]
    assert [line["status"] for line in summary] == ["ok", "ok", "failed"]
    assert [line["resumed"] for line in summary] == ["1", "0", "0"]
    assert "no sample edge found" in summary[2]["message"]
    for line in summary[:2]:
        assert abs(float(line["layers.Al.thickness_um"]) - 400.0) < 2.0
        assert line["rows_fitted"] == str(N_ROWS) and line["rows_flagged"] == "0"
    result = json.loads((out / "proj_000" / "result.json").read_text())
    assert float(summary[0]["chi2_reduced"]) == pytest.approx(result["chi2_reduced"], rel=1e-8)


@pytest.mark.slow
def test_dask_run_matches_the_serial_run(series, tmp_path):
    """Two images on a LocalCluster of two worker processes (one each): every output number
    equals the serial run's (the same compiled program on the same data)."""
    pytest.importorskip("distributed")
    folder, truth = series
    scene = str(folder / "scene.toml")
    serial, dask = tmp_path / "serial", tmp_path / "dask"
    pair = tmp_path / "pair"  # the serial run reads a folder, the cluster a glob
    pair.mkdir()
    for i in range(N_IMAGES):
        shutil.copy(folder / f"proj_{i:03d}.tif", pair)
    assert main(["fit-images", scene, str(pair), "--out", str(serial), "--workers", "1", "--quiet"]) == 0
    assert main(["fit-images", scene, str(folder / "proj_*.tif"), "--out", str(dask), "--workers", "2",
                 "--quiet"]) == 0
    for i in range(N_IMAGES):
        name = f"proj_{i:03d}"
        a, b = _rows(serial / name), _rows(dask / name)
        assert np.max(np.abs(a["centre_um"] - truth[i])) < 0.6
        for column in a:
            np.testing.assert_allclose(b[column], a[column], rtol=1e-9, atol=1e-12, equal_nan=True)
        for image in ("T_att.tif", "T_corrected.tif", "residual.tif"):
            np.testing.assert_allclose(tifffile.imread(dask / name / image), tifffile.imread(serial / name / image),
                                       rtol=1e-6, atol=0)
        shared_a = json.loads((serial / name / "result.json").read_text())["parameters"]
        shared_b = json.loads((dask / name / "result.json").read_text())["parameters"]
        for key, value in shared_a.items():
            assert shared_b[key]["value"] == pytest.approx(value["value"], rel=1e-9, abs=1e-12)
    lines = _summary(dask)
    assert [line["status"] for line in lines] == ["ok"] * N_IMAGES
    shifts = np.array([float(line["sample.centre_um"]) for line in lines])
    assert np.all(np.diff(shifts) > 0)  # the series drifts to the right


def _refused(capsys, argv, out: Path) -> str:
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("fwdfit: error: ") and "\n" not in err and "Traceback" not in err
    assert not out.exists()
    return err


def test_bad_input_is_one_line_and_writes_nothing(series, tmp_path, capsys):
    folder, _ = series
    scene, out = str(folder / "scene.toml"), tmp_path / "out"
    assert "no image matches" in _refused(capsys, ["fit-images", scene, str(tmp_path / "x_*.tif"),
                                                   "--out", str(out)], out)
    assert "file not found" in _refused(capsys, ["fit-images", scene, str(tmp_path / "missing.tif"),
                                                 "--out", str(out)], out)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no .tif or .tiff" in _refused(capsys, ["fit-images", scene, str(empty), "--out", str(out)], out)
    narrow = tmp_path / "narrow.tif"
    tifffile.imwrite(narrow, np.ones((N_ROWS, N_COLS - 1), np.float32))
    err = _refused(capsys, ["fit-images", scene, str(folder / "proj_000.tif"), str(narrow), "--out", str(out)], out)
    assert "12 x 299 pixels, the template image 12 x 300" in err
    counts = tmp_path / "counts.tif"
    tifffile.imwrite(counts, np.ones((N_ROWS, N_COLS), np.uint16))
    assert "pixel type uint16" in _refused(capsys, ["fit-images", scene, str(counts), "--out", str(out)], out)
    other = tmp_path / "other"
    other.mkdir()
    tifffile.imwrite(other / "proj_000.tif", np.ones((N_ROWS, N_COLS), np.float32))
    assert "same name as" in _refused(capsys, ["fit-images", scene, str(folder / "proj_000.tif"),
                                               str(other / "proj_000.tif"), "--out", str(out)], out)
    image = str(folder / "proj_000.tif")
    assert "--workers must be >= 1" in _refused(capsys, ["fit-images", scene, image, "--out", str(out),
                                                         "--workers", "0"], out)
    assert "--workers is for a local cluster" in _refused(
        capsys, ["fit-images", scene, image, "--out", str(out), "--workers", "2", "--scheduler", "tcp://x:1"], out)
    two = tmp_path / "two.toml"  # a scene that is not one image profile
    two.write_text(fwdfit.dump_scene(series_scene(tmp_path), tmp_path).replace(
        'image = "proj_000.tif"\nx0_um = -360.0', 'file = "missing.csv"'))
    assert _refused(capsys, ["fit-images", str(two), image, "--out", str(out)], out)
    assert os.listdir(tmp_path) and not out.exists()


def test_a_cluster_without_dask_installed_is_a_one_line_error(monkeypatch):
    from fwdfit import FwdfitError
    from fwdfit.images import local_client

    monkeypatch.setitem(__import__("sys").modules, "distributed", None)
    with pytest.raises(FwdfitError, match=r"pip install 'fwdfit\[cluster\]'"):
        local_client(None, 2)
