"""Rough faces (RMS slope of the local normal) and graded layers against independent references.

- The model against the exact ray tracer with the same physics (``tests/data/raytrace_rough``,
  made by its ``make_reference.py``): an Al block whose faces have RMS normal slopes of 0.5 and
  2 mrad (ICON line at 0.24°, BOA white beam at 0°, 1.1 and 10 mm; Fresnel reflection on, and
  off on the same rays), and a coating graded in SLD and mu on Al traced as 50 sublayers:
  RMS of T - T_ref and of T_att - T_att_ref at most 0.002, default settings. The sharp model
  is far off the rough references (the roughness is seen).
- Roughness 0 is the sharp model (to 1e-10) on the rough code path, and its derivative in the
  roughness is finite and continuous there; a graded layer with equal ends is the uniform one.
- float32 and float64: finite values and gradients with every term on (rough, Fresnel, graded).
- Fits of the tracer's rough profiles recover the slope within 20 % (slow).
"""

from __future__ import annotations

import dataclasses
import math
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fwdfit
from fwdfit.scene import FitSpec, dump_scene, load_scene
from helpers import DATA, rms, load_reference, random_weights, replace_params, weighted_value, weighted_value_and_grad

ROUGH = DATA / "raytrace_rough"
RMS_TOLERANCE = 0.002
CASES = [(case, p.name) for case in ("rough0.5_icon", "rough2_icon", "rough2_boa", "graded") if (ROUGH / case / "scene.toml").exists()
         for p in load_scene(ROUGH / case / "scene.toml").profiles]
CASE_IDS = [f"{case}/{name}" for case, name in CASES]


def _with(scene, *, fresnel=None, roughness_mrad=None):
    """The scene with Fresnel reflection set and/or every face's roughness replaced."""
    if fresnel is not None:
        scene = dataclasses.replace(scene, instruments={k: dataclasses.replace(v, fresnel=fresnel)
                                                        for k, v in scene.instruments.items()})
    if roughness_mrad is not None:
        layers = tuple(dataclasses.replace(l, roughness_mrad=roughness_mrad) for l in scene.sample.layers)
        scene = dataclasses.replace(scene, sample=dataclasses.replace(
            scene.sample, layers=layers, left_roughness_mrad=roughness_mrad))
    return scene


def _simulate(scene):
    T, T_att = eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene))
    return {p.name: (np.asarray(t), np.asarray(a)) for p, t, a in zip(scene.profiles, T, T_att)}


@pytest.fixture(scope="module")
def predictions():
    """``predictions(case, variant)`` -> {profile: (T, T_att)}: the scene as it is
    (``scene``), Fresnel off (``fresnel_off``) or sharp (``sharp``: roughness 0)."""
    cache = {}

    def get(case, variant="scene"):
        if (case, variant) not in cache:
            scene = load_scene(ROUGH / case / "scene.toml")
            scene = {"scene": scene, "fresnel_off": _with(scene, fresnel=False),
                     "sharp": _with(scene, roughness_mrad=0.0)}[variant]
            cache[case, variant] = _simulate(scene)
        return cache[case, variant]

    return get


def _reference(case, name):
    ref = load_reference(ROUGH / case, name)
    table = np.loadtxt(ROUGH / case / f"{name}.csv", delimiter=",", skiprows=1)
    if table.shape[1] > 5:
        ref["T_fresnel_off"] = table[:, 5]
    return ref


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_transmission_rms(predictions, case, name):
    """RMS(T - T_ref) and RMS(T_att - T_att_ref) at most 0.002 (rough cases: Fresnel on)."""
    T, T_att = predictions(case)[name]
    ref = _reference(case, name)
    errors = {"T": rms(T - ref["T"]), "T_att": rms(T_att - ref["T_att"])}
    print(f"{case}/{name}: RMS T {errors['T']:.5f}, T_att {errors['T_att']:.5f} "
          f"(tracer noise {rms(ref['T_err']):.5f})")
    assert max(errors.values()) <= RMS_TOLERANCE


