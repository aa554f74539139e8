"""The hard cases of PHYSICS.md, in float32 and float64: finite, sane, differentiable.

Two compiled models carry the cases (compiling value-and-gradient costs ~10 s per model
and precision, so the cases are parameter values of shared models, not new scenes):

- ``stack``: a five-layer stack (oxide 80 | oxide 160 | Al 1000 | oxide 160 | oxide 80 µm),
  BOA white beam 0.8-10 Å, the largest distance Delta = 34.4 mm (a blur 75 pixels
  wide), built for tilt 0.5° and with every layer parameter free (so no interface is
  pruned). Cases: the stack itself; tilt 0.5° (8.7 mrad, larger than the 2.7 mrad
  half-divergence: each side face is hit from one side only); zero delta contrast
  between the 160 µm layers and Al (their kernels run at k = 0); zero-thickness 160 µm
  layers (two interfaces at one place); 2 µm layers (thinner than depth * |a|).
- ``narrow``: an Al block seen through a 1 mm aperture (half-divergence 67 µrad) with a
  4 Å line of relative FWHM 1e-3 at 1.1 mm: a refraction kernel narrower than a pixel.
  Cases: untilted; and the tilt at which the steepest ray meets the face at exactly the
  critical angle at the line centre (tilt + D / 2L = theta_c), with neighbours 1e-9 rad
  either side, which must give the same profile (no jump at the switch from total
  reflection to refraction).

For every case and precision: T and T_att finite, 0 <= T < 3, and the gradient of a
random linear functional of (T, T_att) finite for every ModelParams field. float32 is
compared with float64. Separately, the thin-layer case is compared with the exact ray
tracer to measure the independent-interface approximation.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fwdfit
from fwdfit import ReferenceLayer, trace_reference
from helpers import (STACK_LAYERS, al_layer, free_layer_parameters, gaussian_line_table, oxide_layer,
                     random_weights, replace_params, rms, stack_scene, weighted_value_and_grad,
                     white_beam, write_scene)

FIELDS = ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A", "tilt_deg", "centre_um",
          "depth_mm", "distance_mm", "shift_um")
FLOAT32_TOLERANCE = 1e-3  # max |T32 - T64|; measured up to 2.7e-4 (critical case)


AL = (2.078, 1.39, 0.1)  # sld, mu, mu_per_A of the Al layers (stack and narrow)

# Narrow kernel: 1 mm square aperture at 7.5 m, 4 Å, Al.
NARROW_L_M, NARROW_D_MM, NARROW_LAMBDA_A = 7.5, 1.0, 4.0
THETA_C = NARROW_LAMBDA_A * math.sqrt(AL[0] * 1e-6 / math.pi)  # 3.25 mrad
CRITICAL_TILT = THETA_C - 0.5 * NARROW_D_MM / (NARROW_L_M * 1e3)  # rad


def _stack_case(params, case):
    """Parameter values of one ``stack`` case."""
    th, sld, mu, mu1 = (np.asarray(getattr(params, f)).copy() for f in
                        ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A"))
    changes = {"tilt_deg": 0.0}  # the scene's 0.5° only sizes the kernel windows
    if case == "tilt_0.5deg":
        changes["tilt_deg"] = 0.5
    elif case == "zero_contrast":
        sld[[1, 3]], mu[[1, 3]], mu1[[1, 3]] = AL
        changes.update(sld_e6_per_A2=sld, mu_per_m=mu, mu_per_m_per_A=mu1)
    elif case in ("zero_thickness", "zero_thickness_as_al"):
        th[[1, 3]] = 0.0
        changes["thickness_um"] = th
        if case == "zero_thickness_as_al":  # the same empty layer, but made of Al
            sld[[1, 3]], mu[[1, 3]], mu1[[1, 3]] = AL
            changes.update(sld_e6_per_A2=sld, mu_per_m=mu, mu_per_m_per_A=mu1)
    elif case == "thin_2um":
        th[[0, 1, 3, 4]] = 2.0
        changes["thickness_um"] = th
    else:
        assert case == "largest_delta"
    return replace_params(params, **changes)


def _narrow_case(params, case):
    tilt_rad = {"untilted": 0.0, "critical": CRITICAL_TILT, "critical_minus": CRITICAL_TILT - 1e-9,
                "critical_plus": CRITICAL_TILT + 1e-9}[case]
    return replace_params(params, tilt_deg=math.degrees(tilt_rad))


STACK_CASES = ["largest_delta", "tilt_0.5deg", "zero_contrast", "zero_thickness", "thin_2um"]
NARROW_CASES = ["untilted", "critical", "critical_minus", "critical_plus"]
ALL_CASES = [("stack", c) for c in STACK_CASES] + [("narrow", c) for c in NARROW_CASES]
PRECISIONS = ["float64", "float32"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hard")
    stack = stack_scene(folder)
    narrow = write_scene(folder, [al_layer(mu=1.39, mu_per_A=0.1)], name="narrow.toml",
                         tilt_deg=0.25, aperture="square", aperture_mm=NARROW_D_MM,
                         aperture_distance_m=NARROW_L_M,
                         profiles=[("d01.1mm", 1.1, -720.0, 720.0)],
                         spectrum=fwdfit.GaussianLine(NARROW_LAMBDA_A, 1e-3))
    return {"stack": stack, "narrow": narrow}


@pytest.fixture(scope="module")
def results(scenes):
    """``results(model, case, precision)`` -> (T, T_att, grads as NumPy), computed once each."""
    cache = {}
    built = {}

    def get(model_name, case, precision):
        key = (model_name, case, precision)
        if key not in cache:
            scene = scenes[model_name]
            with jax.enable_x64(precision == "float64"):
                if (model_name, precision) not in built:
                    free = free_layer_parameters(scene)
                    dtype = jnp.float64 if precision == "float64" else jnp.float32
                    built[model_name, precision] = (fwdfit.build_model(scene, free=free),
                                                    fwdfit.initial_params(scene, dtype=dtype),
                                                    random_weights(scene, dtype))
                model, params, weights = built[model_name, precision]
                params = (_stack_case if model_name == "stack" else _narrow_case)(params, case)
                (_, (T, T_att)), grads = weighted_value_and_grad(params, model, weights)
                assert T[0].dtype == jnp.dtype(precision)
                cache[key] = (np.asarray(T[0], float), np.asarray(T_att[0], float),
                              {f: np.asarray(getattr(grads, f), float) for f in FIELDS})
        return cache[key]

    return get


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("model_name, case", ALL_CASES, ids=[f"{m}-{c}" for m, c in ALL_CASES])
def test_finite_and_sane(results, model_name, case, precision):
    """T and T_att finite, 0 <= T < 3, T_att in [0, 1] up to rounding (float32 sums of
    kernel differences overshoot 1 by up to 5e-6), and a visible edge signal."""
    T, T_att, _ = results(model_name, case, precision)
    assert np.all(np.isfinite(T)) and np.all(np.isfinite(T_att))
    assert T.min() >= 0.0 and T.max() < 3.0
    rounding = 2e-5 if precision == "float32" else 1e-12
    assert T_att.min() >= 0.0 and T_att.max() <= 1.0 + rounding
    assert T.max() > 1.005  # refraction lifts the open beam next to an edge in every case


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("model_name, case", ALL_CASES, ids=[f"{m}-{c}" for m, c in ALL_CASES])
def test_gradients_finite(results, model_name, case, precision):
    """d/dparams of a random linear functional of (T, T_att) is finite for every field,
    and not identically zero for the fields every profile depends on."""
    _, _, grads = results(model_name, case, precision)
    for field in FIELDS:
        assert np.all(np.isfinite(grads[field])), field
    for field in ("sld_e6_per_A2", "tilt_deg", "centre_um", "distance_mm"):
        assert np.any(grads[field] != 0.0), field


@pytest.mark.parametrize("model_name, case", ALL_CASES, ids=[f"{m}-{c}" for m, c in ALL_CASES])
def test_float32_matches_float64(results, model_name, case):
    """float32 T and T_att within 1e-3 (max over pixels) of float64 (measured: 2.7e-4 at
    the critical configuration, below 1e-5 elsewhere; printed with -s)."""
    T64, Ta64, _ = results(model_name, case, "float64")
    T32, Ta32, _ = results(model_name, case, "float32")
    diff, diff_att = np.max(np.abs(T32 - T64)), np.max(np.abs(Ta32 - Ta64))
    print(f"{model_name}/{case}: max|T32-T64| = {diff:.2e}, RMS {rms(T32 - T64):.2e}, "
          f"max|T_att32-T_att64| = {diff_att:.2e}")
    assert diff < FLOAT32_TOLERANCE and diff_att < FLOAT32_TOLERANCE


@pytest.mark.parametrize("precision", PRECISIONS)
def test_critical_angle_switch_is_continuous(results, precision):
    """Tilting by 1e-9 rad across the exact critical configuration moves T by < 1e-5:
    the switch from total reflection to refraction (where a2 = sqrt(a1^2 - theta_c^2)
    has an infinite slope) leaves no jump."""
    T, _, _ = results("narrow", "critical", precision)
    for side in ("critical_minus", "critical_plus"):
        T_side, _, _ = results("narrow", side, precision)
        assert np.max(np.abs(T_side - T)) < 1e-5


def test_critical_configuration_reflects(results):
    """At the critical tilt the rays on the face hit at the steepest angles are all at or
    below theta_c: the profile differs from the untilted one by well over the 1e-5 floor."""
    T_crit, _, _ = results("narrow", "critical", "float64")
    T_flat, _, _ = results("narrow", "untilted", "float64")
    assert np.max(np.abs(T_crit - T_flat)) > 0.05


# --------------------------------------------------------------------------- thin layers


THIN_LINE = fwdfit.GaussianLine(4.0, 0.15)
THIN_GEOMETRY = dict(aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5)


@pytest.fixture(scope="module")
def thin_layer_errors(tmp_path_factory):
    """Model vs exact tracer near the left edge of oxide (t µm) | Al | oxide (t µm), 1.1 mm.

    Returns {t: (rms, max |diff|, tracer noise RMS, peak model, peak tracer)}.
    """
    folder = tmp_path_factory.mktemp("thin")
    lam, weight = gaussian_line_table(THIN_LINE.wavelength_A, THIN_LINE.fwhm_rel)
    out = {}
    for t in (2.0, 20.0):
        oxide = oxide_layer("ox", t, 3.518, 12.0)
        layers = [oxide, al_layer(), oxide.tied("ox_r")]
        # The same grid for every t: the left outer face +- 60 µm.
        scene = write_scene(folder, layers, name=f"thin{t:g}.toml",
                            profiles=[("d01.1mm", 1.1, -561.6, -441.6)], spectrum=THIN_LINE,
                            **THIN_GEOMETRY)
        T, _ = eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene))
        T = np.asarray(T[0])
        x = scene.profiles[0].x_um
        ref = trace_reference([ReferenceLayer(t, 3.518, 12.0, 0.3), ReferenceLayer(1000.0, 2.078, 1.39),
                               ReferenceLayer(t, 3.518, 12.0, 0.3)],
                              depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, distance_mm=1.1,
                              spectrum_lambda_A=lam, spectrum_weight=weight,
                              pixel_edges_um=np.append(x - 1.2, x[-1] + 1.2), n_rays=1_000_000,
                              seed=11, **THIN_GEOMETRY)
        d = T - ref.T
        out[t] = (rms(d), float(np.max(np.abs(d))), rms(ref.T_err), float(T.max()), float(ref.T.max()))
        print(f"oxide {t:g} µm | Al | oxide: RMS(model - tracer) = {out[t][0]:.4f}, max {out[t][1]:.4f}, "
              f"tracer noise RMS {out[t][2]:.4f}, peak T model {out[t][3]:.4f} vs tracer {out[t][4]:.4f}")
    return out


def test_thin_layer_is_coupled(thin_layer_errors):
    """2 µm oxide on Al (thinner than depth * |a| ~ 6 µm): its faces are coupled (``_thin``)
    and model and tracer agree within the tracer's noise (RMS difference < 2x the noise RMS,
    peaks within 0.01). The independent-interface approximation was off by RMS ~0.018, max
    ~0.06 here (noise RMS ~0.003)."""
    rms_2, max_2, noise_2, peak_model, peak_tracer = thin_layer_errors[2.0]
    assert rms_2 < 2 * noise_2 and max_2 < 0.02
    assert abs(peak_model - peak_tracer) < 0.01


def test_thick_coating_is_exact(thin_layer_errors):
    """20 µm of oxide, thicker than the sideways drift: model and tracer agree within the
    tracer's noise (RMS difference < 2x the noise RMS, peaks within 0.01)."""
    rms_20, _, noise_20, peak_model, peak_tracer = thin_layer_errors[20.0]
    assert rms_20 < 2 * noise_20
    assert abs(peak_model - peak_tracer) < 0.01



