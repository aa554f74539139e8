"""``fwdfit paganin``: the filter on every measured profile of a scene, tau by hand, bad input."""

import dataclasses
import math
import re
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

import fwdfit
from fwdfit import load_scene, simulate
from fwdfit import FwdfitError
from fwdfit.paganin import paganin_filter_1d
from fwdfit.paganin import paganin_layer, paganin_profiles
from fwdfit.scene import read_columns, write_columns
from fwdfit.cli import main

jax.config.update("jax_enable_x64", True)

CASE = Path(__file__).parent / "data" / "raytrace" / "al_boa_tilt0"
DISTANCES_MM = {"d01.1mm": 1.1, "d08.5mm": 8.5}
HALF_WIDTH_UM = 720.0
PIXEL_UM = 2.4
D_OVER_L = 0.040 / 7.5  # BOA, rad
AL_SLD = 2.078e-6  # Å^-2, as in the scene
AL_MU = 1.39  # 1/m
COAT = fwdfit.Layer("coat", 100.0, 3.3, 20.0, 1.5)


def _scene(folder: Path, measured: bool, *, layers_extra=(), aperture_distance_m: float = 7.5,
           profiles_extra=()) -> fwdfit.Scene:
    """The al_boa_tilt0 scene with our two profiles, measured (read from ``folder``) or simulated."""
    base = load_scene(CASE / "scene.toml")
    profiles = tuple(fwdfit.Profile(name, distance, "white", "", fwdfit.pixel_grid(-HALF_WIDTH_UM, HALF_WIDTH_UM, PIXEL_UM),
                                    file=folder / f"{name}.csv" if measured else None)
                     for name, distance in DISTANCES_MM.items())
    return dataclasses.replace(
        base, sample=dataclasses.replace(base.sample, layers=base.sample.layers + tuple(layers_extra)),
        instruments={name: dataclasses.replace(instrument, aperture_distance_m=aperture_distance_m)
                     for name, instrument in base.instruments.items()},
        profiles=profiles + tuple(profiles_extra))


@pytest.fixture(scope="module")
def measured_dir(tmp_path_factory):
    """A folder with the simulated scene, its 'measured' profiles and the measured scene."""
    folder = tmp_path_factory.mktemp("al_measured")
    for p in simulate(_scene(folder, False)):
        write_columns(folder / f"{p.name}.csv", {"x_um": p.x_um, "T": p.T})
    fwdfit.save_scene(_scene(folder, True), folder / "scene.toml")
    return folder


def _variant(measured_dir, tmp_path, measured: bool = True, **options) -> Path:
    """A copy of the measured scene in tmp_path, with options passed to ``_scene``."""
    for name in DISTANCES_MM:
        shutil.copy(measured_dir / f"{name}.csv", tmp_path)
    return fwdfit.save_scene(_scene(tmp_path, measured, **options), tmp_path / "variant.toml")


def _mean_wavelength_A() -> float:
    """Mean of the BOA spectral density, exact for a density linear between table rows."""
    table = read_columns(CASE / "spectrum_boa.csv", ["lambda_A", "weight"])
    lam, w = table["lambda_A"], table["weight"]
    a, b, wa, wb = lam[:-1], lam[1:], w[:-1], w[1:]
    norm = np.sum((b - a) * (wa + wb) / 2)
    first_moment = np.sum((b - a) * (wa * (2 * a + b) + wb * (a + 2 * b)) / 6)
    return float(first_moment / norm)


def _tau_by_hand(lam_A, distance_mm, *, sld=AL_SLD, mu_per_m=AL_MU, b_factor=1.0, d_over_l=D_OVER_L):
    """tau = b lambda^2 SLD Delta / (2 pi mu) - (Theta Delta)^2 / 8, in um^2."""
    distance_m = 1e-3 * distance_mm
    tau_m2 = (b_factor * (lam_A * 1e-10) ** 2 * (sld * 1e20) * distance_m / (2 * math.pi * mu_per_m)
              - (d_over_l * distance_m) ** 2 / 8)
    return tau_m2 * 1e12