@pytest.mark.slow
@pytest.mark.parametrize("case, name", [c for c in CASES if c[0] != "graded" and "d01.1mm" in c[1]],
                         ids=[i for i in CASE_IDS if not i.startswith("graded") and "d01.1mm" in i])
def test_rough_faces_without_fresnel_and_the_sharp_model(predictions, case, name):
    """Fresnel off against the tracer's run without Fresnel on the same rays: RMS at most
    0.002; the sharp model (roughness 0) at least twice as far off the 2 mrad references.
    (1.1 mm profiles only, for the suite's time: the 10 mm ones are checked with Fresnel on.)"""
    ref = _reference(case, name)
    off = rms(predictions(case, "fresnel_off")[name][0] - ref["T_fresnel_off"])
    print(f"{case}/{name}: RMS T fresnel off {off:.5f}")
    assert off <= RMS_TOLERANCE
    if case.startswith("rough2"):
        sharp = rms(predictions(case, "sharp")[name][0] - ref["T"])
        print(f"  sharp model {sharp:.5f}")
        assert sharp > 2 * rms(predictions(case)[name][0] - ref["T"])


def _near(scene):
    """The scene with its first profile (1.1 mm) only: cheap to compile."""
    return dataclasses.replace(scene, profiles=scene.profiles[:1])


def _free_rough_scene(roughness_mrad=0.0):
    """The ICON 2 mrad case at 1.1 mm with the given roughness, Fresnel on."""
    return _near(_with(load_scene(ROUGH / "rough2_icon" / "scene.toml"), roughness_mrad=roughness_mrad))


ROUGH_FREE = ("sample.left_roughness_mrad", "layers.Al.roughness_mrad")


def test_rough_landing_range_holds_every_ray():
    """A rough face's window bounds (``landing_range`` with ``tilt``) hold the outgoing angle of
    every ray at every normal tilt, traced ray by ray: straight from behind the facet (a' <= 0),
    totally reflected (t - a'), refracted (t + sqrt(a'^2 - k)), and with Fresnel reflection also
    reflected above the critical angle; with tilt 0 they hold the sharp face's range; and they are
    tight: the traced extremes reach them to within 2 % of the tilted range's width."""
    from fwdfit.model import landing_range

    rng = np.random.default_rng(16)
    for _ in range(200):
        offset, half_width = rng.uniform(-2e-3, 8e-3), rng.uniform(2.5e-3, 4e-3)  # some rays cross
        k, tilt, fresnel = rng.choice([-1, 1]) * rng.uniform(0, 1.5e-4), rng.uniform(0, 8e-3), bool(rng.integers(2))
        lo, hi = landing_range(offset, half_width, k, fresnel, xp=np, tilt=tilt)
        sharp = landing_range(offset, half_width, k, fresnel, xp=np)
        assert lo <= sharp[0] and hi >= sharp[1]
        a_min, a_max = max(offset - half_width, 0.0), max(offset + half_width, 0.0)
        a, t = (v.ravel() for v in np.meshgrid(np.linspace(a_min, a_max, 401), np.linspace(-tilt, tilt, 401)))
        local = a - t
        front = local > 0
        total = front & (local**2 < k)
        out = [a, np.where(front & ~total, t + np.sqrt(np.maximum(local**2 - k, 0.0)), a),
               np.where(total | (fresnel & front & (k != 0)), t - local, a)]
        out = np.concatenate(out)
        assert out.min() >= lo - 1e-12 and out.max() <= hi + 1e-12
        assert out.min() - lo <= 0.02 * (hi - lo) and hi - out.max() <= 0.02 * (hi - lo)


