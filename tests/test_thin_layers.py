"""Coupled thin layers: layers thinner than the sideways drift depth x |angle|.

Checked against the exact ray tracer's profiles stored in ``tests/data/raytrace_thin``
(generator and provenance there): a 2 µm and a 1.2 µm oxide skin on 1 mm of Al and a
4 µm Ti layer (SLD -1.95, mu 60 /m) inside Al, BOA white beam at 1.1 and 10 mm and an
ICON 4 Å line at 1.1 mm, tilts 0 and 0.24°, with and without Fresnel reflection (the
``*_fresnel`` cases), default accuracy, float64. A free thickness
going to 0 must make the layer vanish smoothly; thick scenes must not change.
"""

import dataclasses
import warnings
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

import fwdfit
from fwdfit.cli import main
from fwdfit.scene import read_columns
from helpers import al_layer, make_scene, oxide_layer, rms, skin_scene

DATA = Path(__file__).parent / "data" / "raytrace_thin"
CASES = sorted(p.parent.name for p in DATA.glob("*/case.json"))
LIMIT = 2e-3  # RMS of T - T_ref and of T_att - T_att_ref, every profile


@pytest.fixture(scope="module")
def evaluate():
    """Model and parameters in, (T, T_att) out: one compilation per layer structure (skins,
    Ti), the models built with windows for tilts 0 to 0.24° so that both tilts share it."""
    return eqx.filter_jit(lambda model, params: model(params))


@pytest.mark.slow  # ~80 s per compiled model on a loaded 2-core machine, four models (Fresnel off and on)
@pytest.mark.parametrize("case", CASES)
def test_thin_layer_matches_the_tracer(case, evaluate):
    scene = fwdfit.load_scene(DATA / case / "scene.toml")
    model = fwdfit.build_model(scene, tilt_range_deg=(0.0, 0.24))
    assert model.thin, "a layer thinner than the drift must be coupled"
    T, T_att = evaluate(model, fwdfit.initial_params(scene))
    for i, profile in enumerate(scene.profiles):
        ref = read_columns(DATA / case / f"{profile.name}.csv", ("x_um", "T", "T_err", "T_att", "T_att_err"))
        errors = rms(np.asarray(T[i]) - ref["T"]), rms(np.asarray(T_att[i]) - ref["T_att"])
        print(f"{case} {profile.name}: RMS T {errors[0]:.5f}, T_att {errors[1]:.5f}, "
              f"tracer noise {rms(ref['T_err']):.5f}")
        assert errors[0] <= LIMIT and errors[1] <= LIMIT, (case, profile.name, errors)


def test_thick_scenes_are_planned_as_before():
    """A 1 mm Al block, and the same block under a 100 µm coating with fixed thicknesses,
    couple no layer: the same interfaces and kernels as without thin layers (no cost)."""
    for layers in ([al_layer()], [oxide_layer("ox", 100.0, 3.5, 12.0), al_layer()]):
        scene = make_scene(layers, profiles=[("p", 1.1, -600.0, 600.0)], spectrum=fwdfit.GaussianLine(4.0, 0.15))
        model = fwdfit.build_model(scene)
        assert model.thin == () and len(model.interfaces) == len(layers) + 1
        assert all(group.guided_cells == 0 and group.thin_nodes == () for group in model.groups)
    thin = fwdfit.build_model(skin_scene(2.0))
    assert [(t.left, t.layer, t.right) for t in thin.thin] == [(0, 1, 2)]
    assert len(thin.interfaces) == 1  # Al | vacuum on the right; the skin's faces are coupled