# --------------------------------------------------------------------------- wide tilted layers


def test_face_wholly_before_the_mid_plane_matches_tracer():
    """An 80 mm wide Al layer (mu 300 / m, 1 mm deep) tilted by 1°: its right-hand face spans
    depths z = -698 +- 500 µm, wholly before the mid-plane z = 0. The step profile used to give
    rays their side of that face at z = 0, where the face does not reach: the rays that cross
    its line between its end and z = 0 (a 9 µm band) counted as inside the layer, and T_att
    was 0.0043 RMS off the tracer (T 0.0047). Its assignment plane is the face's end now
    (``_model._assignment_planes``): measured 0.00035 (T 0.0016, the tracer's noise)."""
    width_um, tilt_deg, line = 80000.0, 1.0, fwdfit.GaussianLine(4.0, 0.1)
    geometry = dict(aperture="square", aperture_mm=20.0, aperture_distance_m=5.0)
    face_um = 0.5 * width_um / math.cos(math.radians(tilt_deg))
    with jax.enable_x64(True):
        scene = fwdfit.Scene(
            sample=fwdfit.Sample(depth_mm=1.0, tilt_deg=tilt_deg, centre_um=0.0,
                                 layers=(fwdfit.Layer("Al", width_um, AL[0], 300.0),)),
            instruments={"": fwdfit.Instrument(geometry["aperture"], geometry["aperture_mm"],
                                               geometry["aperture_distance_m"], 2.4)},
            spectra={"line": line},
            profiles=(fwdfit.Profile("p", 10.0, "line", "", fwdfit.pixel_grid(face_um - 90.0, face_um + 90.0, 2.4)),))
        T, T_att = (np.asarray(v[0]) for v in eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene)))
    x = scene.profiles[0].x_um
    ref = trace_reference([ReferenceLayer(width_um, AL[0], 300.0)], depth_mm=1.0, tilt_deg=tilt_deg, centre_um=0.0,
                          distance_mm=10.0, spectrum_lambda_A=gaussian_line_table(4.0, 0.1)[0],
                          spectrum_weight=gaussian_line_table(4.0, 0.1)[1],
                          pixel_edges_um=np.append(x - 1.2, x[-1] + 1.2), n_rays=2_000_000, seed=5, **geometry)
    print(f"wide tilted layer: RMS(T_att - tracer) = {rms(T_att - ref.T_att):.5f}, "
          f"RMS(T - tracer) = {rms(T - ref.T):.5f}, tracer noise RMS {rms(ref.T_err):.5f}")
    assert rms(T_att - ref.T_att) < 0.001
    assert rms(T - ref.T) < 0.003