def test_landing_regions_hold_every_ray():
    """Each (tilt, wavelength) sample's sub-windows (``landing_regions``) hold the outgoing angle of
    every ray of their side, traced ray by ray at sharp and tilted facets: left of the facet's
    projection those reflected (totally, or partially with Fresnel reflection: any ray meeting the
    facet) and those meeting the facet from behind (straight on), right of it the refracted ones.
    The bounds are reached (within 1e-9 rad: the fan's ends, the ray along the facet and the
    critical ray are traced) and within the widths the plan sizes the sub-windows for: the fan
    on the left, sqrt(a'_max^2 - a'_min^2) on the right."""
    from fwdfit.model import landing_regions

    rng = np.random.default_rng(17)
    for _ in range(300):
        offset, half_width = rng.uniform(-2e-3, 8e-3), rng.uniform(2.5e-3, 4e-3)  # some rays cross
        k = rng.choice([-1, 1]) * rng.uniform(0, 1.5e-4)
        tilt = rng.choice([0.0, rng.uniform(-8e-3, 8e-3)])
        a_min, a_max = max(offset - half_width, 0.0), max(offset + half_width, 0.0)
        regions = landing_regions(a_min, a_max, k, tilt, xp=np)
        a = np.linspace(a_min, a_max, 2001)
        # the rays along the facet and at its critical angle (those leave along it)
        a = np.concatenate([a] + [[v] for v in (tilt, tilt + np.sqrt(max(k, 0.0))) if a_min < v < a_max])
        local = a - tilt
        front = local >= 0  # the ray along the facet on both sides: the limit of each
        refracted = front & (local**2 >= k - 1e-18)  # the critical ray, within rounding
        rays = (np.concatenate([a[local <= 0], (tilt - local)[front]]),
                tilt + np.sqrt(np.maximum(local**2 - k, 0.0))[refracted])
        for out, (lo, hi) in zip(rays, regions):
            if out.size:
                assert lo - 1e-12 <= out.min() <= lo + 1e-9 and hi - 1e-9 <= out.max() <= hi + 1e-12, (offset, k, tilt)
        front_lo, front_hi = max(a_min - tilt, 0.0), max(a_max - tilt, 0.0)
        assert regions[0][1] - regions[0][0] <= a_max - a_min + 1e-12
        if refracted.any():  # else it is the left one, for no ray
            assert regions[1][1] - regions[1][0] <= np.sqrt(front_hi**2 - front_lo**2) + 1e-12


def test_rough_kernel_windows_hold_every_ray():
    """mu = 0 conserves intensity with rough faces (2 and 5 mrad, Fresnel on, BOA white beam, 34.4 mm,
    tilts 0 and 0.5°): |sum (T - 1) * pixel| < 1e-6 µm of 2-5 µm displaced. The windows are set
    by the bounds of ``test_rough_landing_range_holds_every_ray`` and each sample's sub-windows
    by those of ``test_landing_regions_hold_every_ray``; a window too narrow loses rays. Two
    depth nodes per piece (accuracy 5e-4), as in ``test_model_limits.py``'s test of the sharp
    windows; the profile is wide enough for the 5 mrad kernels (±3 mm)."""
    base = _with(load_scene(ROUGH / "rough2_boa" / "scene.toml"), fresnel=True)
    block = dataclasses.replace(base.sample.layers[0], mu_per_m=0.0, mu_per_m_per_A=0.0)
    profile = dataclasses.replace(base.profiles[0], name="d34.4mm", distance_mm=34.4,
                                  x_um=np.arange(-2999.0, 3000.0, 2.4))
    for roughness, tilt in ((2.0, 0.0), (5.0, 0.5)):
        scene = _with(dataclasses.replace(base, profiles=(profile,), sample=dataclasses.replace(
            base.sample, layers=(block,), tilt_deg=tilt)), roughness_mrad=roughness)
        model = fwdfit.build_model(scene, 5e-4)
        assert model.groups[0].sub_window and model.groups[0].straight_window  # each sample on its sub-windows
        (T,), _ = eqx.filter_jit(model)(fwdfit.initial_params(scene))
        T = np.asarray(T)
        assert 0.5 * np.sum(np.abs(T - 1.0)) * 2.4 > 1.0
        assert abs(np.sum(T - 1.0) * 2.4) < 1e-6, (roughness, tilt)


