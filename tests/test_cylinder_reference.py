"""The exact tracer of concentric circles (rods, tubes): analytic chords, conservation, symmetry,
agreement with McStas's Refractor cylinder, a tube with shells on both faces, bad input."""

import json
from pathlib import Path

import numpy as np
import pytest

from fwdfit import FwdfitError
from fwdfit.reference import ReferenceLayer, maxwellian_spectrum, trace_cylinder_reference

DATA = Path(__file__).parent / "data" / "mcstas_cylinder"
PIXEL_UM = 2.4
BOA = dict(aperture="square", aperture_mm=40.0, aperture_distance_m=7.5)
LAM, WEIGHT = maxwellian_spectrum(47.25, 0.8, 10.0)
SPECTRUM = dict(spectrum_lambda_A=LAM, spectrum_weight=WEIGHT)


def _edges(lo_um, hi_um):
    return lo_um + PIXEL_UM * np.arange(int(round((hi_um - lo_um) / PIXEL_UM)) + 1)


def _chord(r_um, b_um):
    return 2.0 * np.sqrt(np.maximum(r_um * r_um - b_um * b_um, 0.0))


def _analytic_attenuation(radii_um, mu_of_lambda, lam, weight, edges, distance_mm, aperture_mm, lever_m,
                          centre_um=0.0, aperture="square"):
    """Bin average of <exp(-Σ mu_k (chord_k - chord_k+1))> over the aperture (a disk: weights
    sqrt(1 - (2x/D)²)) and a tabulated spectrum (trapezoid weights), rays straight from the
    aperture to the pixel: the limit SLD = 0."""
    delta, lever = 1e3 * distance_mm, 1e6 * lever_m
    sub = 8
    x_det = (edges[:-1, None] + PIXEL_UM * (np.arange(sub) + 0.5)[None, :] / sub).ravel()
    x_ap = 1e3 * aperture_mm * ((np.arange(400) + 0.5) / 400 - 0.5)
    w_ap = np.ones(x_ap.size) if aperture == "square" else np.sqrt(1.0 - (2e-3 * x_ap / aperture_mm) ** 2)
    x_s = x_det[:, None] * (1 - delta / lever) + x_ap[None, :] * delta / lever - centre_um
    b = x_s * lever / np.hypot(lever, x_det[:, None] - x_ap[None, :])  # impact parameter
    chords = [_chord(r, b) for r in radii_um] + [0.0 * b]
    paths = [chords[k] - chords[k + 1] for k in range(len(radii_um))]
    p = weight * np.gradient(lam)
    T = np.zeros(x_det.size)
    for lam_i, p_i in zip(lam, p / p.sum()):
        att = sum(mu(lam_i) * 1e-6 * path for mu, path in zip(mu_of_lambda, paths))
        T += p_i * (np.exp(-att) @ w_ap) / w_ap.sum()
    return T.reshape(-1, sub).mean(axis=1)


ROD3 = [ReferenceLayer(50.0, 0.0, 2000.0), ReferenceLayer(30.0, 0.0, 500.0, 100.0), ReferenceLayer(0.0, 0.0, 300.0)]


@pytest.mark.parametrize("method, aperture", [("quadrature", "square"), ("quadrature", "circular"),
                                              ("monte_carlo", "square")])
def test_mu_only_equals_analytic_chords(method, aperture):
    """SLD 0 everywhere: T = exp(-Σ mu_k chord_k) averaged over the source and the spectrum."""
    lam = np.linspace(2.0, 6.0, 41)
    weight = np.exp(-((lam - 4.0) ** 2))
    edges = _edges(-480.0, 480.0)
    kw = dict(outer_radius_um=300.0, centre_um=12.0, distance_mm=20.0, spectrum_lambda_A=lam,
              spectrum_weight=weight, pixel_edges_um=edges, method=method, n_aperture=48,
              **(BOA | dict(aperture=aperture)))
    if method == "monte_carlo":
        kw.update(n_rays=400_000, n_batches=8)
    res = trace_cylinder_reference(ROD3, **kw)
    mus = [lambda l, s=s: s.mu_per_m + s.mu_per_m_per_A * l for s in ROD3]
    expected = _analytic_attenuation([300.0, 250.0, 220.0], mus, lam, weight, edges, 20.0, 40.0, 7.5,
                                     centre_um=12.0, aperture=aperture)
    assert expected.min() < 0.65  # the shells and the core matter
    np.testing.assert_array_equal(res.T, res.T_att)  # no refraction without SLD
    if method == "quadrature":
        assert np.max(np.abs(res.T - expected)) < 2e-3
        assert np.sqrt(np.mean((res.T - expected) ** 2)) < 3e-4
    else:
        pull = (res.T - expected) / np.maximum(res.T_err, 1e-4)
        assert np.mean(pull**2) < 2.0


