"""Analytic limits of the forward model: Beer-Lambert, conservation, symmetry, invariances,
and gradients against central differences.

Models are built once per module and varied through their parameters where the physics
allows (tilt, distance, mu, SLD are ModelParams fields), because each new model shape
costs a few seconds of compilation. Kernel windows are sized from the scene's tilt, so
scenes are written with the largest tilt a test evaluates.
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import fwdfit
from fwdfit import ReferenceLayer, trace_reference
from helpers import (al_layer, boa_spectrum, central_difference, free_layer_parameters, make_scene,
                     oxide_layer, random_weights, replace_params, rms, spectrum_average_transmission,
                     stack_scene, straight_ray_profile, weighted_value, weighted_value_and_grad,
                     white_beam, write_scene)

BOA = dict(aperture="square", aperture_mm=40.0, aperture_distance_m=7.5)
ICON = dict(aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5)
WHITE = white_beam()
LINE = fwdfit.GaussianLine(4.6, 0.15)
PIXEL_UM = 2.4


def _run(model, params):
    T, T_att = eqx.filter_jit(model)(params)
    return [np.asarray(t) for t in T], [np.asarray(t) for t in T_att]


# --------------------------------------------------------------------------- no refraction

# A strongly and wavelength-dependently attenuating block without refraction.
MU0, MU1 = 60.0, 20.0  # 1/m, 1/m/Å: exp(-mu d) from 0.86 (0.8 Å) to 0.54 (10 Å)
BL_PROFILES = [("d01.1mm", 1.1, -672.0, 672.0), ("d34.4mm", 34.4, -1200.0, 1200.0)]


@pytest.fixture(scope="module")
def no_sld(tmp_path_factory):
    """(scene, {tilt_deg: (T list, T_att list)}) for an SLD = 0 block, BOA, tilts 0 and 0.5°."""
    block = fwdfit.Layer("B", 1000.0, 0.0, MU0, MU1)
    scene = write_scene(tmp_path_factory.mktemp("nosld"), [block], profiles=BL_PROFILES,
                        spectrum=WHITE, tilt_deg=0.5, **BOA)
    model, params = fwdfit.build_model(scene), fwdfit.initial_params(scene)
    return scene, {tilt: _run(model, replace_params(params, tilt_deg=tilt)) for tilt in (0.0, 0.5)}


def _edge_pixels(profile, tilt_deg):
    """Pixels where some ray crosses a side face of the 1000 µm block: within half the
    penumbra + the depth's sideways extent (2 mm x (tilt + half-divergence)) + 10 µm of
    an edge. Elsewhere every ray misses the block or crosses its full depth."""
    margin = (0.5 * profile.distance_mm * 1e3 * 40.0 / 7500.0
              + 2000.0 * math.tan(math.radians(abs(tilt_deg)) + 20.0 / 7500.0) + 10.0)
    return np.abs(np.abs(profile.x_um) - 500.0) < margin


def _exact_straight(profile, tilt_deg, x_um=None):
    """Brute-force straight-ray profile (``helpers.straight_ray_profile``) at x_um."""
    lam, weight = boa_spectrum()
    return straight_ray_profile(profile.x_um if x_um is None else x_um, PIXEL_UM,
                                thickness_um=1000.0, mu_per_m=MU0, mu_per_m_per_A=MU1,
                                depth_mm=2.0, tilt_deg=tilt_deg, centre_um=0.0,
                                distance_mm=profile.distance_mm, lam=lam, weight=weight, **BOA)


def _compare_with_straight_rays(profile, T, tilt_deg, atol):
    """Max |T - exact| over the edge pixels (brute force) and over the rest, where the exact
    value is 1 outside and, under the block, the brute-force value of the centre pixel."""
    edge = _edge_pixels(profile, tilt_deg)
    exact = np.ones_like(T)
    exact[edge] = _exact_straight(profile, tilt_deg, profile.x_um[edge])
    under = (np.abs(profile.x_um) < 500.0) & ~edge
    exact[under] = _exact_straight(profile, tilt_deg, np.array([0.0]))[0]
    assert edge.sum() > 20 and under.sum() > 100
    np.testing.assert_allclose(T, exact, rtol=0, atol=atol)
    return exact


def test_no_refraction_T_equals_T_att(no_sld):
    """With every SLD zero no interface refracts: T and T_att are the same numbers."""
    _, runs = no_sld
    for T, T_att in runs.values():
        for t, a in zip(T, T_att):
            assert np.array_equal(t, a)
            assert t.min() < 0.8  # the block is there


def test_untilted_block_is_beer_lambert(no_sld):
    """Untilted: T = spectrum average of exp(-mu(lambda) d) under the block, 1 far outside,
    and at the edges the straight-ray profile blurred by the penumbra Delta * D / L and
    integrated over pixels. The reference is computed by brute force in NumPy
    (``helpers.straight_ray_profile``: every ray's path length through the block, 24
    points per pixel x 600 over the aperture). Measured max differences 7.6e-5 (1.1 mm)
    and 3.5e-5 (34.4 mm); 3.4e-5 of it is the bulk value, from the model's wavelength
    quadrature of the white beam (the spectrum average itself is exact to ~1e-7 here)."""
    scene, runs = no_sld
    T_all, _ = runs[0.0]
    lam, weight = boa_spectrum()
    inside = spectrum_average_transmission(lam, weight, MU0, MU1, 2000.0)[0]
    for profile, T in zip(scene.profiles, T_all):
        x = profile.x_um
        penumbra = profile.distance_mm * 1e3 * 40.0 / 7500.0
        bulk = np.abs(x) < 500.0 - penumbra - 10.0
        outside = np.abs(x) > 500.0 + penumbra + 10.0
        np.testing.assert_allclose(T[bulk], inside, rtol=0, atol=5e-5)
        np.testing.assert_allclose(T[outside], 1.0, rtol=0, atol=1e-12)
        _compare_with_straight_rays(profile, T, 0.0, atol=1.5e-4)


def test_tilted_block_is_beer_lambert_along_tilted_paths(no_sld):
    """Tilted by 0.5° (more than the 2.7 mrad half-divergence): across the 17 µm where rays
    cross a side face, the transmission follows the partial path length through the
    tilted block. Compared with the brute-force straight-ray profile: max difference
    below 1.5e-3 and RMS below 2e-4 at the default accuracy (measured 1.04e-3 / 1.0e-4
    at 1.1 mm, from the depth quadrature; see the convergence test)."""
    scene, runs = no_sld
    T_all, _ = runs[0.5]
    for profile, T in zip(scene.profiles, T_all):
        exact = _compare_with_straight_rays(profile, T, 0.5, atol=1.5e-3)
        assert rms(T - exact) < 2e-4


def test_tilted_beer_lambert_converges(tmp_path):
    """At accuracy 1e-5 the tilted no-refraction profile at 1.1 mm matches the brute-force
    straight-ray profile to 5e-5 (measured 1.6e-5; 1.0e-3 at the default 1e-3): the
    default's error is quadrature, not physics."""
    block = fwdfit.Layer("B", 1000.0, 0.0, MU0, MU1)
    scene = write_scene(tmp_path, [block], profiles=BL_PROFILES[:1], spectrum=WHITE,
                        tilt_deg=0.5, **BOA)
    (T,), _ = _run(fwdfit.build_model(scene, accuracy=1e-5), fwdfit.initial_params(scene))
    _compare_with_straight_rays(scene.profiles[0], T, 0.5, atol=5e-5)


