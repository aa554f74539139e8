"""``fwdfit fit-image`` on images of real samples (issue 42): weak absorbers whose attenuation
step is below the pixel noise, one edge in view, parameters the view cannot determine.

Images from the exact Monte Carlo reference (``helpers.traced_image``: the ICON 2.7 Å line at
8.5 mm, tilt 0.24°, the stack's centre moving from row to row). The weak absorber is the
paper's Al block with mu = 1.4 /m (attenuation step 0.28 %, refraction peaks of 5-6 %), the
strong one mu = 9.06 /m (1.8 %); the scenes start 80 µm too thick, at mu = 3 /m.

Runtime on two cores: ~45 s (five traces of 2-12 million rays, two fits, the rest finds
edges or refuses before any fit).
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

import fwdfit
from fwdfit.cli import main
from fwdfit.images import FLAG_NO_EDGE, edge_centres
from helpers import image_scene, read_table, rms, traced_image

SLD_AL = 2.0785
VARY = ("sample.tilt_deg", "sample.centre_um", "layers.Al.thickness_um", "layers.Al.sld_e6_per_A2",
        "layers.Al.mu_per_m")
ONE_EDGE_VARY = ("sample.tilt_deg", "sample.centre_um", "layers.Al.sld_e6_per_A2", "layers.Al.mu_per_m")


def _path(n_rows: int, phase: float = 0.0) -> np.ndarray:
    """A curved edge: the centre (µm) in each row, 12 µm peak to peak."""
    rows = np.arange(n_rows)
    return 4.0 + 6.0 * np.sin(2 * np.pi * rows / n_rows + phase)


@functools.cache
def _block(mu: float, psf: float, n_rows: int = 24, n_cols: int = 500, x0: float = -600.0, n_rays: int = 2_000_000,
           phase: float = 0.0):
    """(centres, T, T_att) of a 1000 µm Al block with attenuation mu /m, detector blur psf µm."""
    return traced_image([fwdfit.ReferenceLayer(1000.0, SLD_AL, mu, 0.0)], _path(n_rows, phase), x0_um=x0,
                        n_cols=n_cols, psf_fwhm_um=psf, n_rays=n_rays)


def _scene_file(folder, image, *, x0, psf=0.0, thickness=1080.0, vary=VARY):
    tifffile.imwrite(folder / "T.tif", image.astype(np.float32))
    scene = image_scene(folder / "T.tif", thickness_um=thickness, x0_um=x0, n_cols=image.shape[1],
                        psf_fwhm_um=psf, layers=(fwdfit.Layer("Al", thickness, SLD_AL, 3.0, 0.0),), vary=vary)
    return fwdfit.save_scene(scene, folder / "scene.toml")


@pytest.mark.parametrize("noise", [0.002, 0.02])
@pytest.mark.parametrize("psf", [0.0, 8.0])
@pytest.mark.parametrize("mu", [1.4, 9.06])
def test_faces_are_found_in_every_row(tmp_path, mu, psf, noise):
    """Weak and strong absorbers, sharp and blurred detectors, 0.2 and 2 % noise: every row's
    centre is found, all with one common offset (the start's tilt moves where the faces
    land) to within a pixel at 0.2 % noise. At 2 % noise a strong absorber's face matches
    its template in two places, on the step and on the refraction (the start's tilt moves
    them apart by ~14 µm), and rows take one or the other: within 16 µm there."""
    centres, T, _ = _block(mu, psf)
    image = T + noise * np.random.default_rng(11).standard_normal(T.shape)
    scene = fwdfit.load_scene(_scene_file(tmp_path, image, x0=-600.0, psf=psf))
    found, flags = edge_centres(scene, scene.profiles[0])
    assert np.all(flags == 0) and np.isfinite(found).all()
    miss = found - centres
    assert abs(np.median(miss)) < 15.0
    assert np.max(np.abs(miss - np.median(miss))) < (2.4 if noise < 0.01 else 16.0), miss


def test_a_row_without_the_sample_beside_rows_with_it_has_no_edge(tmp_path):
    centres, T, _ = _block(1.4, 0.0)
    image = T + 0.005 * np.random.default_rng(12).standard_normal(T.shape)
    image[10] = 1.0 + 0.005 * np.random.default_rng(13).standard_normal(T.shape[1])
    scene = fwdfit.load_scene(_scene_file(tmp_path, image, x0=-600.0))
    found, flags = edge_centres(scene, scene.profiles[0])
    assert flags[10] == FLAG_NO_EDGE and np.isnan(found[10])
    assert np.all(np.delete(flags, 10) == 0)


def _check_fit(out, centres, T_att, *, thickness=True):
    rows = read_table(out / "rows.csv")
    good = rows["flag"] == 0
    assert good.all()
    assert np.mean(np.abs(rows["centre_um"] - centres) < 1.0) >= 0.95
    assert rms(tifffile.imread(out / "T_att.tif") - T_att) <= 0.003
    parameters = json.loads((out / "result.json").read_text())["parameters"]
    if thickness:
        assert abs(parameters["layers.Al.thickness_um"]["value"] - 1000.0) < 2.0
    assert abs(parameters["layers.Al.sld_e6_per_A2"]["value"] / SLD_AL - 1) < 0.05


def test_fit_image_finds_a_weak_absorber(tmp_path):
    """The issue's case, smaller: attenuation step 0.28 % under 0.5 % noise, both edges in
    view, the centre curving across 40 rows of 500 pixels (the fit failed "no sample edge")."""
    centres, T, T_att = _block(1.4, 0.0, n_rows=40, n_rays=4_000_000, phase=1.0)
    image = T + 0.005 * np.random.default_rng(14).standard_normal(T.shape)
    scene = _scene_file(tmp_path, image, x0=-600.0)
    assert main(["fit-image", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    _check_fit(tmp_path / "out", centres, T_att)


@functools.cache
def _one_edge():
    """40 rows of 300 pixels from -800 µm: the block's left face in view, its right one not."""
    return _block(1.4, 0.0, n_rows=40, n_cols=300, x0=-800.0, n_rays=12_000_000)