def test_cli_writes_filtered_profiles_with_tau_by_hand(measured_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["paganin", str(measured_dir / "scene.toml"), "--out", str(out),
                 "--b-factor", "3"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [".fwdfit-output", *(f"{name}.csv" for name in DISTANCES_MM)]
    printed = capsys.readouterr().out
    assert "layer Al (the thickest layer" in printed
    lam = _mean_wavelength_A()
    for name, distance in DISTANCES_MM.items():
        assert (out / f"{name}.csv").read_text().splitlines()[0] == "x_um,T,T_filtered"
        table = read_columns(out / f"{name}.csv", ["x_um", "T", "T_filtered"])
        data = read_columns(measured_dir / f"{name}.csv", ["x_um", "T"])
        np.testing.assert_allclose(table["x_um"], data["x_um"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(table["T"], data["T"], rtol=1e-8)
        tau = _tau_by_hand(lam, distance, b_factor=3.0)
        assert tau > 0
        expected = paganin_filter_1d(data["T"], PIXEL_UM, tau)
        # the library's mean wavelength is a 4001-point sum (1e-5 relative): tau to 1e-4
        np.testing.assert_allclose(table["T_filtered"], expected, rtol=0, atol=1e-7)
        printed_tau = re.search(rf"^{name}: tau = (\S+) um\^2", printed, re.MULTILINE).group(1)
        assert float(printed_tau) == pytest.approx(tau, rel=1e-4)
        # the filter must have done something: the edge peaks shrink
        peak = lambda T: np.max(np.abs(T - np.median(T[np.abs(data["x_um"]) < 300])))
        assert peak(table["T_filtered"]) < 0.5 * peak(data["T"])


def test_material_and_mode(measured_dir, tmp_path):
    scene = load_scene(_variant(measured_dir, tmp_path, layers_extra=[COAT]))
    assert paganin_layer(scene).name == "Al"
    lam = _mean_wavelength_A()
    profiles = paganin_profiles(scene, material="coat")
    for p, distance in zip(profiles, DISTANCES_MM.values()):
        tau = _tau_by_hand(lam, distance, sld=3.3e-6, mu_per_m=20.0 + 1.5 * lam)
        assert p.tau_um2 == pytest.approx(tau, rel=1e-4)
        np.testing.assert_allclose(p.T_filtered, paganin_filter_1d(p.T, PIXEL_UM, tau), atol=1e-7)
    # weighted_tau: tau(lambda) averaged over the spectral density, by a fine Riemann sum
    table = read_columns(CASE / "spectrum_boa.csv", ["lambda_A", "weight"])
    grid = np.linspace(table["lambda_A"][0], table["lambda_A"][-1], 200_001)
    density = np.interp(grid, table["lambda_A"], table["weight"])
    weighted = paganin_profiles(scene, material="coat", mode="weighted_tau")
    for p, distance in zip(weighted, DISTANCES_MM.values()):
        tau = np.average(_tau_by_hand(grid, distance, sld=3.3e-6, mu_per_m=20.0 + 1.5 * grid),
                         weights=density)
        assert p.tau_um2 == pytest.approx(tau, rel=1e-5)


@pytest.mark.parametrize("variant, extra, message", [
    ({}, ["--material", "Alu"], "material 'Alu' is not a layer of the scene (layers: Al)"),
    # L/D = 2: the divergence term (Theta Delta)^2 / 8 beats the phase term
    ({"aperture_distance_m": 0.6}, [], "profile d08.5mm: Paganin filter: tau = -"),
    ({"measured": False}, [], "profile d01.1mm has no measured T (file =)"),
    ({}, ["--b-factor", "-1"], "--b-factor: -1 is outside the validity domain"),
])
def test_bad_input_exits_1_with_one_line_and_writes_nothing(measured_dir, tmp_path, capsys,
                                                           variant, extra, message):
    scene = _variant(measured_dir, tmp_path, **variant)
    out = tmp_path / "out"
    assert main(["paganin", str(scene), "--out", str(out), *extra]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fwdfit: error: ")
    assert message in lines[0]
    assert not out.exists()


def test_a_later_simulation_only_profile_stops_everything(measured_dir, tmp_path, capsys):
    sim = fwdfit.Profile("sim", 4.8, "white", "", fwdfit.pixel_grid(-600.0, 600.0, PIXEL_UM))
    scene = _variant(measured_dir, tmp_path, profiles_extra=[sim])
    out = tmp_path / "out"
    assert main(["paganin", str(scene), "--out", str(out)]) == 1
    assert "profile sim has no measured T (file =)" in capsys.readouterr().err
    assert not out.exists()


def test_uneven_grid_is_rejected(measured_dir, tmp_path):
    scene = _variant(measured_dir, tmp_path)
    data = read_columns(tmp_path / "d08.5mm.csv", ["x_um", "T"])
    keep = np.ones(data["x_um"].size, bool)
    keep[100] = False  # one missing pixel
    write_columns(tmp_path / "d08.5mm.csv", {"x_um": data["x_um"][keep], "T": data["T"][keep]})
    with pytest.raises(FwdfitError, match="profile d08.5mm: x_um is not evenly spaced"):
        paganin_profiles(load_scene(scene))