def test_strong_absorber_face_matches_tracer():
    """A 1 mm block with mu x depth = 20 (T = 2e-9 through it), 10 mm away: the crossing rays'
    attenuation exp(-mu (z_hi - z)) is far from polynomial in the depth, and two depth nodes per
    piece left T_att 0.0065 RMS (max 0.032) off the tracer, whose noise is 0.0036. The plan now
    gives such scenes more depth nodes (``_plan._DEPTH_NODES_PER_ATTENUATION``): measured 0.0040
    (max 0.012)."""
    depth_mm, mu_per_m, line = 2.0, 1e4, fwdfit.GaussianLine(4.0, 0.15)
    with jax.enable_x64(True):
        scene = fwdfit.Scene(
            sample=fwdfit.Sample(depth_mm=depth_mm, tilt_deg=0.1, centre_um=0.0,
                                 layers=(fwdfit.Layer("X", 1000.0, AL[0], mu_per_m),)),
            instruments={"": fwdfit.Instrument(THIN_GEOMETRY["aperture"], THIN_GEOMETRY["aperture_mm"],
                                               THIN_GEOMETRY["aperture_distance_m"], 2.4)},
            spectra={"line": line},
            profiles=(fwdfit.Profile("p", 10.0, "line", "", fwdfit.pixel_grid(-560.0, -440.0, 2.4)),))
        _, T_att = (np.asarray(v[0]) for v in eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene)))
    x = scene.profiles[0].x_um
    lam, weight = gaussian_line_table(line.wavelength_A, line.fwhm_rel)
    ref = trace_reference([ReferenceLayer(1000.0, AL[0], mu_per_m)], depth_mm=depth_mm, tilt_deg=0.1, centre_um=0.0,
                          distance_mm=10.0, spectrum_lambda_A=lam, spectrum_weight=weight,
                          pixel_edges_um=np.append(x - 1.2, x[-1] + 1.2), n_rays=2_000_000, seed=3, **THIN_GEOMETRY)
    d, noise = T_att - ref.T_att, rms(ref.T_att_err)
    print(f"mu x depth = 20: RMS(T_att - tracer) = {rms(d):.4f}, max {np.max(np.abs(d)):.4f}, noise RMS {noise:.4f}")
    assert rms(d) < 1.3 * noise and np.max(np.abs(d)) < 0.02

