"""Fresnel partial reflection (``fresnel = true``) against independent references.

- The angular transfer (``_kernel.fresnel_transfer``) against a brute-force integral of
  R(a) q(a) a da on a fine grid, square and circular apertures, both signs of k.
- The model against the exact ray tracer with Fresnel reflection
  (``tests/data/raytrace_fresnel``, made by its ``make_reference.py``: BOA white beam
  and ICON lines, tilts 0 and 0.24°, 1.1 and 10 mm, an Al block and a Ti | Al pair whose
  inner interface has k < 0 one way and k > 0 the other): RMS of T - T_ref and of
  T_att - T_att_ref at most 0.002, per profile, default settings.
- The Fresnel signal itself: the tracer ran each profile twice with the same rays, with
  and without Fresnel reflection, so T_ref - T_sharp_ref is nearly noise-free; the
  model's T_fresnel - T_sharp must match it (RMS error at most 20 % of its RMS; measured
  0.8-1.7e-4 for signals of RMS 0.6-5.9e-3), and it must be visible (at least 0.005 in
  some pixel; measured 0.007-0.076). The model with Fresnel off matches the tracer without it.
- Hard cases with Fresnel on, float32 and float64: the steepest ray exactly at the
  critical angle and 1e-9 rad either side (continuous), zero SLD contrast; values and
  gradients finite; float64 forward-mode derivatives (what the fit's errors use) of SLD
  and tilt against central differences.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tomllib

import fwdfit
from fwdfit.model import APERTURES
from fwdfit.model import AngularMass, fresnel_transfer
from fwdfit.model import fresnel_nodes
from fwdfit.cli import main
from helpers import (DATA, al_layer, load_reference, random_weights, replace_params,
                     rms, weighted_value, weighted_value_and_grad, write_scene)

FRESNEL = DATA / "raytrace_fresnel"
RMS_TOLERANCE = 0.002
SIGNAL_RTOL = 0.2
SIGNAL_VISIBLE = 0.005


def _profile_names(path: Path) -> list[str]:
    with open(path, "rb") as stream:
        return [p["name"] for p in tomllib.load(stream)["profiles"]]


CASES = [(p.parent.name, name) for p in sorted(FRESNEL.glob("*/scene.toml")) for name in _profile_names(p)]
CASE_IDS = [f"{case}/{name}" for case, name in CASES]


def _without_fresnel(scene):
    instruments = {k: dataclasses.replace(v, fresnel=False) for k, v in scene.instruments.items()}
    return dataclasses.replace(scene, instruments=instruments)


# --------------------------------------------------------------------------- the angular transfer


GRAZINGS = (-3e-3, -1e-3, 1e-3, 4e-3)  # rad: edges left and right of the interface


def _brute_transfer(aperture, mass, k, tilt=0.0):
    """(loss, gain) of ``fresnel_transfer`` at ``GRAZINGS``, and the whole reflected mass,
    by the trapezoidal rule on 2e5 angles; tilt: a rough face's facet tilt (``mass.tilt``), at
    which rays of local angle a cross at the global angle a + tilt."""
    a = np.linspace(float(mass.a_min), float(mass.a_max), 200_001)
    cdf = np.asarray(APERTURES[aperture][0]((a - float(mass.offset)) / float(mass.half_width)))
    a2 = np.sqrt(np.maximum(a * a - k, 0.0))
    above = a * a > k
    reflected = np.where(above, ((a - a2) / np.where(above, a + a2, 1.0)) ** 2, 0.0) * np.gradient(cdf, a) * (a + tilt)
    loss = [np.trapezoid(reflected * (above & (a2 < g)), a) for g in GRAZINGS]
    gain = [np.trapezoid(reflected * (-a < g), a) for g in GRAZINGS]
    return np.array(loss), np.array(gain), np.trapezoid(reflected, a)


@pytest.mark.parametrize("aperture", ["square", "circular"])
@pytest.mark.parametrize("k", [1e-5, 4e-6, -1e-5])
@pytest.mark.parametrize("position_um", [0.0, 8000.0])
def test_transfer_matches_brute_force_integral(aperture, k, position_um):
    """Lost and gained masses within 2e-3 of the whole Fresnel-reflected mass for edges on
    both sides of the interface, with the default number of nodes (measured: exact to
    rounding for the square, 5e-4 for the circle)."""
    x, w = np.polynomial.legendre.leggauss(fresnel_nodes(1e-3, aperture))
    mass = AngularMass(aperture, position_um, 0.0, 7.5e6, 40_000.0)
    loss, gain, scale = _brute_transfer(aperture, mass, k)
    got = fresnel_transfer(mass, jnp.asarray(GRAZINGS), jnp.asarray(k), tuple(0.5 * (x + 1)), tuple(0.5 * w))
    np.testing.assert_allclose(np.asarray(got[0]), loss, rtol=0, atol=2e-3 * scale)
    np.testing.assert_allclose(np.asarray(got[1]), gain, rtol=0, atol=2e-3 * scale)
    assert scale > 0 or position_um == 0.0 and k > 0  # every ray is totally reflected there


@pytest.mark.parametrize("aperture, atol", [("square", 1e-4), ("circular", 2e-3)])
@pytest.mark.parametrize("k", [1e-5, -1e-5])
@pytest.mark.parametrize("tilt", [8e-4, -8e-4])
def test_transfer_at_a_tilted_facet_matches_brute_force_integral(aperture, atol, k, tilt):
    """A rough face's facet tilted by +-0.8 mrad (rays cross at their global angle): lost and
    gained masses (at local grazing angles) within ``atol`` of the whole reflected mass; the square aperture's closed
    form is exact (its two-node rule was 1e-4 off), the circle's nodes as untilted."""
    x, w = np.polynomial.legendre.leggauss(fresnel_nodes(1e-3, aperture))
    mass = AngularMass(aperture, 12_000.0, 0.0, 7.5e6, 40_000.0, jnp.asarray(tilt))  # partly above critical
    loss, gain, scale = _brute_transfer(aperture, mass, k, tilt)
    got = fresnel_transfer(mass, jnp.asarray(GRAZINGS), jnp.asarray(k), tuple(0.5 * (x + 1)), tuple(0.5 * w))
    assert scale > 0
    np.testing.assert_allclose(np.asarray(got[0]), loss, rtol=0, atol=atol * scale)
    np.testing.assert_allclose(np.asarray(got[1]), gain, rtol=0, atol=atol * scale)


