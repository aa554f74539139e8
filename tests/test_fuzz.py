"""Fuzz: every scene ends in a right answer or in one clear line.

Scenes are drawn over the whole validity domain of every key (docs/SCENE.md,
``fwdfit.scene.DOMAIN``), then some are broken at one place: a value outside the
domain (NaN and infinities included), a wrong type, a missing or an unknown key, a
wrong name or reference, a broken spectrum table. Each is written as TOML and run
through ``fwdfit.cli.main(["simulate", scene, "--out", dir])`` in-process. It must end
either in exit 0 with one finite CSV per profile and nothing on stderr, or in exit 1
with exactly one stderr line ``fwdfit: error: ...``, no output folder and no temporary
files left.

Compilation dominates: a few seconds for every new static shape of the model (the
instrument's values, pixels, blur sub-bins, quadrature sizes, interfaces, aperture kind).
Profiles have 8 pixels, and the default run draws the static choices from three
configurations at the domain's edges (``FEW_SHAPES``) with every other key over its
whole domain: 60 valid and 150 broken scenes, about 20 compilations, 60-80 s on two
loaded cores (30-40 s before thin layers were coupled: a scene whose drawn thickness is
below the sideways drift compiles the coupled kernels). The slow run
(``FWDFIT_FUZZ=many``; the CI runs slow tests, so these wait for the variable) draws the
static choices from their whole domain too: 600 scenes, most compiled anew (~0.7 s each,
about 7 min), and 3000 broken ones (about 2 min).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fwdfit.scene import DOMAIN
from fwdfit.cli import main

N_PIXELS = 8
MATERIALS = ["Al", "Si", "Fe", "Cu", "Al2O3", "H2O", "D2O", "Gd2O3"]
NAME = st.text("abcdefghijklmnopqrstuvwxyz0123456789_.-", min_size=1, max_size=12)

# Static choices, each a new compilation: the instrument (its values are static in the
# model), the spectrum's kind ("line0": zero width, one wavelength node), the number of
# layers and profiles, [model] accuracy. FEW_SHAPES holds three, at domain edges.
FEW_SHAPES = st.sampled_from([
    dict(aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5, pixel_um=2.4,
         psf_pixels=0.0, spectrum="line", n_layers=1, accuracy=None, n_profiles=1),
    dict(aperture="square", aperture_mm=1e3, aperture_distance_m=100.0, pixel_um=1e4,
         psf_pixels=1.0, spectrum="table", n_layers=2, accuracy=0.1, n_profiles=1),
    dict(aperture="circular", aperture_mm=1e-3, aperture_distance_m=0.01, pixel_um=0.01,
         psf_pixels=100.0, spectrum="line0", n_layers=3, accuracy=1e-5, n_profiles=2),
])
ALL_SHAPES = st.fixed_dictionaries(dict(
    aperture=st.sampled_from(["square", "circular"]),
    aperture_mm=st.floats(*DOMAIN["aperture_mm"]),
    aperture_distance_m=st.floats(*DOMAIN["aperture_distance_m"]),
    pixel_um=st.floats(*DOMAIN["pixel_um"]),
    spectrum=st.sampled_from(["line", "line0", "table"]),
    n_layers=st.integers(1, 4),
    psf_pixels=st.one_of(st.just(0.0), st.floats(0.0, 100.0)),
    accuracy=st.one_of(st.none(), st.floats(*DOMAIN["accuracy"])),
    n_profiles=st.integers(1, 3),
))
# The CI runs the slow tests too: the many-example runs wait for FWDFIT_FUZZ=many.
MANY = pytest.mark.skipif(os.environ.get("FWDFIT_FUZZ") != "many",
                          reason="thousands of scenes: set FWDFIT_FUZZ=many")
FEW = settings(max_examples=60, deadline=None, derandomize=True, database=None,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# --------------------------------------------------------------------------- TOML


def toml_value(value) -> str:
    """Any TOML value, tables inline (so that broken structures can be written too)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{toml_value(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"


def toml_document(document: dict) -> str:
    return "".join(f"{toml_value(str(key))} = {toml_value(value)}\n"
                   for key, value in document.items())


# ------------------------------------------------------------------ valid scenes


def domain(key: str) -> st.SearchStrategy[float]:
    return st.floats(*DOMAIN[key])


@st.composite
def layer(draw, index: int, earlier: list[str]) -> dict:
    name = f"layer{index}"
    form = draw(st.sampled_from(["explicit", "material", "same_as"] if earlier
                                else ["explicit", "material"]))
    if form == "same_as":
        return {"name": name, "same_as": draw(st.sampled_from(earlier))}
    entry = {"name": name, "thickness_um": draw(domain("thickness_um"))}
    if form == "material":
        entry.update(material=draw(st.sampled_from(MATERIALS)),
                     density_g_cm3=draw(domain("density_g_cm3")))
    else:
        entry.update({key: draw(domain(key)) for key in ("sld_e6_per_A2", "mu_per_m")})
        if draw(st.booleans()):
            entry["mu_per_m_per_A"] = draw(domain("mu_per_m_per_A"))
    return entry


@st.composite
def spectrum_table(draw) -> str:
    """A spectrum table: 2-6 increasing wavelengths in the domain, weights >= 0."""
    lam = sorted(draw(st.lists(domain("lambda_A"), min_size=2, max_size=6, unique=True)))
    weights = draw(st.lists(st.floats(0.0, 1e6), min_size=len(lam), max_size=len(lam)))
    weights[draw(st.integers(0, len(lam) - 1))] = draw(st.floats(1e-3, 1e6))
    return "lambda_A,weight\n" + "".join(f"{a!r},{w!r}\n" for a, w in zip(lam, weights))


@st.composite
def valid_scenes(draw, shapes) -> tuple[dict, dict[str, str]]:
    """A scene with every value drawn from its domain; (document, {file name: text}).

    Dependent values are drawn so that the scene mostly holds together: distances
    between the tilted sample's reach and the aperture, the pixel grid N_PIXELS wide, the
    blur as a number of pixels. Where a draw still breaks a combination (a distance on
    the limit, a material's SLD beyond the domain), exit 1 is the answer.
    """
    shape = draw(shapes)
    depth = draw(domain("depth_mm"))
    sample = {"depth_mm": depth, "tilt_deg": draw(domain("tilt_deg")),
              "centre_um": draw(domain("centre_um")),
              "drift_um_per_mm": draw(domain("drift_um_per_mm")), "layers": []}
    for index in range(shape["n_layers"]):
        earlier = [entry["name"] for entry in sample["layers"]]
        sample["layers"].append(draw(layer(index, earlier)))
    pixel, aperture_distance_m = shape["pixel_um"], shape["aperture_distance_m"]
    instrument = {"aperture": shape["aperture"], "aperture_mm": shape["aperture_mm"],
                  "aperture_distance_m": aperture_distance_m, "pixel_um": pixel,
                  "psf_fwhm_um": min(shape["psf_pixels"] * pixel, DOMAIN["psf_fwhm_um"][1]),
                  "fresnel": False}
    files = {}
    if shape["spectrum"] == "table":
        spectra = {"beam": {"file": "spectrum.csv"}}
        files["spectrum.csv"] = draw(spectrum_table())
    else:
        width = 0.0 if shape["spectrum"] == "line0" else draw(st.floats(1e-6, DOMAIN["fwhm_rel"][1]))
        spectra = {"beam": {"wavelength_A": draw(domain("wavelength_A")), "fwhm_rel": width}}
    thickness = {}
    for entry in sample["layers"]:
        thickness[entry["name"]] = thickness.get(entry.get("same_as"), entry.get("thickness_um"))
    tilt = math.radians(sample["tilt_deg"])
    reach = 0.5 * depth + 0.5e-3 * sum(thickness.values()) * abs(math.sin(tilt))
    far = min(DOMAIN["distance_mm"][1], 1e3 * aperture_distance_m - reach)
    profiles = []
    for index in range(shape["n_profiles"]):
        x_min = draw(st.floats(DOMAIN["x_min_um"][0], DOMAIN["x_max_um"][1] - N_PIXELS * pixel))
        profiles.append({
            "name": f"p{index}-" + draw(NAME), "spectrum": "beam",
            "distance_mm": reach + draw(st.floats(1e-9, 1.0)) * max(far - reach, 0.0),
            "x_min_um": x_min, "x_max_um": x_min + N_PIXELS * pixel,
            "shift_um": draw(domain("shift_um")), "norm": draw(domain("norm")),
            "background": draw(domain("background"))})
    document = {"sample": sample, "instrument": instrument, "spectra": spectra,
                "profiles": profiles}
    if shape["accuracy"] is not None:
        document["model"] = {"accuracy": shape["accuracy"]}
    if draw(st.booleans()):
        document["fit"] = {"vary": ["sample.tilt_deg", "layers.layer0.thickness_um"],
                           "bounds": {"sample.tilt_deg": [-1.0, 1.0]}}
    return document, files


# ----------------------------------------------------------------- broken scenes


def _places(node, path=()) -> list[tuple]:
    """Paths to every table, array and value of a document."""
    places = [path] if path else []
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in children:
        places += _places(child, (*path, key))
    return places


def _parent(document, path):
    for key in path[:-1]:
        document = document[key]
    return document


WRONG_TYPES = st.sampled_from(["text", "", True, [1.0, 2.0], {"a": 1.0}, [], {}, 7])


def outside(key: str) -> st.SearchStrategy[float]:
    low, high = DOMAIN[key]
    return st.one_of(st.floats(max_value=low, exclude_max=True),
                     st.floats(min_value=high, exclude_min=True),
                     st.sampled_from([math.nan, math.inf, -math.inf]))


@st.composite
def broken_scenes(draw, shapes) -> tuple[dict, dict[str, str]]:
    """A valid scene broken at one place (which may happen to leave it valid)."""
    document, files = draw(valid_scenes(shapes))
    places = _places(document)
    kind = draw(st.sampled_from(["outside", "wrong_type", "missing", "unknown_key", "text",
                                 "file"]))
    if kind == "outside":
        numeric = [p for p in places if isinstance(p[-1], str) and p[-1] in DOMAIN]
        path = draw(st.sampled_from(numeric))
        _parent(document, path)[path[-1]] = draw(outside(path[-1]))
    elif kind in ("wrong_type", "missing"):
        path = draw(st.sampled_from(places))
        if kind == "missing":
            del _parent(document, path)[path[-1]]
        else:
            _parent(document, path)[path[-1]] = draw(WRONG_TYPES)
    elif kind == "unknown_key":
        tables = [()] + [p for p in places if isinstance(_parent(document, (*p, None)), dict)]
        path = draw(st.sampled_from(tables))
        _parent(document, (*path, None))[draw(st.text(min_size=1, max_size=12))] = 1.0
    elif kind == "text":
        strings = [p for p in places if isinstance(_parent(document, p)[p[-1]], str)]
        path = draw(st.sampled_from(strings))
        _parent(document, path)[path[-1]] = draw(st.text(max_size=20))
    elif files:
        files["spectrum.csv"] = draw(st.sampled_from([
            "", "lambda_A,weight\n", "lambda_A,weight\n1.0,nan\n2.0,1.0\n",
            "lambda_A,weight\n2.0,1.0\n1.0,1.0\n", "lambda_A,weight\n1.0,0\n2.0,0\n",
            "lambda,weight\n1.0,1.0\n2.0,1.0\n", "lambda_A,weight\n1.0,1.0,3.0\n2.0,1.0,3.0\n",
            "lambda_A,weight\n1e-3,1.0\n2.0,1.0\n", "\x00\xff binary"]))
    else:
        document["spectra"] = {"beam": {"file": "missing.csv"}}
    return document, files


# ------------------------------------------------------------------------ the check


def check_outcome(case: tuple[dict, dict[str, str]]) -> None:
    """Run ``fwdfit simulate`` on the scene; assert a finite result or one clean line."""
    document, files = case
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        scene = folder / "scene.toml"
        scene.write_text(toml_document(document), encoding="utf-8")
        for name, text in files.items():
            (folder / name).write_text(text, encoding="utf-8")
        out = folder / "out"
        stderr = io.StringIO()
        with (contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()),
              warnings.catch_warnings(record=True) as caught):
            warnings.simplefilter("always")
            status = main(["simulate", str(scene), "--out", str(out), "--quiet"])
        # A warning would be printed on the terminal: it counts as a line.
        lines = stderr.getvalue().splitlines() + [f"warning: {w.message}" for w in caught]
        if status == 0:  # only the note of a thin layer that the model leaves uncoupled
            assert all(line.startswith("warning: layer ") and "modelled independently" in line
                       for line in lines), lines
            names = [profile["name"] for profile in document["profiles"]]
            notes = ["warnings.txt"] if lines else []  # the printed notes, written beside the profiles
            assert sorted(os.listdir(out)) == sorted([f"{name}.csv" for name in names] + notes + [".fwdfit-output"])
            for name in names:
                path = out / f"{name}.csv"
                assert path.read_text().splitlines()[0] == "x_um,T,T_att"
                table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
                assert table.shape == (N_PIXELS, 3) and np.all(np.isfinite(table)), name
        else:
            assert status == 1, (status, lines)
            assert len(lines) == 1 and lines[0].startswith("fwdfit: error: "), lines
            assert lines[0].count("scene.toml") <= 1, lines  # named once, not per layer of code
            assert not out.exists()
        leftovers = [p.name for p in folder.iterdir() if p.name.startswith(".")]
        assert leftovers == [], leftovers


@FEW
@given(valid_scenes(FEW_SHAPES))
def test_scenes_over_the_domain(case):
    check_outcome(case)


@settings(FEW, max_examples=150)
@given(broken_scenes(FEW_SHAPES))
def test_broken_scenes(case):
    check_outcome(case)


@pytest.mark.slow
@MANY
@settings(FEW, max_examples=600)
@given(valid_scenes(ALL_SHAPES))
def test_scenes_over_the_domain_everywhere(case):
    """Static choices too from their whole domain: most scenes compile anew."""
    check_outcome(case)


@pytest.mark.slow
@MANY
@settings(FEW, max_examples=3000)
@given(broken_scenes(FEW_SHAPES))
def test_broken_scenes_many(case):
    check_outcome(case)


@settings(FEW, max_examples=150)
@given(valid_scenes(ALL_SHAPES))
def test_valid_scenes_round_trip_through_dump_scene(case):
    """``load_scene(dump_scene(scene))`` is the scene, field for field, over the whole domain
    (no model is built: cheap)."""
    import fwdfit
    from helpers import scene_differences

    document, files = case
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        (folder / "scene.toml").write_text(toml_document(document), encoding="utf-8")
        for name, text in files.items():
            (folder / name).write_text(text, encoding="utf-8")
        try:
            scene = fwdfit.load_scene(folder / "scene.toml")
        except fwdfit.FwdfitError:  # a combination of keys out of the domain
            return
        again = fwdfit.load_scene(fwdfit.save_scene(scene, folder / "sub" / "again.toml"))
        assert scene_differences(again, scene) == []