def test_fit_image_with_one_edge_in_view(tmp_path):
    """A sample wider than the field of view, its thickness fixed (the scene's, 1000 µm)."""
    centres, T, T_att = _one_edge()
    image = T + 0.005 * np.random.default_rng(15).standard_normal(T.shape)
    scene = _scene_file(tmp_path, image, x0=-800.0, thickness=1000.0, vary=ONE_EDGE_VARY)
    assert main(["fit-image", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    _check_fit(tmp_path / "out", centres, T_att, thickness=False)


def test_a_thickness_one_edge_cannot_determine_is_refused(tmp_path, capsys):
    centres, T, _ = _one_edge()
    scene = _scene_file(tmp_path, T + 0.005 * np.random.default_rng(16).standard_normal(T.shape), x0=-800.0)
    out = tmp_path / "out"
    assert main(["fit-image", str(scene), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("fwdfit: error:"), err
    assert "layers.Al.thickness_um" in err and "cannot determine" in err and "faces in view: 0" in err, err
    assert not out.exists()


def test_a_multilayer_with_part_of_its_faces_in_view(tmp_path, capsys):
    """Oxide | Al | oxide with only the left oxide's two faces in view: the oxide's thickness
    and SLD are determined, the Al's thickness (no face in view on its right) is refused."""
    oxide = fwdfit.ReferenceLayer(80.0, 4.0, 20.0, 0.0)
    centres, T, _ = traced_image([oxide, fwdfit.ReferenceLayer(1000.0, SLD_AL, 1.4, 0.0), oxide], _path(16),
                                 x0_um=-800.0, n_cols=300, n_rays=2_000_000)
    tifffile.imwrite(tmp_path / "T.tif", (T + 0.005 * np.random.default_rng(17).standard_normal(T.shape))
                     .astype(np.float32))
    layers = (fwdfit.Layer("ox", 90.0, 3.8, 15.0, 0.0), fwdfit.Layer("Al", 1000.0, SLD_AL, 1.4, 0.0),
              fwdfit.Layer("ox", 90.0, 3.8, 15.0, 0.0).tied("ox_right"))
    vary = ["sample.centre_um", "layers.ox.thickness_um", "layers.ox.sld_e6_per_A2", "layers.Al.thickness_um"]
    scene = image_scene(tmp_path / "T.tif", thickness_um=0.0, x0_um=-800.0, n_cols=300, layers=layers, vary=vary)
    path = fwdfit.save_scene(scene, tmp_path / "scene.toml")
    assert main(["fit-image", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "'layers.Al.thickness_um'" in err and "layers.ox" not in err and "faces in view: 0, 1 of 0-3" in err, err


# ------------------------------------------------------------------ orientation, region, mask

LAYOUT_KEYS = 'profile_along = "columns"\nroi = [40, 540, 6, 46]\nmask = "mask.tif"'


def _columns_image(folder, noise_seed=18):
    """The weak block's 40 rows as the columns 6-45 of an 80 x 580 detector image turned on
    its side (the edge horizontal), the region's pixels 40-539 along them; outside it 0.5
    (a holder), a 4 x 100 patch and one pixel masked. Returns the scene, truth and mask."""
    centres, T, T_att = _block(1.4, 0.0, n_rows=40, n_rays=4_000_000, phase=1.0)
    image = T + 0.005 * np.random.default_rng(noise_seed).standard_normal(T.shape)
    full = np.full((52, 580), 0.5)
    full[6:46, 40:540] = image
    mask = np.zeros(full.shape, np.uint8)
    mask[20:24, 100:200] = 1
    mask[30, 300] = 255
    scene = _scene_file(folder, full.T, x0=-696.0)  # x0 of the file's first pixel: -600 - 40 pixels
    tifffile.imwrite(folder / "mask.tif", mask.T)
    scene.write_text(scene.read_text().replace("x0_um = -696.0", "x0_um = -696.0\n" + LAYOUT_KEYS))
    return scene, centres, T_att, mask.T


def test_horizontal_edges_in_a_region_with_a_mask(tmp_path):
    """profile_along = "columns", roi and mask: the outputs have the file's shape and
    orientation, NaN outside the region (and T_corrected on the mask); the fit is the
    weak block's."""
    scene, centres, T_att, mask = _columns_image(tmp_path)
    loaded = fwdfit.load_scene(scene)
    assert loaded.profiles[0].image.shape == (40, 500)
    assert loaded.profiles[0].x_um[0] == pytest.approx(-600.0 + 1.2)
    again = fwdfit.load_scene(fwdfit.save_scene(loaded, tmp_path / "again.toml"))  # the keys round-trip
    assert again.profiles[0].image_layout == loaded.profiles[0].image_layout
    np.testing.assert_allclose(again.profiles[0].x_um, loaded.profiles[0].x_um)
    out = tmp_path / "out"
    assert main(["fit-image", str(scene), "--out", str(out), "--quiet"]) == 0
    att = tifffile.imread(out / "T_att.tif")
    assert att.shape == (580, 52)
    inside = np.zeros(att.shape, bool)
    inside[40:540, 6:46] = True
    assert np.isnan(att[~inside]).all() and np.isfinite(att[inside]).all()
    corrected = tifffile.imread(out / "T_corrected.tif")
    assert corrected.shape == (580, 52) and np.array_equal(np.isnan(corrected), ~inside | (mask != 0))
    region = att[40:540, 6:46].T
    assert rms(np.nan_to_num(region - T_att)) <= 0.003
    rows = read_table(out / "rows.csv")
    assert np.array_equal(rows["column"], np.arange(6, 46))
    assert np.mean(np.abs(rows["centre_um"] - centres) < 1.0) >= 0.95
    result = json.loads((out / "result.json").read_text())
    assert result["masked_pixels"] == 401
    assert abs(result["parameters"]["layers.Al.thickness_um"]["value"] - 1000.0) < 2.0


@pytest.mark.parametrize("change, words", [
    (("roi = [40, 540, 6, 46]", "roi = [40, 600, 6, 46]"), ["roi", "not a region of the image", "580 x 52"]),
    (("roi = [40, 540, 6, 46]", "roi = [40, 540, 6]"), ["roi", "four whole pixel indices"]),
    (('profile_along = "columns"', 'profile_along = "diagonal"'), ["profile_along", "rows, columns"]),
    (('mask = "mask.tif"', 'mask = "small.tif"'), ["mask", "small.tif is 10 x 10 pixels", "580 x 52"]),
])
def test_bad_regions_and_masks_are_refused(tmp_path, capsys, change, words):
    full = np.ones((52, 580))
    _scene_file(tmp_path, full.T, x0=-696.0)
    tifffile.imwrite(tmp_path / "mask.tif", np.zeros((580, 52), np.uint8))
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((10, 10), np.uint8))
    scene = tmp_path / "scene.toml"
    scene.write_text(scene.read_text().replace("x0_um = -696.0", "x0_um = -696.0\n" + LAYOUT_KEYS.replace(*change)))
    out = tmp_path / "out"
    assert main(["fit-image", str(scene), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("fwdfit: error:"), err
    for word in words:
        assert word in err, err
    assert not out.exists()


# ------------------------------------------------------------------ rotation, reporting

def test_a_rotated_edge_is_one_parameter(tmp_path, capsys):
    """A straight edge rotated by 1° in the image plane (its centre moving 8.4 µm over 200
    rows): ``sample.rotation_deg`` in [fit] vary is the line through the rows' centres,
    recovered within 0.01°; rows.csv has each row's centre relative to it; result.json
    and the console give the rows' centres' mean and spread and one chi-square over every
    fitted row (rows.csv's chi2 summed)."""
    n_rows, theta = 200, 1.0
    line = 4.0 + np.tan(np.radians(theta)) * (np.arange(n_rows) - 0.5 * (n_rows - 1)) * 2.4
    centres, T, _ = traced_image([fwdfit.ReferenceLayer(1000.0, SLD_AL, 1.4, 0.0)], line, x0_um=-600.0,
                                 n_cols=500, n_rays=12_000_000)
    image = T + 0.003 * np.random.default_rng(19).standard_normal(T.shape)
    scene = _scene_file(tmp_path, image, x0=-600.0, vary=VARY + ("sample.rotation_deg",))
    out = tmp_path / "out"
    assert main(["fit-image", str(scene), "--out", str(out)]) == 0
    console = capsys.readouterr().out
    result = json.loads((out / "result.json").read_text())
    rotation = result["parameters"]["sample.rotation_deg"]
    assert abs(rotation["value"] - theta) < 0.01 and 0 < rotation["error"] < 0.01, rotation
    assert result["edge_line"]["rotation_fitted"] and abs(result["edge_line"]["centre_um"] - 4.0) < 0.5
    rows = read_table(out / "rows.csv")
    assert np.sqrt(np.mean(rows["centre_from_line_um"] ** 2)) < 0.5
    good = rows["flag"] == 0
    centre = result["parameters"]["sample.centre_um"]
    assert centre["value"] == pytest.approx(np.mean(rows["centre_um"][good]))
    assert centre["spread"] == pytest.approx(np.std(rows["centre_um"][good])) and centre["spread"] > 2.0
    assert result["centre_um"]["rows"] == good.sum()
    assert result["chi2"] == pytest.approx(np.sum(rows["chi2"]))
    assert result["chi2_reduced"] == pytest.approx(result["chi2"] / result["dof"])
    assert "sample.rotation_deg" in console and "mean ± spread of" in console, console


def test_rotation_belongs_to_image_fits(tmp_path):
    """The scene key round-trips; a profile fit refuses to vary it (a profile has no rows);
    fit-image refuses it per row."""
    from helpers import small_scene

    scene = small_scene({"sample.centre_um": 0.0, "layers.Al.thickness_um": 1000.0,
                         "layers.Al.sld_e6_per_A2": 2.0}, vary=("sample.rotation_deg",))
    scene = dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, rotation_deg=0.3))
    text = fwdfit.dump_scene(scene)
    assert "rotation_deg = 0.3" in text
    path = fwdfit.save_scene(scene, tmp_path / "scene.toml")
    assert fwdfit.load_scene(path).sample.rotation_deg == 0.3
    with pytest.raises(fwdfit.FwdfitError, match="only fwdfit fit-image fits it"):
        fwdfit.Fitter(fwdfit.load_scene(path))
    image = tmp_path / "T.tif"
    tifffile.imwrite(image, np.ones((4, 20), np.float32))
    per_row = image_scene(image, thickness_um=1000.0, x0_um=-24.0, n_cols=20, per_row=("sample.rotation_deg",))
    with pytest.raises(fwdfit.FwdfitError, match="one for the image"):
        fwdfit.fit_image(fwdfit.load_scene(fwdfit.save_scene(per_row, tmp_path / "rows.toml")))


@pytest.mark.parametrize("with_errors", [True, False])
def test_the_shared_stage_chi2_is_near_one_when_the_errors_are_right(tmp_path, with_errors):
    """Rows that are independent (the model's own image of the weak block, 2 % noise; the
    tracer's rows share one trace, whose noise the averaged rows do not average away):
    the averaged rows' chi2/dof is near 1, with the error image given and with the noise
    read off the image, and so is every row's."""
    result = _fit_noisy_model_image(tmp_path, seed=22, with_errors=with_errors)
    assert 0.9 < result.shared_chi2_reduced < 1.12, result.shared_chi2_reduced
    assert 0.97 < result.chi2_reduced < 1.03, result.chi2_reduced
    assert abs(result.shared["layers.Al.thickness_um"][0] - 1000.0) < 3 * result.shared["layers.Al.thickness_um"][1] + 2


def _fit_noisy_model_image(tmp_path, seed: int, with_errors: bool):
    """fit-image of the model's image plus 2 % Gaussian noise (``seed``), from 1080 µm."""
    fitted = _model_image(str(tmp_path.parent / "model"))
    image = fitted + 0.02 * np.random.default_rng(seed).standard_normal(fitted.shape)
    tifffile.imwrite(tmp_path / "T.tif", image.astype(np.float32))
    tifffile.imwrite(tmp_path / "T_err.tif", np.full(image.shape, 0.02, np.float32))
    scene = image_scene(tmp_path / "T.tif", thickness_um=1080.0, x0_um=-600.0, n_cols=500, vary=VARY,
                        image_err_file=tmp_path / "T_err.tif" if with_errors else None,
                        layers=(fwdfit.Layer("Al", 1080.0, SLD_AL, 3.0, 0.0),))
    return fwdfit.fit_image(fwdfit.load_scene(fwdfit.save_scene(scene, tmp_path / "scene.toml")))


@functools.cache
def _model_image(folder: str) -> np.ndarray:
    """The model's image (T_model) of a fit of the weak block's 40 rows."""
    folder = Path(folder)
    folder.mkdir(exist_ok=True)
    _, T, _ = _block(1.4, 0.0, n_rows=40, n_rays=4_000_000, phase=1.0)
    scene = _scene_file(folder, T + 0.005 * np.random.default_rng(14).standard_normal(T.shape), x0=-600.0)
    return fwdfit.fit_image(scene).T_model