@pytest.mark.parametrize("method, psf_fwhm_um", [("quadrature", 0.0), ("quadrature", 12.0), ("monte_carlo", 0.0)])
def test_mu_zero_conserves_the_counts(method, psf_fwhm_um):
    """mu = 0: refraction and total reflection only move neutrons, so Σ (T - 1) over a window
    wider than everything they reach is 0, although T departs from 1 by percents."""
    shells = [ReferenceLayer(100.0, 4.0, 0.0), ReferenceLayer(0.0, 2.0, 0.0)]
    edges = _edges(-1200.0, 1200.0)
    kw = dict(outer_radius_um=400.0, distance_mm=30.0, pixel_edges_um=edges, method=method, n_aperture=32,
              psf_fwhm_um=psf_fwhm_um, **BOA, **SPECTRUM)
    if method == "monte_carlo":
        kw.update(n_rays=400_000, fresnel=True)
    res = trace_cylinder_reference(shells, **kw)
    moved = PIXEL_UM * np.sum(np.abs(res.T - 1.0))
    net = PIXEL_UM * np.sum(res.T - 1.0)
    assert np.ptp(res.T) > 0.02 and moved > 1.0  # µm of neutrons moved
    assert abs(net) < (1e-3 if method == "quadrature" else 0.02) * moved
    assert res.n_dropped == 0
    np.testing.assert_allclose(res.T_att, 1.0, atol=1e-12)


def test_mirror_symmetry():
    """A rod on the axis between mirror-symmetric pixels: T(x) = T(-x) within the tracer's noise."""
    res = trace_cylinder_reference([ReferenceLayer(0.0, 2.0787, 9.0592, 0.7742)], outer_radius_um=500.0,
                                   distance_mm=19.6, pixel_edges_um=_edges(-900.0, 900.0), **BOA, **SPECTRUM)
    diff = res.T - res.T[::-1]
    err = np.hypot(res.T_err, res.T_err[::-1])
    noisy = err > 1e-6
    assert np.max(np.abs(diff)) < 2e-3
    assert np.mean(diff[noisy] ** 2 / err[noisy] ** 2) < 4.0


@pytest.mark.parametrize("distance_mm", [8.5, 34.4])
def test_agrees_with_mcstas_al_rod(distance_mm):
    """McStas 3.5 Refractor, Al rod R = 500 µm at BOA (tests/data/PROVENANCE.md): RMS of T - T_McStas
    is what the two noises allow, the gain peak within 5 %, attenuation only within 3e-4."""
    cases = {c["name"]: c for c in json.loads((DATA / "cases.json").read_text())["cases"]}
    name = f"boa_alrod_r500_d{distance_mm:04.1f}mm"
    case = cases[name]
    sample, spectrum = case["sample"], case["spectrum"]
    lam, weight = maxwellian_spectrum(spectrum["T_K"], spectrum["lambda_min_A"], spectrum["lambda_max_A"])
    al = ReferenceLayer(0.0, sample["derived"]["rho_b_A2"] * 1e6, 9.0592, 0.7742)
    ref = np.loadtxt(DATA / f"{name}.csv", delimiter=",", skiprows=1)
    att = np.loadtxt(DATA / f"{name}_attenuation_only.csv", delimiter=",", skiprows=1)
    edges = np.append(ref[:, 0] - PIXEL_UM / 2, ref[-1, 0] + PIXEL_UM / 2)
    res = trace_cylinder_reference(
        [al], outer_radius_um=1e6 * sample["radius_m"], distance_mm=1e3 * sample["Delta_m"],
        aperture="square", aperture_mm=1e3 * case["aperture"]["D_m"],
        aperture_distance_m=case["aperture"]["L_m"], spectrum_lambda_A=lam, spectrum_weight=weight,
        pixel_edges_um=edges)
    d = res.T - ref[:, 1]
    rms, noise = np.sqrt(np.mean(d**2)), np.sqrt(np.mean(ref[:, 2] ** 2 + res.T_err**2))
    assert rms < 1.2e-3 and rms < 1.5 * noise
    gain, gain_ref = res.T.max() - 1.0, ref[:, 1].max() - 1.0
    assert abs(gain - gain_ref) < 0.05 * gain_ref
    assert np.sqrt(np.mean((res.T_att - att[:, 1]) ** 2)) < 3e-4
    assert res.n_dropped == 0