def test_zero_thickness_layer_material_does_not_matter(results, tmp_path):
    """A 0 µm layer has no effect whatever its material: with the 160 µm layers of the
    stack set to 0 µm (kept in the model because their thickness is free, as in a fit; they
    start thick, so their faces are independent), T must not depend on whether they are oxide
    or Al, and must equal the stack built without them. Before the layers faded to
    transparency it did, by up to ~2e-2 (two independent interfaces at one place)."""
    T_oxide, T_att_oxide, _ = results("stack", "zero_thickness", "float64")
    T_al, T_att_al, _ = results("stack", "zero_thickness_as_al", "float64")
    print(f"zero-thickness layer, oxide vs Al: max|dT| = {np.max(np.abs(T_oxide - T_al)):.2e}, "
          f"max|dT_att| = {np.max(np.abs(T_att_oxide - T_att_al)):.2e}")
    np.testing.assert_allclose(T_oxide, T_al, rtol=0, atol=1e-6)
    with jax.enable_x64(True):
        bare = write_scene(tmp_path, [STACK_LAYERS[i] for i in (0, 2, 4)], name="bare.toml", tilt_deg=0.5,
                           profiles=[("d34.4mm", 34.4, -1300.0, 1300.0)], spectrum=white_beam())
        params = replace_params(fwdfit.initial_params(bare, dtype=jnp.float64), tilt_deg=0.0)
        T_bare, T_att_bare = (np.asarray(v[0]) for v in eqx.filter_jit(fwdfit.build_model(bare))(params))
    print(f"zero-thickness layers vs none: max|dT| = {np.max(np.abs(T_oxide - T_bare)):.2e}, "
          f"max|dT_att| = {np.max(np.abs(T_att_oxide - T_att_bare)):.2e}")
    np.testing.assert_allclose(T_oxide, T_bare, rtol=0, atol=1e-6)
    np.testing.assert_allclose(T_att_oxide, T_att_bare, rtol=0, atol=1e-6)


def test_float32_fixture_runs_in_single_precision(float32, scenes, results):
    """Inside the ``float32`` fixture, scene values, the model and its output are float32,
    and the result is the float32 case computed above (same compiled function)."""
    scene = scenes["narrow"]
    params = fwdfit.initial_params(scene)
    assert params.tilt_deg.dtype == jnp.float32
    model = fwdfit.build_model(scene, free=free_layer_parameters(scene))
    (_, (T, _)), grads = weighted_value_and_grad(_narrow_case(params, "untilted"), model,
                                                 random_weights(scene, jnp.float32))
    assert T[0].dtype == jnp.float32 and grads.tilt_deg.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(T[0], float), results("narrow", "untilted", "float32")[0])