def test_straight_ray_reference_agrees_with_tracer(no_sld):
    """The brute-force straight-ray profile used above agrees with the exact Monte Carlo
    tracer (SLD 0, 4e5 rays, tilt 0.5°, 1.1 mm) within 4 sigma of the tracer's batch
    error + 2e-4 in every pixel near the left edge, and so does the model (+ 1.5e-3)."""
    scene, runs = no_sld
    profile = scene.profiles[0]
    near = (profile.x_um > -560) & (profile.x_um < -440)
    x = profile.x_um[near]
    lam, weight = boa_spectrum()
    ref = trace_reference([ReferenceLayer(1000.0, 0.0, MU0, MU1)], depth_mm=2.0, tilt_deg=0.5,
                          centre_um=0.0, distance_mm=profile.distance_mm, spectrum_lambda_A=lam,
                          spectrum_weight=weight, pixel_edges_um=np.append(x - 1.2, x[-1] + 1.2),
                          n_rays=400_000, seed=3, **BOA)
    assert np.array_equal(ref.T, ref.T_att)
    exact = _exact_straight(profile, 0.5, x)
    model = runs[0.5][0][0][near]
    assert np.all(np.abs(exact - ref.T) < 4 * ref.T_err + 2e-4)
    assert np.all(np.abs(model - ref.T) < 4 * ref.T_err + 1.5e-3)
    assert ref.T.min() < 0.8 and ref.T.max() == 1.0