def test_transfer_total_is_k_over_12():
    """A square fan from grazing 0 to far above the critical angle: the Fresnel-reflected
    mass is q |k| / 12 (q the angular density), the paraxial closed form
    int_c^inf R a da = k / 12 less the tail above the fan, (k / 8)(v - v^3 / 3) at
    v = k / (a + a2)^2 ~ 1e-5 here."""
    k = 1e-9
    mass = AngularMass("square", 20_000.0, 0.0, 7.5e6, 40_000.0)  # the fan's edge at grazing 0
    assert float(mass.a_min) == 0.0 and float(mass.a_max) > 100 * math.sqrt(k)
    x, w = np.polynomial.legendre.leggauss(fresnel_nodes(1e-3, "square"))
    _, gain = fresnel_transfer(mass, jnp.asarray(1.0), jnp.asarray(k), tuple(0.5 * (x + 1)), tuple(0.5 * w))
    a_max = float(mass.a_max)
    v = k / (a_max + math.sqrt(a_max**2 - k)) ** 2
    q = 1.0 / (2.0 * float(mass.half_width))
    expected = q * k / 8 * ((1 - 1 / 3) - (v - v**3 / 3))
    assert float(gain) == pytest.approx(expected, rel=1e-9)
    assert expected == pytest.approx(q * k / 12, rel=1e-4)


# --------------------------------------------------------------------------- against the tracer