@pytest.mark.slow
def test_zero_roughness_is_the_sharp_model():
    """Roughness 0 on the rough code path (a free roughness plans its faces rough) equals the
    sharp model to 1e-10; so does a graded layer whose ends are equal (graded code path)."""
    scene = _free_rough_scene(0.0)
    params = fwdfit.initial_params(scene)
    rough_model = fwdfit.build_model(scene, free=ROUGH_FREE)
    assert any(face.rough for face in rough_model.interfaces)
    sharp = eqx.filter_jit(fwdfit.build_model(scene))(params)[0]
    rough = eqx.filter_jit(rough_model)(params)[0]
    assert max(np.max(np.abs(np.asarray(a) - np.asarray(b))) for a, b in zip(rough, sharp)) <= 1e-10
    graded = _near(load_scene(ROUGH / "graded" / "scene.toml"))
    uniform = dataclasses.replace(graded, sample=dataclasses.replace(graded.sample, layers=tuple(
        dataclasses.replace(l, sld_end_e6_per_A2=math.nan, mu_end_per_m=math.nan) for l in graded.sample.layers)))
    equal_ends = dataclasses.replace(graded, sample=dataclasses.replace(graded.sample, layers=tuple(
        dataclasses.replace(l, sld_end_e6_per_A2=l.sld_e6_per_A2, mu_end_per_m=l.mu_per_m)
        for l in graded.sample.layers)))
    model = fwdfit.build_model(equal_ends)
    assert all(model.graded)
    a, b = _simulate(equal_ends), _simulate(uniform)
    assert max(np.max(np.abs(a[n][i] - b[n][i])) for n in a for i in (0, 1)) <= 1e-10


def test_roughness_derivative_is_continuous_at_zero():
    """The forward-mode derivative of a random functional in the roughness: finite at 0 and
    within 1 % (of its scale at 0.5 mrad) of its value at 1e-4 mrad; the model moves by less
    than 1e-6 for 1e-4 mrad."""
    scene = _free_rough_scene(0.0)
    model = fwdfit.build_model(scene, free=ROUGH_FREE)
    params = fwdfit.initial_params(scene)
    weights = random_weights(scene, jnp.float64)

    def value(sigma):
        return weighted_value(replace_params(params, left_roughness_mrad=sigma, roughness_mrad=[sigma]),
                              model, weights)

    slope = eqx.filter_jit(lambda s: jax.jvp(value, (s,), (jnp.ones(()),)))
    (v0, d0), (v1, d1), (_, d5) = (slope(jnp.asarray(s)) for s in (0.0, 1e-4, 0.5))
    assert np.isfinite(float(d0)) and abs(float(d5)) > 0
    assert abs(float(d1) - float(d0)) <= 0.01 * abs(float(d5))
    assert abs(float(v1) - float(v0)) <= 1e-6 * max(1.0, abs(float(v0)))


FIELDS = ("thickness_um", "sld_e6_per_A2", "mu_per_m", "roughness_mrad", "sld_end_e6_per_A2", "mu_end_per_m",
          "left_roughness_mrad", "tilt_deg", "centre_um", "distance_mm")


@pytest.mark.slow
def test_every_term_finite_in_both_precisions():
    """A rough (1 mrad), graded coating on a rough Al block, Fresnel on, every layer value
    free, at 1.1 mm: T, T_att and the reverse-mode gradient of a random functional finite in
    float32 and float64, float32 within 1e-3 of float64. Run in a child process: XLA's CPU
    compiler has crashed with a segmentation fault compiling this float32 gradient (twice on
    one machine, once before with the 10 mm profile: not resolved), which would take the test
    worker down with it; such a crash is reported as a skip naming the signal."""
    import subprocess
    import sys
    from pathlib import Path

    child = ("import jax; jax.config.update('jax_enable_x64', True); import test_rough; "
             "test_rough.check_every_term_finite_in_both_precisions()")
    run = subprocess.run([sys.executable, "-c", child], cwd=Path(__file__).parent, capture_output=True, text=True)
    if run.returncode < 0:
        pytest.skip(f"XLA's compiler crashed (signal {-run.returncode}) compiling the gradient")
    assert run.returncode == 0, run.stderr[-3000:]