# --------------------------------------------------------------------------- conservation, symmetry

_O2, _O1 = oxide_layer("o2", 80.0, 3.518, 12.0), oxide_layer("o1", 160.0, 3.304, 24.0)
OXIDE5 = [_O2, _O1, al_layer(mu=1.39, mu_per_A=0.774), _O1.tied("o1r"), _O2.tied("o2r")]
WIDE = [("wide", 34.4, -1500.0, 1500.0)]  # holds every deflected ray up to 34.4 mm
SETUPS = {
    "boa_al": ([al_layer(mu=9.059, mu_per_A=0.774)], WHITE, BOA),
    "icon_al": ([al_layer(mu=9.059, mu_per_A=0.774)], LINE, ICON),
    "boa_oxide5": (OXIDE5, WHITE, BOA),
}


@pytest.fixture(scope="module")
def wide_models(tmp_path_factory):
    """{setup: (model, params)} on a +-1500 µm grid symmetric about the centre, windows for
    0.5° and 34.4 mm (smaller distances and tilts are parameter values)."""
    folder = tmp_path_factory.mktemp("wide")
    out = {}
    for name, (layers, spectrum, geometry) in SETUPS.items():
        scene = write_scene(folder, layers, name=f"{name}.toml", profiles=WIDE, spectrum=spectrum,
                            tilt_deg=0.5, **geometry)
        out[name] = fwdfit.build_model(scene), fwdfit.initial_params(scene)
    return out


@pytest.mark.parametrize("setup", list(SETUPS))
def test_no_absorption_conserves_intensity(wide_models, setup):
    """mu = 0: refraction and reflection only move intensity, so sum (T - 1) * pixel = 0.

    For distances 1.1, 8.5, 34.4 mm and tilts 0, 0.24, 0.5°: |sum| < 1e-6 µm while the
    displaced intensity (half of sum |T - 1| * pixel) is 1.8 to 11 µm; measured |sum| below
    3e-14 µm (the kernels are differences of cumulative masses, so every quadrature node
    conserves exactly when its window holds all its rays; the BOA kernels' sub-windows, sized
    for 34.4 mm, must hold them from 1.1 mm on too). T_att is 1 everywhere."""
    model, params = wide_models[setup]
    assert setup == "icon_al" or model.groups[0].sub_window  # sized for 34.4 mm, used from 1.1 mm on
    zeros = np.zeros_like(np.asarray(params.mu_per_m))
    for distance in (1.1, 8.5, 34.4):
        for tilt in (0.0, 0.24, 0.5):
            p = replace_params(params, mu_per_m=zeros, mu_per_m_per_A=zeros, tilt_deg=tilt,
                               distance_mm=[distance])
            (T,), (T_att,) = _run(model, p)
            assert np.max(np.abs(T_att - 1.0)) < 1e-12
            moved = 0.5 * np.sum(np.abs(T - 1.0)) * PIXEL_UM
            assert moved > 1.0, (distance, tilt)
            assert abs(np.sum(T - 1.0) * PIXEL_UM) < 1e-6, (distance, tilt)


@pytest.mark.parametrize("setup", list(SETUPS))
def test_untilted_symmetric_stack_is_symmetric(wide_models, setup):
    """Untilted mirror-symmetric stack (Al block; five-layer oxide) on a grid symmetric about
    the centre: T(x) = T(-x) and T_att(x) = T_att(-x) to 1e-9 (measured 3e-14), at 1.1, 8.5
    and 34.4 mm."""
    model, params = wide_models[setup]
    for distance in (1.1, 8.5, 34.4):
        (T,), (T_att,) = _run(model, replace_params(params, tilt_deg=0.0, distance_mm=[distance]))
        assert np.max(np.abs(T - T[::-1])) < 1e-9
        assert np.max(np.abs(T_att - T_att[::-1])) < 1e-9
        assert T.max() > 1.01  # there are edge peaks to compare


