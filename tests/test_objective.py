"""The inference seams: one objective (residuals and log-likelihood) behind every consumer,
the local solver passed in, and the sample's geometry behind its own interface.

Data: the small Al scene's own model at a known truth (tilt 0.15°) plus 1 % Gaussian noise."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import numpy as np
import pytest

import fwdfit
from fwdfit.inference import LayeredBlock, Objective, levenberg_marquardt
from helpers import small_scene

TRUTH = {"sample.centre_um": 3.0, "layers.Al.thickness_um": 1000.0, "layers.Al.sld_e6_per_A2": 2.078}
VARY = ["sample.tilt_deg", "sample.centre_um", "layers.Al.thickness_um"]
TILT_DEG = 0.15
NOISE = 0.01


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("objective")
    truth = _tilted(small_scene(TRUTH), TILT_DEG)
    (profile,) = fwdfit.simulate(truth)
    T = profile.T + np.random.default_rng(3).normal(0.0, NOISE, profile.T.shape)
    np.savetxt(folder / "line.csv", np.c_[profile.x_um, T, np.full_like(T, NOISE)], delimiter=",",
               header="x_um,T,T_err", comments="")
    start = dict(TRUTH, **{"sample.centre_um": 0.0, "layers.Al.thickness_um": 980.0})
    return fwdfit.save_scene(_tilted(small_scene(start, file=folder / "line.csv", vary=VARY), 0.0),
                             folder / "scene.toml")


def _tilted(scene, tilt_deg):
    return dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, tilt_deg=tilt_deg))


@pytest.fixture(scope="module")
def fitter(scene_path):
    return fwdfit.Fitter(scene_path)


@pytest.fixture(scope="module")
def default_fit(fitter):
    return fitter()


def test_log_likelihood_is_the_gaussian_density_of_the_data(fitter):
    """log L = sum of log N(T | T_model, sigma): against the density written out per pixel,
    at two points; the JAX function (the sampler's) gives the same value, and its gradient
    matches central differences of the host values."""
    objective = fitter.objective()
    assert isinstance(objective, Objective)
    values = np.array([[TILT_DEG, 3.0, 1000.0], [0.1, 2.0, 1003.0]])
    T_model, _ = fitter.predict(values)
    density = -0.5 * ((objective.T - T_model) / objective.sigma) ** 2 - np.log(np.sqrt(2 * np.pi) * objective.sigma)
    np.testing.assert_allclose(objective.log_likelihood(values), density.sum(axis=1), rtol=1e-12)

    traced = objective.jax_log_likelihood()
    value_and_grad = eqx.filter_jit(lambda model, assemble, v: jax.value_and_grad(lambda w: traced(model, assemble, w))(v))
    value, grad = value_and_grad(fitter.model, fitter.assemble, jax.numpy.asarray(values[1]))
    assert float(value) == pytest.approx(objective.log_likelihood(values[1:])[0], rel=1e-10)
    steps = np.array([1e-5, 1e-3, 1e-3])
    central = [(objective.log_likelihood(values[1] + np.eye(3)[j] * steps[j])[0]
                - objective.log_likelihood(values[1] - np.eye(3)[j] * steps[j])[0]) / (2 * steps[j]) for j in range(3)]
    np.testing.assert_allclose(np.asarray(grad), central, rtol=1e-4)


def test_the_local_solver_is_passed_in(scene_path, default_fit):
    """Fitter(solver=...) uses the solver it is given: a wrapper around the default sees
    every local solve (rows of n_free unconstrained coordinates) and gives the default's
    result, which recovers the truth."""
    calls = []

    def recording(residual_rows, u, typical, **options):
        calls.append(u.shape)
        return levenberg_marquardt(residual_rows, u, typical, **options)

    result = fwdfit.Fitter(scene_path, solver=recording)()
    assert calls and all(shape[1] == len(VARY) for shape in calls)
    np.testing.assert_allclose(result.values, default_fit.values, rtol=0, atol=0)
    assert abs(result["layers.Al.thickness_um"][0] - 1000.0) < 3 * result["layers.Al.thickness_um"][1] + 0.5
    assert abs(result["sample.tilt_deg"][0] - TILT_DEG) < 3 * result["sample.tilt_deg"][1] + 0.005
    assert 0.8 < result.chi2_reduced < 1.2


class _RecordingBlock(LayeredBlock):
    """The layered block, recording which of the geometry's methods the fit called."""

    def __init__(self):
        self.called = set()

    def __getattribute__(self, name):
        if name in ("build_model", "check_data", "estimate", "at_tilts", "interfaces"):
            object.__getattribute__(self, "called").add(name)
        return object.__getattribute__(self, name)


def test_the_fit_reaches_the_shape_through_the_geometry(scene_path, default_fit):
    """Every shape-specific step of a fit (model, data check, starts, the scan's tilts, the quality gate's
    edge regions) goes through the geometry passed in; the layered block's edge regions lie
    where the tilted faces project: centre -+ t / (2 cos tilt), moved by distance x tan(tilt)."""
    geometry = _RecordingBlock()
    result = fwdfit.Fitter(scene_path, geometry=geometry)()
    assert geometry.called == {"build_model", "check_data", "estimate", "at_tilts", "interfaces"}
    np.testing.assert_allclose(result.values, default_fit.values, rtol=0, atol=0)
    scene = result.scene
    faces, half_width_um = LayeredBlock().interfaces(scene, scene.profiles[0])
    tilt, t, c = np.radians(scene.sample.tilt_deg), scene.sample.layers[0].thickness_um, scene.sample.centre_um
    slide = scene.profiles[0].distance_mm * 1e3 * np.tan(tilt)
    np.testing.assert_allclose([f[:2] for f in faces], [[c - t / 2 / np.cos(tilt), c - t / 2 / np.cos(tilt) + slide],
                                                        [c + t / 2 / np.cos(tilt), c + t / 2 / np.cos(tilt) + slide]])
    assert [f[2] for f in faces] == ["vacuum | Al", "Al | vacuum"] and half_width_um > 0
