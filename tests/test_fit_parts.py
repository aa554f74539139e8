"""The fit's parts, each against an independent answer: starts read off the data,
the least-squares solver, the quality gate, the compilation cache and missing starts.

Fast: no fit of a whole scene here (those are in test_fit.py and test_fit_starts.py).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest

import fwdfit
from fwdfit.inference import cache_dir
from fwdfit.inference import levenberg_marquardt
from fwdfit.inference import forget_compiled
from fwdfit.inference import assess, runs_z
from fwdfit.inference import attenuation_from_plateau, one_edge, outer_edges, refraction_edges, segment
from fwdfit.inference import estimate_starts, free_parameters
from helpers import small_scene

PIXEL_UM = 2.4


# --------------------------------------------------------------------------- starts read off the data


def test_segment_finds_the_plateaus():
    """Least-squares segmentation of three noisy plateaus returns their exact boundaries."""
    rng = np.random.default_rng(0)
    values = np.concatenate([np.full(40, 0.97), np.full(90, 0.95), np.full(30, 0.99)])
    noisy = values + rng.normal(0.0, 0.003, values.shape)
    np.testing.assert_array_equal(segment(noisy, 3), [40, 130])


@pytest.mark.parametrize("noise,tolerance_um", [(0.002, 1.5), (0.01, 5.0)])
def test_outer_edges_of_a_blurred_step(noise, tolerance_um):
    """A 987 µm wide step of depth 2.5 %, blurred by 6 µm, with 0.2 % and 1 % noise: edges
    within 1.5 and 5 µm of the truth (half-way points; at 1 % noise the filter must be 55 µm
    wide to see the step), open level within 3 noise / sqrt(n)."""
    rng = np.random.default_rng(1)
    x = -780.0 + (np.arange(650) + 0.5) * PIXEL_UM
    left, right = -490.5, 496.5
    # a step blurred by a uniform 6 µm penumbra, pixel-averaged: exact via the ramp integral
    ramp = lambda u: np.clip((u + 3.0) / 6.0, 0.0, 1.0)
    inside = ramp(x - left) * ramp(right - x)
    T = 1.0 - 0.025 * inside + rng.normal(0.0, noise, x.shape)
    found_left, found_right, level = outer_edges(x, T, blur_um=8.4, pixel_um=PIXEL_UM)
    assert found_left == pytest.approx(left, abs=tolerance_um)
    assert found_right == pytest.approx(right, abs=tolerance_um)
    assert level == pytest.approx(1.0, abs=3 * noise / math.sqrt(65))


def test_outer_edges_of_a_transparent_block_from_its_refraction_spikes():
    """A block absorbing 0.3 % (below the 0.5 % noise) with refraction gain outside and loss
    inside each edge (0.2 over 5 µm): no plateau to find, but the edges half-way between
    gain and loss, within one pixel of the truth."""
    rng = np.random.default_rng(4)
    x = -700.0 + (np.arange(584) + 0.5) * PIXEL_UM
    left, right = -500.3, 499.1
    T = np.where((x > left) & (x < right), 0.997, 1.0) + rng.normal(0.0, 0.005, x.shape)
    for edge in (left, right):
        outward = np.sign(edge)
        T[(outward * (x - edge) > 0) & (outward * (x - edge) < 5)] += 0.2
        T[(outward * (edge - x) > 0) & (outward * (edge - x) < 5)] -= 0.2
    assert outer_edges(x, T, blur_um=8.0, pixel_um=PIXEL_UM) is None  # no plateau to see
    found_left, found_right, _ = refraction_edges(x, T, 1.0, 0.005)
    assert found_left == pytest.approx(left, abs=PIXEL_UM)
    assert found_right == pytest.approx(right, abs=PIXEL_UM)


@pytest.mark.parametrize("sample_right", [True, False])
def test_one_edge_of_a_wide_absorbing_stack(sample_right):
    """A window 144 µm wide over one edge of a stack 1 mm wide (2 % absorption, 6 µm
    penumbra, 0.5 % noise): the edge within 2 µm, on the right side, the open level within
    3 noise / sqrt(n)."""
    rng = np.random.default_rng(5)
    x = -574.0 + (np.arange(60) + 0.5) * PIXEL_UM
    edge = -501.3
    inside = np.clip((x - edge + 3.0) / 6.0, 0.0, 1.0)
    T = 1.0 - 0.02 * (inside if sample_right else 1.0 - inside) + rng.normal(0.0, 0.005, x.shape)
    found, right, level = one_edge(x, T, blur_um=8.4, pixel_um=PIXEL_UM)
    assert right is sample_right
    assert found == pytest.approx(edge, abs=2.0)
    assert level == pytest.approx(1.0, abs=3 * 0.005 / math.sqrt(20))


def test_one_edge_of_a_transparent_stack_and_its_placement():
    """A nearly transparent stack (0.3 %, below the 0.5 % noise) shows its edge by refraction
    spikes (gain outside, loss inside, 0.2 over 5 µm): found within a pixel. The estimate
    places the stack on it: on the scene's face nearest to it, the outer edge while the scene's
    centre is off by less than half the outer layer, the o | Al face where the scene puts that
    face nearer."""
    rng = np.random.default_rng(6)
    x = -574.0 + (np.arange(60) + 0.5) * PIXEL_UM
    edge = -500.3
    T = np.where(x > edge, 0.997, 1.0) + rng.normal(0.0, 0.005, x.shape)
    T[(x < edge) & (x > edge - 5)] += 0.2
    T[(x > edge) & (x < edge + 5)] -= 0.2
    found, _, _ = one_edge(x, T, blur_um=8.4, pixel_um=PIXEL_UM)
    assert found == pytest.approx(edge, abs=PIXEL_UM)
    layers = (fwdfit.Layer("o", 40.0, 3.5, 12.0), fwdfit.Layer("Al", 920.0, 2.078, 1.39),
              fwdfit.Layer("o2", 40.0, 3.5, 12.0))
    profile = fwdfit.Profile("edge", 1.1, "l46", "", x, T=T)
    for centre, face_um in ((0.0, 0.0), (15.0, 0.0), (-15.0, 0.0), (-70.0, 40.0)):
        scene = fwdfit.Scene(fwdfit.Sample(depth_mm=2.0, tilt_deg=0.0, centre_um=centre, layers=layers),
                             {"": fwdfit.Instrument("circular", 40.0, 5.5, PIXEL_UM)},
                             {"l46": fwdfit.GaussianLine(4.6, 0.15)}, (profile,),
                             fwdfit.FitSpec(("sample.centre_um",), {}))
        free = free_parameters(scene)
        start = estimate_starts(scene, free, [T], fwdfit.build_model(scene, free=[p.name for p in free]))
        assert start.values["sample.centre_um"] == pytest.approx(found - face_um + 500.0, abs=1e-9)


def test_outer_edges_without_a_sample():
    """Open beam only: no edges."""
    T = 1.0 + np.random.default_rng(2).normal(0.0, 0.005, 500)
    assert outer_edges(np.arange(500) * PIXEL_UM, T, 8.0, PIXEL_UM) is None


def test_attenuation_inverts_the_spectrum_average():
    """mu from a spectrum-averaged plateau: sum(w exp(-(mu + c) d)) = T solved for mu."""
    weight = np.array([0.2, 0.5, 0.3])
    offsets = np.array([1.0, 2.5, 4.0])  # 1/m, e.g. 1/v absorption at three wavelengths
    for mu in (0.5, 9.06, 150.0):
        plateau = float(np.sum(weight * np.exp(-(mu + offsets) * 2e-3)))
        assert attenuation_from_plateau(plateau, weight, 2000.0, offsets) == pytest.approx(mu, rel=1e-9)


# --------------------------------------------------------------------------- solver


def test_levenberg_marquardt_solves_many_problems_at_once():
    """An exponential decay y = a exp(-b t) + c, noise-free, from four starts at once: the
    best reaches (a, b, c) to 1e-6 with a Jacobian close to the exact one there; starts that come within
    one standard error of a better one stop early (merged), unconverged."""
    t = np.linspace(0.0, 4.0, 60)
    truth = np.array([2.0, 1.3, 0.5])
    data = truth[0] * np.exp(-truth[1] * t) + truth[2]

    def residuals(rows):
        return rows[:, :1] * np.exp(-rows[:, 1:2] * t) + rows[:, 2:3] - data

    starts = np.array([[1.0, 0.5, 0.0], [3.0, 2.5, 1.0], [0.5, 1.0, 0.8], [2.2, 1.1, 0.4]])
    solution = levenberg_marquardt(residuals, starts, np.ones(3), tolerance=1e-8, max_steps=200)
    best = int(np.argmin(solution.chi2))
    assert solution.converged[best]
    np.testing.assert_allclose(solution.u[best], truth, atol=1e-6)
    assert solution.chi2[best] < 1e-12
    exact = np.stack([np.exp(-truth[1] * t), -truth[0] * t * np.exp(-truth[1] * t), np.ones_like(t)], axis=1)
    np.testing.assert_allclose(solution.jacobian[best], exact, atol=1e-2)  # Broyden-updated
    merged = ~solution.converged
    assert merged.any() and np.all(solution.steps[merged] < solution.steps[best])


def test_levenberg_marquardt_holds_coordinates_of_typical_scale_zero():
    """A coordinate with typical scale 0 stays exactly where it starts, the others reach the
    least-squares optimum given it (a, c of y = a exp(-b t) + c with b held at 1.0: a linear
    fit), and the Jacobian column of the held coordinate costs no evaluation."""
    t = np.linspace(0.0, 4.0, 60)
    data = 2.0 * np.exp(-1.3 * t) + 0.5
    rows_seen = []

    def residuals(rows):
        rows_seen.append(len(rows))
        return rows[:, :1] * np.exp(-rows[:, 1:2] * t) + rows[:, 2:3] - data

    solution = levenberg_marquardt(residuals, np.array([[1.0, 1.0, 0.0]]), np.array([1.0, 0.0, 1.0]),
                                   tolerance=1e-8, max_steps=100)
    assert solution.u[0, 1] == 1.0
    design = np.stack([np.exp(-t), np.ones_like(t)], axis=1)
    expected, *_ = np.linalg.lstsq(design, data, rcond=None)
    np.testing.assert_allclose(solution.u[0, [0, 2]], expected, atol=1e-7)
    assert max(rows_seen) == 2  # difference Jacobians: two columns, not three


def test_levenberg_marquardt_survives_failing_evaluations():
    """Trial points where the model gives NaN are rejected, not accepted: sqrt model."""
    t = np.linspace(1.0, 3.0, 20)
    data = np.sqrt(0.3 * t)

    def residuals(rows):
        with np.errstate(invalid="ignore"):
            return np.sqrt(rows[:, :1] * t) - data

    solution = levenberg_marquardt(residuals, np.array([[2.0]]), np.ones(1), tolerance=1e-9, max_steps=100)
    assert solution.u[0, 0] == pytest.approx(0.3, rel=1e-7)


def test_levenberg_marquardt_floor_stops_within_a_share_of_the_typical_step():
    """Rich data (residuals / 1e-4, standard errors ~1e-4 of a typical step): with floor 0.1
    the solve stops once no step exceeds 0.1 typical steps, in fewer evaluations than the
    tolerance alone needs, within 0.1 typical steps of the optimum; floor 0 reaches it to 1e-7."""
    t = np.linspace(0.0, 4.0, 60)
    truth = np.array([2.0, 1.3, 0.5])
    data = truth[0] * np.exp(-truth[1] * t) + truth[2]
    counted = []

    def residuals(rows):
        counted.append(len(rows))
        return (rows[:, :1] * np.exp(-rows[:, 1:2] * t) + rows[:, 2:3] - data) / 1e-4

    start, typical = np.array([[1.0, 0.8, 0.0]]), np.ones(3)
    exact = levenberg_marquardt(residuals, start, typical, tolerance=0.3, max_steps=200)
    exact_rows, counted[:] = sum(counted), []
    floored = levenberg_marquardt(residuals, start, typical, tolerance=0.3, max_steps=200, floor=0.1)
    np.testing.assert_allclose(exact.u[0], truth, atol=1e-7)
    assert np.max(np.abs(floored.u[0] - truth)) < 0.1
    assert floored.converged[0] and sum(counted) < exact_rows


# --------------------------------------------------------------------------- quality gate


def test_runs_statistic():
    """Alternating signs: many runs (positive z); two long blocks: few runs (negative z)."""
    assert runs_z(np.tile([1.0, -1.0], 50)) > 5
    assert runs_z(np.r_[np.ones(50), -np.ones(50)]) < -5
    assert runs_z(np.ones(10)) == 0.0


def _profile_residuals(rng, n=600):
    x = -720.0 + np.arange(n) * PIXEL_UM
    return x, rng.normal(0.0, 1.0, n)


def test_quality_gate_accepts_noise_and_rejects_a_misfit():
    """Pure noise over three profiles passes; 2 sigma of systematic misfit over 40 pixels
    inside the sample (10 % of its width) fails, and the one line names the profile and
    the region there."""
    rng = np.random.default_rng(3)
    profiles = [_profile_residuals(rng) for _ in range(3)]
    faces = [[(-500.0, -495.0, "vacuum | Al"), (500.0, 505.0, "Al | vacuum")]] * 3
    names = ["a", "b", "c"]
    verdict = assess(names, [x for x, _ in profiles], [z for _, z in profiles], faces, [20.0] * 3, 5)
    assert verdict.passed, verdict.summary()
    x, z = profiles[1]
    bad = z.copy()
    bad[(x > 100) & (x < 196)] += 2.0
    verdict = assess(names, [p[0] for p in profiles], [profiles[0][1], bad, profiles[2][1]], faces,
                     [20.0] * 3, 5)
    assert not verdict.passed
    line = verdict.summary()
    assert "profile b" in line and "inside Al" in line, line


def test_quality_gate_tolerates_a_few_sharp_pixels():
    """Three pixels 3 sigma off, of both signs, at an edge (finest fringes) do not fail."""
    rng = np.random.default_rng(4)
    x, z = _profile_residuals(rng)
    z[np.searchsorted(x, 500.0) + np.array([0, 1, 2])] += np.array([3.0, -3.0, 3.0])
    faces = [[(-500.0, -495.0, "vacuum | Al"), (500.0, 505.0, "Al | vacuum")]]
    assert assess(["a"], [x], [z], faces, [20.0], 5).passed


# --------------------------------------------------------------------------- cache and missing starts


def test_cache_dir_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("FWDFIT_CACHE_DIR", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c"
    for off in ("off", "", "0"):
        monkeypatch.setenv("FWDFIT_CACHE_DIR", off)
        assert cache_dir() is None
        assert fwdfit.enable_compilation_cache() is None
    monkeypatch.delenv("FWDFIT_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "fwdfit"


def _scene_without_starts(path: Path, vary) -> Path:
    """The small Al scene with thickness_um and mu_per_m left out (NaN), ``vary`` free."""
    scene = small_scene({"sample.centre_um": 0.0, "layers.Al.thickness_um": math.nan,
                         "layers.Al.sld_e6_per_A2": 2.078}, vary=vary)
    layer = dataclasses.replace(scene.sample.layers[0], mu_per_m=math.nan)
    return fwdfit.save_scene(dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, layers=(layer,))),
                             path)


def test_free_values_may_have_no_start(tmp_path, capsys):
    """thickness_um and mu_per_m left out: allowed when [fit] vary names them (NaN: the fit
    estimates them), refused by simulate with one line, and refused when not varied."""
    path = _scene_without_starts(tmp_path / "scene.toml", ["layers.Al.thickness_um", "layers.Al.mu_per_m"])
    layer = fwdfit.load_scene(path).sample.layers[0]
    assert math.isnan(layer.thickness_um) and math.isnan(layer.mu_per_m)
    assert layer.sld_e6_per_A2 == 2.078
    from fwdfit.cli import main

    assert main(["simulate", str(path), "--out", str(tmp_path / "out")]) == 1
    line = capsys.readouterr().err.strip()
    assert line.startswith("fwdfit: error:") and "thickness_um is missing" in line, line
    assert not (tmp_path / "out").exists()
    _scene_without_starts(path, ["layers.Al.mu_per_m"])
    with pytest.raises(fwdfit.FwdfitError, match="thickness_um: missing"):
        fwdfit.load_scene(path)


def _open_beam_line_scene(tmp_path, accuracy: float = fwdfit.Scene.accuracy) -> Path:
    """A one-profile Al scene on a 500-pixel open-beam line, its thickness free."""
    rows = np.column_stack([fwdfit.pixel_grid(-600.0, 600.0, PIXEL_UM), np.ones(500), np.full(500, 0.01)])
    np.savetxt(tmp_path / "line.csv", rows, delimiter=",", header="x_um,T,T_err", comments="")
    scene = small_scene({"sample.centre_um": 0.0, "layers.Al.thickness_um": 1000.0, "layers.Al.sld_e6_per_A2": 2.078},
                        file=tmp_path / "line.csv", vary=["layers.Al.thickness_um"])
    return fwdfit.save_scene(dataclasses.replace(scene, accuracy=accuracy), tmp_path / "scene.toml")


def test_compiled_model_is_kept_between_runs(tmp_path):
    """With the cache on, a second Fitter of the same geometry loads the stored program
    (no tracing, no compilation) and predicts the same numbers to the last bit; a damaged
    stored program is compiled anew."""
    path = _open_beam_line_scene(tmp_path)
    before = jax.config.jax_compilation_cache_dir
    try:
        fwdfit.enable_compilation_cache(tmp_path / "cache")
        forget_compiled()  # this process's compiled programs: the second Fitter must load the stored one
        first = fwdfit.Fitter(path)
        stored = list((tmp_path / "cache" / "fwdfit-programs").glob("*.xla"))
        assert len(stored) == len(first.model.groups) == 1
        forget_compiled()
        second = fwdfit.Fitter(path)
        values = np.array([[990.0], [1010.0]])
        np.testing.assert_array_equal(first.predict(values)[0], second.predict(values)[0])
        assert second.compile_time_s < first.compile_time_s
        # a third Fitter of the geometry in this process (a Dask worker's next image) reuses the program
        third = fwdfit.Fitter(path)
        assert all(a is b for a, b in zip(third.predict.programs, second.predict.programs, strict=True))
        np.testing.assert_array_equal(third.predict(values)[0], first.predict(values)[0])
        # a damaged stored program (a full disk, another jaxlib's) is compiled anew, or served by
        # JAX's persistent cache when that holds it, and the damaged file is not read again:
        # the next run loads a working program
        stored[0].write_bytes(b"not an executable")
        forget_compiled()
        fourth = fwdfit.Fitter(path)
        np.testing.assert_array_equal(fourth.predict(values)[0], first.predict(values)[0])
        assert not stored[0].exists() or stored[0].read_bytes() != b"not an executable"
        forget_compiled()
        fifth = fwdfit.Fitter(path)
        assert fifth.predict.program_sources == ["loaded"]
        np.testing.assert_array_equal(fifth.predict(values)[0], first.predict(values)[0])
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_changed_code_does_not_load_programs_another_code_stored(tmp_path):
    """The stored programs are keyed by fwdfit's source as well as its version: a copy of
    the package with one line added to the model (a checkout between releases; the model sits in
    a subfolder, model/block/, which the key covers like the top folder) compiles
    and stores a program of its own instead of loading the one the installed code stored;
    the installed code, run again, loads its own (nothing new stored)."""
    path = _open_beam_line_scene(tmp_path)
    installed = Path(fwdfit.__file__).parent
    changed = tmp_path / "changed" / "fwdfit"
    shutil.copytree(installed, changed, ignore=shutil.ignore_patterns("__pycache__"))
    model_source = changed / "model" / "block" / "_model.py"
    model_source.write_text(model_source.read_text() + "\n# a changed line\n")
    probe = ("import sys, jax; jax.config.update('jax_enable_x64', True); import fwdfit; "
             "fwdfit.enable_compilation_cache(sys.argv[2]); fwdfit.Fitter(sys.argv[1])")
    stored = tmp_path / "cache" / "fwdfit-programs"
    counts = []
    for source in (installed.parent, changed.parent, installed.parent):
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(source), os.environ.get("PYTHONPATH", "")])}
        subprocess.run([sys.executable, "-c", probe, str(path), str(tmp_path / "cache")], env=env, check=True,
                       cwd=tmp_path)
        counts.append(len(list(stored.glob("*.xla"))))
    assert counts == [1, 2, 2]


def test_programs_per_group_predict_the_model_in_scene_order():
    """The Predictor's programs (one per group of profiles) put their rows back in the
    scene's order: profiles of one plan that are not neighbours in the scene (ICON, BOA,
    ICON) come out as the whole model in one program computes them, with norm and
    background applied."""
    from fwdfit.inference import Predictor, assembler, free_parameters

    example = Path(__file__).resolve().parents[1] / "examples" / "al_block" / "scene.toml"
    scene = fwdfit.load_scene(example)
    profiles = {p.name: p for p in scene.profiles}
    order = ("icon_l2.7A", "boa_d01.1mm", "icon_l4.6A")
    scene = dataclasses.replace(scene, accuracy=0.01, profiles=tuple(
        dataclasses.replace(profiles[name], norm=1.0 + 0.01 * i, background=0.001 * i)
        for i, name in enumerate(order)))
    free = free_parameters(scene, ["sample.tilt_deg", "layers.Al.thickness_um"], None)
    model = fwdfit.build_model(scene, free=[p.name for p in free], tilt_range_deg=(0.0, 0.3))
    assert sorted(group.index for group in model.groups) == [(0, 2), (1,)]
    assemble = assembler(scene, free)
    values = np.array([[0.2, 990.0], [0.25, 1005.0]])
    T, T_att = Predictor(model, assemble, len(free))(values)

    def whole(v):
        params, norm, background = assemble(v)
        return model.flat(params, norm, background)

    for row, v in zip(range(2), values):
        expected = jax.jit(whole)(v)
        np.testing.assert_allclose(T[row], expected[0], rtol=0, atol=1e-13)
        np.testing.assert_allclose(T_att[row], expected[1], rtol=0, atol=1e-13)
    assert T.shape == (2, sum(len(profiles[name].x_um) for name in order))


def test_a_group_evaluated_in_chunks_equals_its_profiles_alone():
    """A group's profiles are evaluated in chunks on a CPU (a scan over vmapped chunks, the
    last padded with copies): seven BOA distances whose plans put five near ones (two per
    chunk, one padded) and two far ones (one per chunk) in groups give, profile for
    profile, what each profile's model alone gives (a one-profile group: one vmap)."""
    example = Path(__file__).resolve().parents[1] / "examples" / "al_block" / "scene.toml"
    scene = fwdfit.load_scene(example)
    boa = next(p for p in scene.profiles if p.spectrum == "white")
    distances = (3.6, 4.0, 4.4, 4.8, 5.0, 23.3, 27.0)
    scene = dataclasses.replace(scene, profiles=tuple(
        dataclasses.replace(boa, name=f"d{d}", distance_mm=d, file=None) for d in distances))
    free = ["sample.tilt_deg", "layers.Al.thickness_um"]
    build = lambda s: fwdfit.build_model(s, free=free, tilt_range_deg=(-1.0, 1.0))
    joint = build(scene)
    assert sorted(len(group.index) for group in joint.groups) == [2, 5]
    params = fwdfit.initial_params(dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, tilt_deg=0.24)))
    flat = eqx.filter_jit(lambda model, params: model.flat(params))
    T, T_att = flat(joint, params)
    n = len(boa.x_um)
    for i, profile in enumerate(scene.profiles):
        alone = dataclasses.replace(scene, profiles=(profile,))
        expected = flat(build(alone), fwdfit.initial_params(
            dataclasses.replace(alone, sample=dataclasses.replace(alone.sample, tilt_deg=0.24))))
        np.testing.assert_allclose(T[i * n:(i + 1) * n], expected[0], rtol=0, atol=1e-12, err_msg=profile.name)
        np.testing.assert_allclose(T_att[i * n:(i + 1) * n], expected[1], rtol=0, atol=1e-12, err_msg=profile.name)