@pytest.mark.parametrize("setup", list(SETUPS))
def test_tilt_sign_mirrors_the_profile(wide_models, setup):
    """A symmetric stack tilted by +phi is the mirror image of the one tilted by -phi:
    T(x; phi) = T(-x; -phi) to 1e-9, for phi = 0.24° and 0.5° at 1.1 and 34.4 mm. Checks that
    both crossing directions of both faces see the tilt with the right sign; the tilted
    profile itself is asymmetric by > 0.01."""
    model, params = wide_models[setup]
    for distance in (1.1, 34.4):
        for tilt in (0.24, 0.5):
            (T_plus,), _ = _run(model, replace_params(params, tilt_deg=tilt, distance_mm=[distance]))
            (T_minus,), _ = _run(model, replace_params(params, tilt_deg=-tilt, distance_mm=[distance]))
            assert np.max(np.abs(T_plus - T_minus[::-1])) < 1e-9
            assert np.max(np.abs(T_plus - T_plus[::-1])) > 0.01


# --------------------------------------------------------------------------- invariances


@pytest.fixture(scope="module")
def icon_al(wide_models):
    model, params = wide_models["icon_al"]
    return _run(model, replace_params(params, tilt_deg=0.24, distance_mm=[8.5]))


def _icon_variant(tmp_path, layers, free=()):
    scene = write_scene(tmp_path, layers, profiles=WIDE, spectrum=LINE, tilt_deg=0.5, **ICON)
    params = replace_params(fwdfit.initial_params(scene), tilt_deg=0.24, distance_mm=[8.5])
    return _run(fwdfit.build_model(scene, free=free), params)


def test_split_block_and_empty_layer_change_nothing(tmp_path, icon_al):
    """Al 1000 µm == Al 400 µm | oxide 0 µm | Al 600 µm (tilted 0.24°, 8.5 mm, ICON 4.6 Å):
    an interface without contrast and a zero-thickness layer leave T and T_att unchanged
    to 1e-10."""
    layers = [al_layer("A1", 400.0, mu=9.059, mu_per_A=0.774), oxide_layer("ox", 0.0, 3.518, 12.0),
              al_layer("A2", 600.0, mu=9.059, mu_per_A=0.774)]
    (T,), (T_att,) = _icon_variant(tmp_path, layers)
    (T_ref,), (T_att_ref,) = icon_al
    np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(T_att, T_att_ref, rtol=0, atol=1e-10)


def test_zero_contrast_kernel_changes_nothing(tmp_path, icon_al):
    """oxide 0 µm | Al 400 | Al 600 with the first Al's SLD and mu free: the no-contrast
    interface keeps its refraction kernel (evaluated at k = 0, no attenuation step), which
    must add nothing: T and T_att equal the plain block's to 1e-10 (measured 1e-16)."""
    layers = [oxide_layer("ox", 0.0, 3.518, 12.0), al_layer("A1", 400.0, mu=9.059, mu_per_A=0.774),
              al_layer("A2", 600.0, mu=9.059, mu_per_A=0.774)]
    (T,), (T_att,) = _icon_variant(tmp_path, layers, free=("layers.A1.sld_e6_per_A2",
                                                           "layers.A1.mu_per_m"))
    (T_ref,), (T_att_ref,) = icon_al
    np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(T_att, T_att_ref, rtol=0, atol=1e-10)


# --------------------------------------------------------------------------- gradients

# Central-difference steps per field: small enough that no isolated kink of the profile
# falls inside (+-h), large enough for float64 rounding (a random functional of
# 1083 pixels of T and T_att is ~10; roundoff ~1e-15 * 10 / h).
STEPS = {"thickness_um": 1e-4, "sld_e6_per_A2": 1e-6, "mu_per_m": 1e-4, "mu_per_m_per_A": 1e-4,
         "tilt_deg": 1e-6, "centre_um": 1e-4, "depth_mm": 1e-7, "distance_mm": 1e-6, "shift_um": 1e-4}
GRADIENT_RTOL = 1e-4