def test_monte_carlo_agrees_with_quadrature():
    """The two integrations of the same physics (rays histogrammed, nodes spread onto pixels)
    agree within the Monte Carlo error on a rod with an oxide-like shell, refraction on."""
    shells = [ReferenceLayer(40.0, 5.2, 40.0), ReferenceLayer(0.0, 3.07, 28.0)]
    kw = dict(outer_radius_um=300.0, distance_mm=10.0, pixel_edges_um=_edges(-420.0, 420.0), **BOA, **SPECTRUM)
    quad = trace_cylinder_reference(shells, **kw)
    mc = trace_cylinder_reference(shells, method="monte_carlo", n_rays=600_000, n_batches=8, **kw)
    err = np.hypot(quad.T_err, mc.T_err)
    noisy = err > 1e-5
    assert np.ptp(quad.T - quad.T_att) > 0.05  # refraction matters
    assert np.mean((quad.T - mc.T)[noisy] ** 2 / err[noisy] ** 2) < 2.0


CLADDING = [ReferenceLayer(20.0, 5.2, 0.0),  # ZrO2-like rim outside
            ReferenceLayer(520.0, 3.07, 0.0),  # Zircaloy wall
            ReferenceLayer(30.0, 2.0, 0.0)]  # a hydride-like rim inside the wall


def test_tube_with_two_rims_runs_and_conserves():
    """A tube (vacuum core) with an oxide rim outside and a hydride rim inside the wall: every ray
    traced, T = 1 far away, and with mu = 0 the counts are conserved over the whole tube."""
    edges = _edges(-1300.0, 1300.0)
    kw = dict(outer_radius_um=1000.0, core="vacuum", distance_mm=20.0, pixel_edges_um=edges,
              n_aperture=32, **BOA, **SPECTRUM)
    res = trace_cylinder_reference(CLADDING, **kw)
    net, moved = PIXEL_UM * np.sum(res.T - 1.0), PIXEL_UM * np.sum(np.abs(res.T - 1.0))
    assert res.n_dropped == 0 and np.all(np.isfinite(res.T)) and moved > 1.0
    assert abs(net) < 1e-3 * moved
    lossy = [ReferenceLayer(20.0, 5.2, 30.0), ReferenceLayer(520.0, 3.07, 25.0), ReferenceLayer(30.0, 2.0, 3000.0)]
    res = trace_cylinder_reference(lossy, **kw)
    x = 0.5 * (edges[1:] + edges[:-1])
    np.testing.assert_allclose(res.T_att[np.abs(x) > 1100.0], 1.0, atol=1e-12)  # beyond the penumbra
    wall = (np.abs(x) > 500.0) & (np.abs(x) < 900.0)  # through the wall only
    centre = np.abs(x) < 5.0  # through the hydride rim twice, near-radially: exp(-Σ mu 2 t)
    assert res.T_att[centre].mean() < res.T_att[wall].mean() < 1.0
    np.testing.assert_allclose(res.T_att[centre].mean(), np.exp(-2e-6 * (20 * 30 + 520 * 25 + 30 * 3000)), rtol=2e-3)


@pytest.mark.parametrize("change, message", [
    (dict(core="hollow"), "unknown core"),
    (dict(outer_radius_um=10.0), "positive thickness"),
    (dict(fresnel=True), "monte_carlo"),
    (dict(method="exact"), "unknown method"),
    (dict(distance_mm=0.1), "distance_mm"),
])
def test_bad_input_is_refused(change, message):
    kw = dict(outer_radius_um=1000.0, core="vacuum", distance_mm=20.0, pixel_edges_um=_edges(-100.0, 100.0),
              **BOA, **SPECTRUM) | change
    with pytest.raises(FwdfitError, match=message):
        trace_cylinder_reference(CLADDING, **kw)
