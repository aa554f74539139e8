"""``fwdfit simulate SCENE --out DIR`` through ``fwdfit.cli.main``: output files and bad input.

Success: one CSV per profile with columns x_um,T,T_att equal to ``fwdfit.simulate``.
Bad input: exit code 1, exactly one line on stderr that names the scene file and the
offending key, no traceback, and no output folder.
"""

import shutil
import subprocess
import sys

import numpy as np
import pytest

import fwdfit
from fwdfit.cli import main
from helpers import RAYTRACE, read_table

LINE_CASE = RAYTRACE / "al_icon_tilt0.24"  # Gaussian lines: no spectrum file needed
WHITE_CASE = RAYTRACE / "al_boa_tilt0"  # names spectrum_boa.csv


@pytest.fixture
def line_scene(tmp_path):
    path = tmp_path / "scene.toml"
    shutil.copy(LINE_CASE / "scene.toml", path)
    return path


def test_simulate_writes_one_csv_per_profile(line_scene, tmp_path, capsys):
    """Exit 0; DIR/<profile>.csv for each of the 4 profiles, header x_um,T,T_att, the
    profile's pixel centres, and T, T_att equal to the library's ``simulate`` (to the
    9 significant digits written)."""
    out = tmp_path / "out"
    assert main(["simulate", str(line_scene), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    expected = fwdfit.simulate(line_scene)
    assert sorted(p.name for p in out.iterdir()) == sorted([".fwdfit-output", *(f"{p.name}.csv" for p in expected)])
    for p in expected:
        path = out / f"{p.name}.csv"
        assert path.read_text().splitlines()[0] == "x_um,T,T_att"
        table = read_table(path)
        np.testing.assert_allclose(table["x_um"], p.x_um, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(table["T"], p.T, rtol=1e-8, atol=0)
        np.testing.assert_allclose(table["T_att"], p.T_att, rtol=1e-8, atol=0)
        assert p.T.max() > 1.05 and p.T_att.min() < 1.0  # a real profile, not a flat line


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


BAD_SCENES = {
    # name: (edit of the line scene, key the message must name)
    "unknown_key": (("tilt_deg = 0.24", "tilt_deg = 0.24\ntilt_degree = 0.24"), "sample.tilt_degree"),
    "unknown_material": (("sld_e6_per_A2 = 2.078\nmu_per_m = 1.39",
                          'material = "Xq"\ndensity_g_cm3 = 2.7'), "sample.layers[0].material"),
    "negative_thickness": (("thickness_um = 1000", "thickness_um = -5"),
                           "sample.layers[0].thickness_um"),
    "negative_distance": (("distance_mm = 1.1", "distance_mm = -1.1"), "profiles[0].distance_mm"),
    "duplicate_layer_name": (("[instrument]", '[[sample.layers]]\nname = "Al"\nthickness_um = 10\n'
                              'sld_e6_per_A2 = 3.5\nmu_per_m = 12.0\n\n[instrument]'),
                             "sample.layers[1].name"),
    "same_as_unknown": (("[instrument]", '[[sample.layers]]\nname = "coat"\nsame_as = "oxide"\n\n'
                         '[instrument]'), "sample.layers[1].same_as"),
}


def _assert_one_line_error(capsys, scene_path, key, out, extra=()):
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith("fwdfit: error: ")
    assert scene_path.name in line and key in line, line
    for word in extra:
        assert word in line, line
    assert "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("case", list(BAD_SCENES))
def test_bad_scene_is_one_line_error(line_scene, tmp_path, capsys, case):
    """Each bad scene: exit 1, one stderr line naming the file and the key, nothing written."""
    (old, new), key = BAD_SCENES[case]
    bad = tmp_path / f"{case}.toml"
    bad.write_text(_edit(line_scene.read_text(), old, new))
    out = tmp_path / "out"
    assert main(["simulate", str(bad), "--out", str(out)]) == 1
    _assert_one_line_error(capsys, bad, key, out)


def test_missing_spectrum_file_is_one_line_error(tmp_path, capsys):
    """A scene whose spectrum table is not next to it: exit 1, one line naming the scene, the
    spectrum key and the missing file, nothing written."""
    scene = tmp_path / "scene.toml"
    shutil.copy(WHITE_CASE / "scene.toml", scene)  # without spectrum_boa.csv
    out = tmp_path / "out"
    assert main(["simulate", str(scene), "--out", str(out)]) == 1
    _assert_one_line_error(capsys, scene, "spectra.white", out, extra=("spectrum_boa.csv",))


def test_missing_scene_file_is_one_line_error(tmp_path, capsys):
    """A scene path that does not exist: exit 1, one line naming it, nothing written."""
    scene = tmp_path / "nowhere.toml"
    out = tmp_path / "out"
    assert main(["simulate", str(scene), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "nowhere.toml" in err and "Traceback" not in err
    assert not out.exists()


def test_python_m_fwdfit_is_the_command(tmp_path):
    """``python -m fwdfit`` runs the same command line: its exit status and one-line errors."""
    scene = tmp_path / "nowhere.toml"
    done = subprocess.run([sys.executable, "-m", "fwdfit", "simulate", str(scene), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1
    assert lines[0].startswith("fwdfit: error: ") and "nowhere.toml" in lines[0]
    assert not (tmp_path / "out").exists()