def check_every_term_finite_in_both_precisions():
    """The body of ``test_every_term_finite_in_both_precisions``."""
    base = _near(load_scene(ROUGH / "graded" / "scene.toml"))
    scene = _with(base, fresnel=True, roughness_mrad=1.0)
    free = [f"layers.{l.name}.{k}" for l in scene.sample.layers
            for k in ("thickness_um", "sld_e6_per_A2", "mu_per_m", "roughness_mrad")]
    free += ["layers.coating.sld_end_e6_per_A2", "layers.coating.mu_end_per_m", "sample.left_roughness_mrad"]
    results = {}
    for precision in ("float64", "float32"):
        with jax.enable_x64(precision == "float64"):
            dtype = jnp.dtype(precision)
            model = fwdfit.build_model(scene, free=free)
            params = fwdfit.initial_params(scene, dtype=dtype)
            (_, (T, T_att)), grads = weighted_value_and_grad(params, model, random_weights(scene, dtype))
            assert T[0].dtype == dtype
        values = [np.asarray(t, float) for t in T + T_att]
        assert all(np.all(np.isfinite(v)) for v in values), precision
        for field in FIELDS:
            assert np.all(np.isfinite(np.asarray(getattr(grads, field), float))), (precision, field)
        assert np.any(np.asarray(grads.roughness_mrad) != 0) and np.any(np.asarray(grads.sld_end_e6_per_A2) != 0)
        results[precision] = values
    assert max(np.max(np.abs(a - b)) for a, b in zip(results["float32"], results["float64"])) <= 1e-3


def test_scene_keys_round_trip_and_validation(tmp_path):
    """The new keys read back field for field through dump_scene; a negative roughness is a
    one-line error naming the file, key and value."""
    scene = _with(load_scene(ROUGH / "graded" / "scene.toml"), roughness_mrad=0.7)
    scene = dataclasses.replace(scene, fit=FitSpec(vary=("layers.coating.sld_end_e6_per_A2",
                                                         "layers.Al.roughness_mrad")))
    path = tmp_path / "scene.toml"
    fwdfit.save_scene(scene, path)
    back = load_scene(path)
    assert back.sample.left_roughness_mrad == 0.7
    assert [l.roughness_mrad for l in back.sample.layers] == [0.7, 0.7]
    coating = back.sample.layers[0]
    assert (coating.sld_end_e6_per_A2, coating.mu_end_per_m) == (1.6, 120.0)
    assert math.isnan(back.sample.layers[1].sld_end_e6_per_A2)
    from fwdfit.inference import free_parameters

    names = [p.name for p in free_parameters(back)]
    assert names == ["layers.coating.sld_end_e6_per_A2", "layers.Al.roughness_mrad"]
    path.write_text(path.read_text().replace("roughness_mrad = 0.7", "roughness_mrad = -0.1", 1))
    with pytest.raises(fwdfit.FwdfitError, match=r"scene.toml: .*roughness_mrad.*-0.1"):
        load_scene(path)


# --------------------------------------------------------------------------- fits of the tracer's data

FIT_ERROR = 0.003  # Gaussian noise added to the tracer's profiles, and their T_err