@pytest.fixture(scope="module")
def predictions():
    """``predictions(case)`` -> (scene, {profile: (T, T_att, T_sharp)}), each scene run once."""
    cache = {}

    def get(case):
        if case not in cache:
            scene = fwdfit.load_scene(FRESNEL / case / "scene.toml")
            params = fwdfit.initial_params(scene)
            T, T_att = eqx.filter_jit(fwdfit.build_model(scene))(params)
            T_sharp, _ = eqx.filter_jit(fwdfit.build_model(_without_fresnel(scene)))(params)
            cache[case] = scene, {p.name: tuple(np.asarray(v) for v in values)
                                  for p, *values in zip(scene.profiles, T, T_att, T_sharp)}
        return cache[case]

    return get


def _reference(case, name):
    ref = load_reference(FRESNEL / case, name)
    ref["T_sharp"] = np.loadtxt(FRESNEL / case / f"{name}.csv", delimiter=",", skiprows=1)[:, 5]
    return ref


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_transmission_rms(predictions, case, name):
    """RMS(T - T_ref) and RMS(T_att - T_att_ref) at most 0.002, Fresnel on."""
    scene, result = predictions(case)
    ref = _reference(case, name)
    (profile,) = [p for p in scene.profiles if p.name == name]
    np.testing.assert_allclose(profile.x_um, ref["x_um"], rtol=0, atol=1e-6)
    T, T_att, _ = result[name]
    print(f"{case}/{name}: RMS T {rms(T - ref['T']):.5f} T_att {rms(T_att - ref['T_att']):.5f}")
    assert rms(T - ref["T"]) <= RMS_TOLERANCE
    assert rms(T_att - ref["T_att"]) <= RMS_TOLERANCE
    assert T_att.min() < 0.999


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_fresnel_signal(predictions, case, name):
    """T - T_sharp: visible (max |.| >= 0.005) and within 20 % RMS of the tracer's; Fresnel
    off matches the tracer without Fresnel to 0.002 RMS."""
    _, result = predictions(case)
    ref = _reference(case, name)
    T, _, T_sharp = result[name]
    signal, signal_ref = T - T_sharp, ref["T"] - ref["T_sharp"]
    error = rms(signal - signal_ref)
    print(f"{case}/{name}: Fresnel signal RMS {rms(signal_ref):.5f} (max {np.abs(signal_ref).max():.4f}), "
          f"model error {error:.5f}")
    assert np.abs(signal_ref).max() >= SIGNAL_VISIBLE
    assert error <= SIGNAL_RTOL * rms(signal_ref)
    assert rms(T_sharp - ref["T_sharp"]) <= RMS_TOLERANCE


# --------------------------------------------------------------------------- hard cases

# Al block through a 1 mm square aperture at 7.5 m (half-divergence 67 µrad), 4 Å line of
# relative FWHM 1e-3, 1.1 mm: the steepest ray meets the face at the critical angle at the
# tilt below.
THETA_C = 4.0 * math.sqrt(2.078e-6 / math.pi)
CRITICAL_TILT_DEG = math.degrees(THETA_C - 0.5 * 1.0 / 7500.0)
HARD_CASES = {"untilted": {"tilt_deg": 0.0},
              "critical": {"tilt_deg": CRITICAL_TILT_DEG},
              "critical_minus": {"tilt_deg": CRITICAL_TILT_DEG - math.degrees(1e-9)},
              "critical_plus": {"tilt_deg": CRITICAL_TILT_DEG + math.degrees(1e-9)},
              "zero_contrast": {"tilt_deg": 0.1, "sld_e6_per_A2": [2.078, 2.078]}}