def test_gradients_match_central_differences(tmp_path):
    """jax gradient of a random linear functional of (T, T_att) against central differences,
    every component of every ModelParams field, float64.

    The five-layer stack (BOA white beam, 34.4 mm) at tilt 0.3°, centre 7.3 µm, shift 2.1 µm
    and mu_per_m_per_A != 0. Steps are ~1e-7 relative: the model is smooth between isolated
    kinks (where the critical angle of a wavelength node meets the end of a fan), and such
    steps do not straddle one. Tolerance: |fd - grad| <= 1e-4 * max(|grad|, 1e-3 * max|grad of field|);
    the largest relative error is printed (measured ~1e-7)."""
    scene = stack_scene(tmp_path)
    model = fwdfit.build_model(scene, free=free_layer_parameters(scene))
    params = replace_params(fwdfit.initial_params(scene), tilt_deg=0.3, centre_um=7.3,
                            shift_um=[2.1], mu_per_m_per_A=[0.5, 0.8, 0.774, 0.8, 0.5])
    weights = random_weights(scene, jnp.float64, seed=1)
    (_, _), grads = weighted_value_and_grad(params, model, weights)
    worst = 0.0
    for field, h in STEPS.items():
        base = np.asarray(getattr(params, field))
        analytic = np.atleast_1d(np.asarray(getattr(grads, field)))
        scale = max(np.max(np.abs(analytic)), 1e-300)
        for i in range(analytic.size):
            def value(s, i=i):
                shifted = base.copy().ravel()
                shifted[i] += s
                return weighted_value(replace_params(params, **{field: shifted.reshape(base.shape)}),
                                      model, weights)

            fd = central_difference(value, 0.0, h)
            error = abs(fd - analytic[i]) / max(abs(analytic[i]), 1e-3 * scale)
            worst = max(worst, error)
            assert error <= GRADIENT_RTOL, (field, i, fd, analytic[i])
    print(f"gradient check: largest relative error {worst:.1e}")


def test_model_is_smooth_in_the_interface_positions(wide_models):
    """The stack moved sideways (centre_um 0.3 µm + 20 steps of h; five-layer oxide, BOA
    white beam, 12.2 mm, untilted): second differences of a random linear functional of T
    and T_att stay bounded as h shrinks from 0.04 to 0.004 µm, as for a C^1 function (max
    |second difference| within 1.5x; measured 0.035 and 0.034). A depth quadrature on fixed
    nodes makes the model piecewise linear, and its second differences grow like 1/h
    (measured with the earlier fixed-node quadrature: 0.47 and 4.1): the solver then stops
    at kinks. Here every edge's depth integral is split where its integrand kinks."""
    model, params = wide_models["boa_oxide5"]
    (T,), _ = _run(model, params)
    rng = np.random.default_rng(0)
    weights = ([jnp.asarray(rng.normal(size=T.size))], [jnp.asarray(rng.normal(size=T.size))])
    largest = {}
    for h in (0.04, 0.004):
        centres = 0.3 + h * np.arange(21)
        values = [float(weighted_value(replace_params(params, centre_um=c, tilt_deg=0.0, distance_mm=[12.2]),
                                       model, weights)) for c in centres]
        largest[h] = np.max(np.abs(np.diff(values, 2))) / h**2
    assert largest[0.004] < 1.5 * largest[0.04], largest
    assert largest[0.04] > 0  # the functional does see the stack move


# Tilt at which the kernel of the Al block's entering face is widest (BOA white beam to
# 10 Å): the aperture's grazing angles just reach the critical angle, so the totally
# reflected and the straight rays land furthest apart.
WIDEST_TILT_DEG = math.degrees(10.0 * math.sqrt(2.078e-6 / math.pi) + 20.0 / (7500.0 - 35.4))


