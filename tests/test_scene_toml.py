"""``dump_scene``, the one scene writer: ``load_scene`` gives every scene back field for field."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import fwdfit
import fwdfit.inference
from helpers import BOA_SPECTRUM, scene_differences

ROOT = Path(__file__).parent.parent
SHIPPED = sorted([*(ROOT / "tests" / "data").rglob("*.toml"), *(ROOT / "examples").rglob("*.toml"),
                  *(ROOT / "notebooks" / "data").rglob("*.toml")])


def round_trip(scene, folder: Path, name: str = "again.toml"):
    return fwdfit.load_scene(fwdfit.save_scene(scene, Path(folder) / name))


@pytest.mark.parametrize("path", SHIPPED, ids=[str(p.relative_to(ROOT)) for p in SHIPPED])
def test_every_shipped_scene_round_trips(path, tmp_path):
    if "ncrystal" in path.read_text():
        pytest.importorskip("NCrystal")
    scene = fwdfit.load_scene(path)
    assert scene_differences(round_trip(scene, tmp_path), scene) == []
    assert scene_differences(round_trip(scene, path.parent, f".again_{tmp_path.name}.toml"), scene) == []
    (path.parent / f".again_{tmp_path.name}.toml").unlink()


def test_scene_built_in_python_round_trips(tmp_path):
    """Every kind of layer, spectrum and profile, keys off their defaults, an odd grid start."""
    white = fwdfit.TabulatedSpectrum(*np.loadtxt(BOA_SPECTRUM, delimiter=",", skiprows=1, unpack=True),
                                     path=BOA_SPECTRUM)
    al = fwdfit.Layer.from_material("Al", 1000.0, fwdfit.constants_from_formula("Al", 2.70), 0.98)
    oxide = fwdfit.Layer("oxide", math.nan, 3.5, 12.0, 0.25)  # a start left to the fit
    pixel_um = 2.4
    scene = fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.24, centre_um=-3.3, drift_um_per_mm=0.01,
                             layers=(oxide, al, oxide.tied("o2"))),
        instruments={"": fwdfit.Instrument("circular", 20.0, 5.5, pixel_um, psf_fwhm_um=3.0, fresnel=True),
                     'ICON "2"': fwdfit.Instrument("square", 40.0, 7.5, 13.5)},
        spectra={"line": fwdfit.GaussianLine(4.6, 0.1), "white": white,
                 "band": fwdfit.BandSpectrum(2.0, 3.0, white), "flat": fwdfit.BandSpectrum(1.0, 5.0, None)},
        profiles=(fwdfit.Profile("a", 10.0, "line", "", fwdfit.pixel_grid(-600.1, 600.0, pixel_um),
                                 shift_um=1.5, norm=0.99, background=0.01),
                  fwdfit.Profile("b\u00e9", 34.4, "band", 'ICON "2"', fwdfit.pixel_grid(-0.3, 1000.0, 13.5))),
        fit=fwdfit.FitSpec(vary=("layers.oxide.thickness_um", "sample.tilt_deg"),
                           bounds={"sample.tilt_deg": (-1.0, 1.0)}),
        accuracy=3e-4)
    again = round_trip(scene, tmp_path)
    assert scene_differences(again, scene) == []
    assert scene_differences(round_trip(again, tmp_path / "other"), scene) == []


def test_what_a_scene_cannot_hold_is_one_error(tmp_path):
    scene = fwdfit.load_scene(ROOT / "examples" / "al_block" / "scene.toml")
    spectra = {name: fwdfit.TabulatedSpectrum(np.array([1.0, 2.0]), np.array([1.0, 1.0]))
               for name in scene.spectra}
    with pytest.raises(fwdfit.FwdfitError, match="came from no file"):
        fwdfit.save_scene(fwdfit.Scene(scene.sample, scene.instruments, spectra, scene.profiles), tmp_path / "s.toml")
    assert list(tmp_path.iterdir()) == []
    uneven = dataclasses.replace(scene.profiles[0], file=None, x_um=np.array([0.0, 1.0, 3.0]))
    with pytest.raises(fwdfit.FwdfitError, match="not a grid of pixel_um"):
        fwdfit.save_scene(dataclasses.replace(scene, profiles=(uneven,)), tmp_path / "s.toml")
    assert list(tmp_path.iterdir()) == []


def test_placeholders_are_commented_out():
    scene = fwdfit.load_scene(ROOT / "examples" / "al_block" / "scene.toml")
    text = fwdfit.dump_scene(scene, comment="one\ntwo", placeholders=("sample", "instrument.aperture_mm"))
    import tomllib

    document = tomllib.loads(text)
    assert text.startswith("# one\n# two\n") and "sample" not in document
    assert "# [sample]" in text and "# [[sample.layers]]" in text
    assert all("aperture_mm" not in table for table in [document.get("instrument", {}),
                                                          *document.get("instruments", {}).values()])


def test_registry_defaults_are_the_scene_defaults(tmp_path):
    """Every fitted quantity with a default in ``fwdfit.inference.QUANTITIES`` has it as its
    dataclass default and gets it from the reader when the key is left out."""
    parts = {"sample": fwdfit.Sample, "layers": fwdfit.Layer, "profiles": fwdfit.Profile}
    scene = fwdfit.load_scene(fwdfit.save_scene(fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, layers=(fwdfit.Layer("a", 10.0, 1.0, 1.0),)),
        instruments={"": fwdfit.Instrument("square", 1.0, 5.0, 2.4)}, spectra={"s": fwdfit.GaussianLine(4.0, 0.1)},
        profiles=(fwdfit.Profile("p", 5.0, "s", "", fwdfit.pixel_grid(-24.0, 24.0, 2.4)),)), tmp_path / "s.toml"))
    read = {"sample": scene.sample, "layers": scene.sample.layers[0], "profiles": scene.profiles[0]}
    checked = 0
    same = lambda a, b: a == b or (math.isnan(a) and math.isnan(b))  # NaN: a graded layer's end left out
    for q in fwdfit.inference.QUANTITIES:
        fields = {f.name: f for f in dataclasses.fields(parts[q.part])}
        assert q.key in fields, q
        if q.default is not None:
            assert same(getattr(read[q.part], q.key), q.default), q
            if fields[q.key].default is not dataclasses.MISSING:
                assert same(fields[q.key].default, q.default), q
            checked += 1
    assert checked >= 7
    keys = [q.key for q in fwdfit.inference.QUANTITIES]
    assert len(set(keys)) == len(keys), "a key names one quantity (a vary name ends in its key)"