_SHARDED_PROBE = """
import sys, jax, numpy as np
jax.config.update("jax_enable_x64", True)
import fwdfit
from fwdfit.inference import Predictor
fitter = fwdfit.Fitter(sys.argv[1])
values = np.array([[990.0], [995.0], [1000.0], [1005.0], [1010.0]])
single = fitter.predict(values)
sharded = Predictor(fitter.model, fitter.assemble, 1, rows_per_call=3, devices=jax.devices())
spread = sharded.programs[0].input_shardings[0][1].device_set
both = sharded(values)
print(len(jax.devices()), sharded.rows_per_call, len(spread),
      max(float(np.max(np.abs(a - b))) for a, b in zip(single, both)))
"""


def test_rows_are_sharded_across_devices(tmp_path):
    """On two devices (two host devices forced, as on a machine with two accelerators) a
    call's rows are split between them (rows per call rounded up to a multiple of 2) and
    the predictions equal the one-device program's to rounding."""
    path = _open_beam_line_scene(tmp_path, accuracy=0.01)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               FWDFIT_CACHE_DIR="off")
    done = subprocess.run([sys.executable, "-c", _SHARDED_PROBE, str(path)], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    devices, per_call, spread, difference = done.stdout.split()[-4:]
    assert (int(devices), int(per_call), int(spread)) == (2, 4, 2)
    assert float(difference) < 1e-12