def test_kernel_windows_hold_every_ray(tmp_path):
    """mu = 0 conserves intensity (|sum (T - 1) * pixel| < 1e-6 µm, of 4 to 9 µm displaced)
    at 34.4 mm for tilts 0, 0.24°, the widest-kernel tilt (±0.62°) and 1°: with windows
    sized for each tilt alone, and with one model whose tilt is free (windows for ±5°), and
    each wavelength's kernels on sub-windows of their own (``_model._sub_windows``).
    A window too narrow loses the rays outside it. Two depth nodes per piece (accuracy 5e-4):
    the kernels' crossing rays and the step assignment they replace are then integrated over the
    depth to 1e-12 alike; the default's one node there (``_plan._ONE_NODE_LOG_RATIO``) conserves
    to 5e-4 µm (1e-4 of what it displaces)."""
    scene = write_scene(tmp_path, [al_layer(mu=0.0)], profiles=[("d34.4mm", 34.4, -1500.0, 1500.0)],
                        spectrum=WHITE, tilt_deg=0.0, **BOA)
    params = fwdfit.initial_params(scene)
    free = fwdfit.build_model(scene, 5e-4, free=("sample.tilt_deg",))
    assert free.groups[0].sub_window and free.groups[0].straight_window  # the kernels' own sub-windows too
    for tilt in (0.0, 0.24, WIDEST_TILT_DEG, -WIDEST_TILT_DEG, 1.0):
        fixed = fwdfit.build_model(scene, 5e-4, tilt_range_deg=(tilt, tilt))
        for model in (fixed, free):
            (T,), _ = _run(model, replace_params(params, tilt_deg=tilt))
            assert 0.5 * np.sum(np.abs(T - 1.0)) * PIXEL_UM > 1.0, tilt
            assert abs(np.sum(T - 1.0) * PIXEL_UM) < 1e-6, (tilt, model is free)
        (T,), _ = _run(fwdfit.build_model(scene, tilt_range_deg=(tilt, tilt)), replace_params(params, tilt_deg=tilt))
        assert abs(np.sum(T - 1.0) * PIXEL_UM) < 1e-3, tilt


def test_one_depth_node_far_from_the_sample():
    """From a lever ratio of e^0.1 (21 mm for 2 mm of depth) the plan takes one depth node per
    piece where faces hardly absorb: the Al block at 0.24° on the ICON line with Fresnel
    reflection (the worst case measured) is then within 5e-4 RMS of the converged model (accuracy
    1e-4) in T and T_att at 21 and 34.4 mm; at 15 mm, or with mu x depth 0.5, it keeps two."""
    profiles = [("d21mm", 21.0, -800.0, 800.0), ("d34.4mm", 34.4, -1000.0, 1000.0)]
    scene = make_scene([al_layer(mu=9.06)], profiles=profiles, spectrum=LINE, tilt_deg=0.24, fresnel=True, **ICON)
    model = fwdfit.build_model(scene)
    assert {len(group.z_nodes) for group in model.groups} == {1}
    params = fwdfit.initial_params(scene)
    (T, T_att), (T_ref, T_att_ref) = _run(model, params), _run(fwdfit.build_model(scene, 1e-4), params)
    for values, converged in ((T, T_ref), (T_att, T_att_ref)):
        for got, want in zip(values, converged):
            assert rms(got - want) < 5e-4
    near = make_scene([al_layer()], profiles=[("d15mm", 15.0, -800.0, 800.0)], spectrum=LINE, **ICON)
    absorbing = make_scene([al_layer(mu=250.0)], profiles=profiles, spectrum=LINE, **ICON)
    for other in (near, absorbing):
        assert {len(group.z_nodes) for group in fwdfit.build_model(other).groups} == {2}


def test_a_window_over_one_edge_equals_the_whole_profile_there():
    """A 1 mm Al block seen through windows over its left edge only (BOA white beam, 1.1 and
    10 mm, tilt 0.2°; the right face's kernels reach none of their pixels and are skipped)
    gives the same T and T_att as windows over the whole block on the pixels they share."""
    narrow = make_scene([al_layer()], profiles=[("near", 1.1, -560.0, -440.0), ("far", 10.0, -620.0, -380.0)],
                        spectrum=white_beam(), tilt_deg=0.2)
    wide = make_scene([al_layer()], profiles=[("near", 1.1, -560.0, 640.0), ("far", 10.0, -620.0, 700.0)],
                      spectrum=white_beam(), tilt_deg=0.2)
    values = []
    for scene in (narrow, wide):
        T, T_att = eqx.filter_jit(lambda m, p: m(p))(fwdfit.build_model(scene), fwdfit.initial_params(scene))
        values.append([np.asarray(v)[:len(p.x_um)] for v, p in zip(T + T_att, 2 * narrow.profiles)])
    for a, b in zip(*values):
        assert np.max(np.abs(a - b)) < 1e-12, np.max(np.abs(a - b))
    assert min(np.min(v) for v in values[0]) < 0.99  # the edge is in the windows