def test_a_thin_layer_left_independent_is_reported():
    """A 2 µm skin is coupled without a warning, with Fresnel reflection on or off; with a rough
    face, or as one of two adjacent thin layers, its faces stay independent and a ModelWarning
    names it and why."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", fwdfit.ModelWarning)
        assert fwdfit.build_model(skin_scene(2.0)).thin
        assert fwdfit.build_model(skin_scene(2.0, fresnel=True)).thin
    with pytest.warns(fwdfit.ModelWarning, match=r"layer 'skin' \(2 µm\).*with a rough face"):
        assert fwdfit.build_model(skin_scene(2.0, roughness_mrad=1.0)).thin == ()
    two = make_scene([oxide_layer("outer", 1.0, 4.5, 100.0), oxide_layer("inner", 2.0, 3.0, 50.0), al_layer()],
                     profiles=[("p", 1.1, -530.0, -470.0)], spectrum=fwdfit.GaussianLine(4.0, 0.15))
    with pytest.warns(fwdfit.ModelWarning, match="next to another thin layer") as caught:
        assert len(fwdfit.build_model(two).thin) == 1
    assert len(caught) == 1


def test_the_command_line_prints_the_model_warning_as_one_line(tmp_path, capsys):
    path = fwdfit.save_scene(skin_scene(2.0, roughness_mrad=1.0), tmp_path / "scene.toml")
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("warning: layer 'skin'"), lines
    assert (tmp_path / "out" / "warnings.txt").read_text() == lines[0].removeprefix("warning: ") + "\n"


def test_a_window_over_one_skin_equals_the_whole_profile_there():
    """The tracer's 1.2 µm skins on 1 mm of Al (0.24°, ICON 4 Å, 1.1 mm): a window over the
    left edge only (the right skin's kernels reach none of its pixels and are skipped) gives
    the same T and T_att as a window over the whole sample (both skins' kernels evaluated) on
    the pixels they share. Before the skip the far skin's kernels, evaluated on the narrow
    window's last edges, added up to 8e-7 there (their depth quadrature's drift)."""
    scene = fwdfit.load_scene(DATA / "skin1.2_tilt0.24" / "scene.toml")
    narrow = next(p for p in scene.profiles if p.name == "icon_d01.1mm")
    shared = len(narrow.x_um)
    wide = dataclasses.replace(narrow, x_um=narrow.x_um[0] + 2.4 * np.arange(shared + 500))
    assert wide.x_um[-1] > 500.0 > narrow.x_um[-1] + 900.0  # the right skin at +500 µm
    values = []
    for profile in (narrow, wide):
        one = dataclasses.replace(scene, profiles=(profile,))
        (T,), (T_att,) = eqx.filter_jit(lambda m, p: m(p))(fwdfit.build_model(one), fwdfit.initial_params(one))
        values.append(np.concatenate([np.asarray(T)[:shared], np.asarray(T_att)[:shared]]))
    assert np.max(np.abs(values[0] - values[1])) < 1e-12, np.max(np.abs(values[0] - values[1]))


def test_a_fit_keeps_the_model_warning_in_its_result(tmp_path):
    """A fit of a skin with a rough face (left independent) reports that in result.json's
    model_warnings, and still recovers the centre from simulated data with 0.2 % noise."""
    import json

    truth = dataclasses.replace(skin_scene(2.0, roughness_mrad=1.0), fit=fwdfit.FitSpec(("sample.centre_um",)))
    with pytest.warns(fwdfit.ModelWarning):
        (T,), _ = fwdfit.build_model(truth)(fwdfit.initial_params(truth))
    noise = 0.002 * np.random.default_rng(3).standard_normal(T.shape)
    profile = dataclasses.replace(truth.profiles[0], T=np.asarray(T) + noise, T_err=np.full(T.shape, 0.002))
    scene = dataclasses.replace(truth, sample=dataclasses.replace(truth.sample, centre_um=1.5), profiles=(profile,))
    with pytest.warns(fwdfit.ModelWarning, match=r"layer 'skin'"):
        result = fwdfit.Fitter(scene)()
    assert len(result.model_warnings) == 1 and "with a rough face" in result.model_warnings[0]
    assert abs(result.values[0]) < 3 * result.errors[0] + 0.05, (result.values, result.errors)
    fwdfit.write_fit(result, tmp_path / "out")
    written = json.loads((tmp_path / "out" / "result.json").read_text())
    assert written["model_warnings"] == list(result.model_warnings)