FIELDS = ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A", "tilt_deg", "centre_um",
          "depth_mm", "distance_mm", "shift_um")


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
    """``hard(case, precision)`` -> (T, T_att, grads); one Fresnel scene of two layers (Ti | Al
    unless the case says otherwise), every layer parameter free."""
    folder = tmp_path_factory.mktemp("fresnel_hard")
    scene = write_scene(folder, [al_layer("Ti", 400.0, sld=-1.925, mu=60.0), al_layer("Al", 600.0)],
                        tilt_deg=CRITICAL_TILT_DEG, aperture="square", aperture_mm=1.0,
                        aperture_distance_m=7.5, fresnel=True, profiles=[("d01.1mm", 1.1, -720.0, 720.0)],
                        spectrum=fwdfit.GaussianLine(4.0, 1e-3))
    free = [f"layers.{l.name}.{key}" for l in scene.sample.layers
            for key in ("thickness_um", "sld_e6_per_A2", "mu_per_m")]
    cache, built = {}, {}

    def get(case, precision):
        if (case, precision) not in cache:
            with jax.enable_x64(precision == "float64"):
                dtype = jnp.dtype(precision)
                if precision not in built:
                    built[precision] = (fwdfit.build_model(scene, free=free),
                                        fwdfit.initial_params(scene, dtype=dtype), random_weights(scene, dtype))
                model, params, weights = built[precision]
                params = replace_params(params, **HARD_CASES[case])
                (_, (T, T_att)), grads = weighted_value_and_grad(params, model, weights)
                assert T[0].dtype == dtype
                cache[case, precision] = (np.asarray(T[0], float), np.asarray(T_att[0], float),
                                          {f: np.asarray(getattr(grads, f), float) for f in FIELDS},
                                          (model, params, weights))
        return cache[case, precision]

    return get


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_cases_finite(hard, case, precision):
    """T, T_att and the gradient of a random functional finite for every field, Fresnel on;
    float32 within 1e-3 of float64."""
    T, T_att, grads, _ = hard(case, precision)
    assert np.all(np.isfinite(T)) and np.all(np.isfinite(T_att))
    rounding = 2e-5 if precision == "float32" else 0.0  # a total-reflection shadow reaches T ~ 0
    assert T.min() >= -rounding and T.max() > 1.001  # an edge signal
    for field in FIELDS:
        assert np.all(np.isfinite(grads[field])), field
    for field in ("sld_e6_per_A2", "tilt_deg"):
        assert np.any(grads[field] != 0.0), field
    if precision == "float32":
        assert np.max(np.abs(T - hard(case, "float64")[0])) <= 1e-3


def test_continuous_through_the_critical_angle(hard):
    """1e-9 rad either side of the critical configuration moves T by < 1e-5 (as the sharp
    model's test; measured 4e-6): no jump where the Fresnel reflectivity meets 1."""
    T = [hard(case, "float64")[0] for case in ("critical_minus", "critical", "critical_plus")]
    assert np.max(np.abs(T[0] - T[1])) < 1e-5 and np.max(np.abs(T[2] - T[1])) < 1e-5


@pytest.mark.parametrize("field, h", [("sld_e6_per_A2", 1e-6), ("tilt_deg", 1e-6)])
def test_derivatives_match_central_differences(hard, field, h):
    """Fresnel on, tilt 0.1°: the jitted forward- and reverse-mode derivatives of a random
    functional of (T, T_att) against central differences, relative 1e-4 (as the sharp
    model's test). The Ti | Al pair's Al faces reflect every ray of their fans there, so that
    their clipped angles coincide: reverse mode was 26 % off in the tilt before
    ``_kernel._clip`` (measured now: 3e-15 from forward mode)."""
    _, _, _, (model, params, weights) = hard("untilted", "float64")
    params = replace_params(params, tilt_deg=0.1)
    base = np.asarray(getattr(params, field))
    reverse = np.asarray(getattr(weighted_value_and_grad(params, model, weights)[1], field))

    def value(shift):
        return weighted_value(replace_params(params, **{field: base + shift}), model, weights)

    for i in range(base.size):
        direction = np.zeros(base.shape)
        direction.ravel()[i] = 1.0
        derivative = float(eqx.filter_jit(lambda d: jax.jvp(value, (jnp.zeros(base.shape),), (d,))[1])(
            jnp.asarray(direction)))
        fd = (float(value(h * direction)) - float(value(-h * direction))) / (2 * h)
        assert abs(fd - derivative) <= 1e-4 * abs(derivative), (i, fd, derivative)
        assert abs(fd - reverse.ravel()[i]) <= 1e-4 * abs(derivative), (i, fd, reverse.ravel()[i])


# --------------------------------------------------------------------------- the commands