def fit_tracer_profiles(case: str, vary: tuple[str, ...], start: dict[str, float], seed: int = 1,
                        scene=None):
    """Least-squares fit of ``vary`` to the tracer's profiles of ``case`` plus FIT_ERROR noise
    (``fwdfit.inference``: the compiled predictor and Levenberg-Marquardt, from ``start``;
    the profiles show one edge, so the whole-profile starts of ``fwdfit.fit`` do not apply).
    Returns ({name: value}, chi2 per degree of freedom)."""
    from fwdfit.inference import Predictor, assembler, free_parameters, levenberg_marquardt

    scene = scene or load_scene(ROUGH / case / "scene.toml")
    rng = np.random.default_rng(seed)
    data = np.concatenate([_reference(case, p.name)["T"] + rng.normal(0.0, FIT_ERROR, len(p.x_um))
                           for p in scene.profiles])
    free = free_parameters(dataclasses.replace(scene, fit=FitSpec(vary=vary)))
    predictor = Predictor(fwdfit.build_model(scene, free=vary), assembler(scene, free), len(free))
    residuals = lambda rows: (predictor(rows)[0] - data) / FIT_ERROR
    u0 = np.array([[start.get(p.name, p.value) for p in free]])
    typical = np.array([p.step for p in free])
    solution = levenberg_marquardt(residuals, u0, typical, tolerance=0.01, max_steps=60)
    best = int(np.argmin(solution.chi2))
    return dict(zip([p.name for p in free], solution.u[best])), solution.chi2[best] / (data.size - len(free))


@pytest.mark.slow
@pytest.mark.parametrize("case, truth", [("rough0.5_icon", 0.5), ("rough2_icon", 2.0)])
def test_fit_recovers_the_roughness(case, truth):
    """Tilt, centre, SLD and the visible face's roughness free, roughness started at 1 mrad
    (the other values 2 % or 0.02° off): the slope within 20 %, SLD within 5 %, tilt within
    0.02°, centre within 1 µm, chi2/dof below 1.5."""
    vary = ("sample.left_roughness_mrad", "sample.tilt_deg", "sample.centre_um", "layers.Al.sld_e6_per_A2")
    start = {"sample.left_roughness_mrad": 1.0, "sample.tilt_deg": 0.26, "sample.centre_um": 0.5,
             "layers.Al.sld_e6_per_A2": 2.12}
    values, chi2 = fit_tracer_profiles(case, vary, start)
    print(case, values, f"chi2/dof {chi2:.3f}")
    assert values["sample.left_roughness_mrad"] == pytest.approx(truth, rel=0.2)
    assert values["layers.Al.sld_e6_per_A2"] == pytest.approx(2.078, rel=0.05)
    assert abs(values["sample.tilt_deg"] - 0.24) <= 0.02 and abs(values["sample.centre_um"]) <= 1.0
    assert chi2 <= 1.5


@pytest.mark.slow
def test_graded_data_need_a_graded_layer():
    """The tracer's graded coating (50 sublayers) plus noise: a graded layer (both ends of SLD
    and mu free, started uniform at the mean values) reaches chi2/dof below 1.3 with its ends
    within 10 % of the truth; one uniform layer (SLD and mu free) cannot (chi2/dof above 3)."""
    graded = load_scene(ROUGH / "graded" / "scene.toml")
    coating = graded.sample.layers[0]
    mean = {"sld_e6_per_A2": 2.3, "mu_per_m": 260.0}
    uniform_layers = (dataclasses.replace(coating, sld_end_e6_per_A2=math.nan, mu_end_per_m=math.nan, **mean),
                      graded.sample.layers[1])
    uniform = dataclasses.replace(graded, sample=dataclasses.replace(graded.sample, layers=uniform_layers))
    keys = ("layers.coating.sld_e6_per_A2", "layers.coating.mu_per_m", "sample.centre_um")
    ends = ("layers.coating.sld_end_e6_per_A2", "layers.coating.mu_end_per_m")
    values, chi2 = fit_tracer_profiles("graded", keys + ends, {}, scene=uniform)
    _, chi2_uniform = fit_tracer_profiles("graded", keys, {}, scene=uniform)
    print(values, f"graded chi2/dof {chi2:.3f}, uniform {chi2_uniform:.3f}")
    assert chi2 <= 1.3 and chi2_uniform >= 3.0
    truth = {"layers.coating.sld_e6_per_A2": 3.0, "layers.coating.sld_end_e6_per_A2": 1.6,
             "layers.coating.mu_per_m": 400.0, "layers.coating.mu_end_per_m": 120.0}
    for name, value in truth.items():
        assert values[name] == pytest.approx(value, rel=0.1), name