def test_simulate_command_on_a_fresnel_scene(tmp_path, capsys):
    """``fwdfit simulate`` accepts ``fresnel = true`` (it was refused) and writes its T, which
    differs from the same scene without Fresnel by the signal checked above."""
    out = tmp_path / "out"
    scene_path = FRESNEL / "al_boa_tilt0.24" / "scene.toml"
    assert main(["simulate", str(scene_path), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    ref = _reference("al_boa_tilt0.24", "d01.1mm")
    table = np.loadtxt(out / "d01.1mm.csv", delimiter=",", skiprows=1)
    assert rms(table[:, 1] - ref["T"]) <= RMS_TOLERANCE
    assert rms(table[:, 1] - ref["T_sharp"]) > 2 * rms(table[:, 1] - ref["T"])


FIT_TRUTH = {"sample.tilt_deg": 0.24, "sample.centre_um": 0.0, "layers.Al.thickness_um": 1000.0,
             "layers.Al.sld_e6_per_A2": 2.078}
FIT_ERROR = 0.002  # T_err given to the tracer's profiles (their own noise is ~4e-4)


STARTS = {"natural": {"tilt_deg = 0.24": "tilt_deg = 0.0", "thickness_um = 1000": "thickness_um = 900",
                     "sld_e6_per_A2 = 2.078": "sld_e6_per_A2 = 2.5"},
          "none": {"tilt_deg = 0.24\n": "", "centre_um = 0.0\n": "", "thickness_um = 1000\n": "",
                   "sld_e6_per_A2 = 2.078\n": ""}}


@pytest.mark.slow
@pytest.mark.parametrize("start", list(STARTS))
def test_fit_command_recovers_the_tracer_truth(tmp_path, capsys, start):
    """``fwdfit fit`` of the tracer's Fresnel profiles (BOA, 0.24°, 1.1 and 10 mm) with
    ``fresnel = true``, from a user's natural first guess (tilt 0, 900 µm, SLD 2.5) and with
    the free start values deleted: tilt within 0.02°, thickness within 2 µm, centre within
    1 µm, SLD within 5 % (the tolerances of test_fit.py), chi2/dof below 1 (T_err 0.002 is
    5x the tracer's noise; measured 0.2402°, 999.99 µm, 0.001 µm, 2.0787). The block absorbs
    0.3 %: its edges are found from the refraction spikes (before, the natural guess ended
    at chi2/dof 19 and the missing starts in a traceback)."""
    case = FRESNEL / "al_boa_tilt0.24"
    text = (case / "scene.toml").read_text()
    for name in _profile_names(case / "scene.toml"):
        ref = _reference("al_boa_tilt0.24", name)
        rows = np.column_stack([ref["x_um"], ref["T"], np.full_like(ref["T"], FIT_ERROR)])
        np.savetxt(tmp_path / f"{name}.csv", rows, delimiter=",", fmt="%.9g", header="x_um,T,T_err", comments="")
        text = re.sub(r"x_min_um = \S+\nx_max_um = \S+", f'file = "{name}.csv"', text, count=1)
    assert text.count("file = \"d") == 2
    for old, new in STARTS[start].items():
        assert old in text
        text = text.replace(old, new, 1)
    text += "\n[fit]\nvary = [" + ", ".join(f'"{k}"' for k in FIT_TRUTH) + "]\n"
    (tmp_path / "scene.toml").write_text(text)
    shutil.copy(case / "spectrum_boa.csv", tmp_path)
    assert main(["fit", str(tmp_path / "scene.toml"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    fitted = {name: entry["value"] for name, entry in result["parameters"].items()}
    print(fitted, result["chi2_reduced"])
    assert abs(fitted["sample.tilt_deg"] - 0.24) < 0.02
    assert abs(fitted["layers.Al.thickness_um"] - 1000.0) < 2.0
    assert abs(fitted["sample.centre_um"]) < 1.0
    assert fitted["layers.Al.sld_e6_per_A2"] == pytest.approx(2.078, rel=0.05)
    assert result["chi2_reduced"] < 1.0