def _oxide_every_term(roughness_mrad: float, distances_mm) -> fwdfit.Scene:
    """The five-layer oxide at these distances with every face rough and Fresnel reflection on."""
    scene = load_scene(DATA / "raytrace" / "oxide5_boa" / "scene.toml")
    layers = tuple(dataclasses.replace(layer, roughness_mrad=roughness_mrad) for layer in scene.sample.layers)
    scene = dataclasses.replace(
        scene, profiles=tuple(p for p in scene.profiles if p.distance_mm in distances_mm),
        instruments={k: dataclasses.replace(v, fresnel=True) for k, v in scene.instruments.items()},
        sample=dataclasses.replace(scene.sample, layers=layers, left_roughness_mrad=roughness_mrad))
    assert len(scene.profiles) == len(distances_mm)
    return scene


def test_slightly_rough_faces_meet_the_accuracy():
    """The five-layer oxide (BOA white beam, 1.1 and 34.4 mm) with every face at 0.5 mrad and
    Fresnel reflection on: the default model is within the default accuracy (1e-3 RMS in T) of
    the model converged in every node count (accuracy 1e-4). One stratum of the normal's tilt
    left it 0.0019 off at 1.1 mm; the plan takes at least two (0.0008 at 1.1 mm, 0.0006 at 34.4)."""
    scene = _oxide_every_term(0.5, (1.1, 34.4))
    evaluate = eqx.filter_jit(lambda model, params: model(params)[0])
    params = fwdfit.initial_params(scene)
    default, converged = (evaluate(fwdfit.build_model(scene, accuracy), params) for accuracy in (None, 1e-4))
    for T, T_converged in zip(default, converged):
        assert rms(np.asarray(T) - np.asarray(T_converged)) < 1e-3


def test_strata_meet_the_accuracy_at_2_mrad(monkeypatch):
    """The strata rule's count (strata x wavelength nodes, ``_plan._ROUGH_SAMPLES``) on the
    five-layer oxide at 12.2 mm with every face at 2 mrad, Fresnel reflection on, BOA white beam
    (4 strata of 16 wavelength nodes): within the default accuracy (1e-3 RMS in T; 9.2e-4 against
    48 strata) of the same model with 8x the strata; half as many are not (2 strata: 2.0e-3)."""
    plan = sys.modules[fwdfit.build_model.__module__]  # the plan's module, wherever it lives

    scene = _oxide_every_term(2.0, (12.2,))
    evaluate = eqx.filter_jit(lambda model, params: model(params)[0][0])
    params = fwdfit.initial_params(scene)
    default = fwdfit.build_model(scene)
    assert [group.rough_strata for group in default.groups] == [4]
    monkeypatch.setattr(plan, "_ROUGH_SAMPLES", 8 * plan._ROUGH_SAMPLES)
    many = fwdfit.build_model(scene)
    monkeypatch.setattr(plan, "_ROUGH_SAMPLES", 0.5 * plan._ROUGH_SAMPLES / 8)
    few = fwdfit.build_model(scene)
    assert [group.rough_strata for group in many.groups] == [32] and [g.rough_strata for g in few.groups] == [2]
    T_many = np.asarray(evaluate(many, params))
    assert rms(np.asarray(evaluate(default, params)) - T_many) < 1e-3
    assert rms(np.asarray(evaluate(few, params)) - T_many) > 1e-3
