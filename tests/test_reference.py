"""The Monte Carlo reference tracer: exact limits, symmetry, and agreement with the shared reference data."""

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fwdfit.reference import ReferenceLayer, trace_reference

DATA = Path(__file__).parent / "data"
PIXEL_UM = 2.4
AL = ReferenceLayer(thickness_um=1000.0, sld_e6_per_A2=2.078, mu_per_m=1.39)


def _table(path):
    return np.loadtxt(path, delimiter=",", skiprows=1)


def _edges(x_um):
    """Pixel edges around the bin centres of a profile CSV."""
    return np.append(x_um - PIXEL_UM / 2, x_um[-1] + PIXEL_UM / 2)


BOA = _table(DATA / "mcstas" / "spectrum_boa.csv")
BOA_GEOMETRY = dict(aperture="square", aperture_mm=40.0, aperture_distance_m=7.5,
                    spectrum_lambda_A=BOA[:, 0], spectrum_weight=BOA[:, 1])


def _scene_kwargs(scene_path, profile, spectrum):
    """trace_reference arguments for one profile of a scene.toml, with a tabulated spectrum."""
    scene = tomllib.loads(scene_path.read_text())
    sample, inst = scene["sample"], scene["instrument"]
    (prof,) = [p for p in scene["profiles"] if p["name"] == profile]
    layers = [ReferenceLayer(lay["thickness_um"], lay["sld_e6_per_A2"], lay["mu_per_m"],
                             lay.get("mu_per_m_per_A", 0.0)) for lay in sample["layers"]]
    return dict(layers=layers, depth_mm=sample["depth_mm"], tilt_deg=sample["tilt_deg"],
                centre_um=sample["centre_um"], aperture=inst["aperture"],
                aperture_mm=inst["aperture_mm"], aperture_distance_m=inst["aperture_distance_m"],
                distance_mm=prof["distance_mm"], psf_fwhm_um=inst["psf_fwhm_um"],
                fresnel=inst["fresnel"], spectrum_lambda_A=spectrum[:, 0],
                spectrum_weight=spectrum[:, 1])


def _one_ray_floor(edges, n_rays):
    """A lower bound on one ray's share of a pixel. Bins with smaller errors are bulk or rare-ray
    bins, where batch errors (0 where no rare ray landed) mean little."""
    return (edges[-1] - edges[0]) / (n_rays * PIXEL_UM)


def _compare(T, T_err, ref, ref_err, floor):
    """Reduced chi2 over the noisy bins (combined error above floor), RMS difference and RMS
    combined error over every bin where the reference is not 1."""
    m = ref != 1.0
    var = T_err[m] ** 2 + ref_err[m] ** 2
    d = T[m] - ref[m]
    noisy = var > floor**2
    return np.mean(d[noisy] ** 2 / var[noisy]), np.sqrt(np.mean(d**2)), np.sqrt(np.mean(var))


def _extremes(x, T):
    """(max, min) of T near the left and the right edge (350 < |x| < 1200 µm)."""
    return [(T[s].max(), T[s].min()) for s in ((x < -350) & (x > -1200), (x > 350) & (x < 1200))]


def test_no_sld_is_beer_lambert():
    mu0, mu1 = 50.0, 20.0
    block = ReferenceLayer(1000.0, 0.0, mu0, mu1)
    edges = np.arange(-720.0, 720.0 + 1e-9, PIXEL_UM)
    r = trace_reference([block], depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, distance_mm=5.0,
                        pixel_edges_um=edges, n_rays=1_000_000, seed=1, **BOA_GEOMETRY)
    assert np.array_equal(r.T, r.T_att) and np.array_equal(r.T_err, r.T_att_err)
    x = 0.5 * (edges[:-1] + edges[1:])
    assert np.all(r.T[np.abs(x) > 600] == 1.0) and np.all(r.T_err[np.abs(x) > 600] == 0.0)
    lam = np.linspace(BOA[0, 0], BOA[-1, 0], 200_001)
    density = np.interp(lam, BOA[:, 0], BOA[:, 1])
    expected = np.sum(density * np.exp(-(mu0 + mu1 * lam) * 2e-3)) / np.sum(density)
    bulk = np.abs(x) < 300
    sigma = np.sqrt(np.sum(r.T_err[bulk] ** 2)) / bulk.sum()
    assert abs(r.T[bulk].mean() - expected) < 3 * sigma
    assert sigma < 1e-4


def test_no_absorption_conserves_intensity():
    block = ReferenceLayer(1000.0, 2.078, 0.0)
    edges = np.arange(-960.0, 960.0 + 1e-9, PIXEL_UM)  # holds every deflected ray (< 2θc·Δ)
    r = trace_reference([block], depth_mm=2.0, tilt_deg=0.24, centre_um=0.0, distance_mm=20.0,
                        pixel_edges_um=edges, n_rays=1_000_000, seed=2, **BOA_GEOMETRY)
    assert r.n_dropped == 0 and np.all(r.T_att == 1.0)
    assert r.T.max() > 1.05 and r.T.min() < 0.95  # refraction moved intensity about
    excess = np.sum(r.T - 1.0) * PIXEL_UM
    assert abs(excess) < 4 * PIXEL_UM * np.sqrt(np.sum(r.T_err**2))


def test_untilted_block_is_symmetric():
    edges = np.arange(-720.0, 720.0 + 1e-9, PIXEL_UM)
    n_rays = 1_500_000
    r = trace_reference([AL], depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, distance_mm=8.5,
                        pixel_edges_um=edges, n_rays=n_rays, n_batches=10, seed=3,
                        **BOA_GEOMETRY)
    half = slice(r.T.size // 2, None)  # x > 0 against its mirror image
    T, T_mirror = r.T[half], r.T[::-1][half]
    var = r.T_err[half] ** 2 + r.T_err[::-1][half] ** 2
    noisy = var > _one_ray_floor(edges, n_rays) ** 2
    assert noisy.sum() > 30 and np.mean((T - T_mirror)[noisy] ** 2 / var[noisy]) < 2.0
    np.testing.assert_allclose(T[~noisy], T_mirror[~noisy], rtol=0, atol=1e-3)
    assert T.max() > 1.05  # the edge peaks are there to compare


def test_agrees_with_shared_raytrace_icon_tilted():
    case = DATA / "raytrace" / "al_icon_tilt0.24"
    ref = _table(case / "l4.6A.csv")
    spectrum = _table(DATA / "mcstas" / "spectrum_icon_l4.6A.csv")
    edges, n_rays = _edges(ref[:, 0]), 4_000_000
    r = trace_reference(**_scene_kwargs(case / "scene.toml", "l4.6A", spectrum),
                        pixel_edges_um=edges, n_rays=n_rays, seed=4)
    floor = _one_ray_floor(edges, n_rays)
    chi2, rms, noise = _compare(r.T, r.T_err, ref[:, 1], ref[:, 2], floor)
    assert chi2 < 2.0 and rms < 1.5 * noise
    # Attenuation only: a handful of noisy corner bins, so compare the RMS and the worst bin.
    _, rms_att, noise_att = _compare(r.T_att, r.T_att_err, ref[:, 3], ref[:, 4], 0.0)
    assert rms_att < 1.5 * noise_att and np.max(np.abs(r.T_att - ref[:, 3])) < 5e-5
    for mine, theirs in zip(_extremes(ref[:, 0], r.T), _extremes(ref[:, 0], ref[:, 1])):
        np.testing.assert_allclose(mine, theirs, rtol=0.035)


def test_agrees_with_mcstas_boa_tilted():
    case = DATA / "mcstas"
    name = "boa_al_tilt0.24_d08.5mm"
    ref, ref_att = _table(case / f"{name}.csv"), _table(case / f"{name}_attenuation_only.csv")
    near = np.abs(ref[:, 0]) < 800  # every deflected ray lands within 800 µm at 8.5 mm
    ref, ref_att = ref[near], ref_att[near]
    edges, n_rays = _edges(ref[:, 0]), 3_000_000
    r = trace_reference(**_scene_kwargs(case / "scene_boa_tilt0.24.toml", name, BOA),
                        pixel_edges_um=edges, n_rays=n_rays, seed=5)
    floor = _one_ray_floor(edges, n_rays)
    chi2, rms, noise = _compare(r.T, r.T_err, ref[:, 1], ref[:, 2], floor)
    assert chi2 < 2.0 and rms < 1.5 * noise
    chi2_att, _, _ = _compare(r.T_att, r.T_att_err, ref_att[:, 1], ref_att[:, 2], 1e-6)
    assert chi2_att < 2.0
    peaks = json.loads((case / "edge_metrics.json").read_text())["peaks"][name]
    (lmax, lmin), (rmax, rmin) = _extremes(ref[:, 0], r.T)
    np.testing.assert_allclose([lmax, lmin, rmax, rmin],
                               [peaks["left"]["T_max"], peaks["left"]["T_min"],
                                peaks["right"]["T_max"], peaks["right"]["T_min"]], rtol=0.03)


def test_blurred_profile_agrees_with_shared_raytrace():
    case = DATA / "raytrace" / "al_boa_tilt0.24_psf"
    ref = _table(case / "d01.1mm.csv")
    edges, n_rays = _edges(ref[:, 0]), 2_000_000
    r = trace_reference(**_scene_kwargs(case / "scene.toml", "d01.1mm", BOA),
                        pixel_edges_um=edges, n_rays=n_rays, seed=6)
    chi2, rms, noise = _compare(r.T, r.T_err, ref[:, 1], ref[:, 2], _one_ray_floor(edges, n_rays))
    assert chi2 < 2.0 and rms < 1.5 * noise


BAD = [
    (dict(layers=[]), "at least one layer"),
    (dict(layers=[ReferenceLayer(-1.0, 2.0, 1.0)]), "thickness"),
    (dict(aperture="hexagonal"), "unknown aperture"),
    (dict(pixel_edges_um=np.array([0.0, 2.4, 2.4])), "increasing"),
    (dict(distance_mm=1.0), "half depth"),
    (dict(spectrum_lambda_A=np.array([]), spectrum_weight=np.array([])), "spectrum"),
    (dict(spectrum_weight=np.zeros_like(BOA[:, 1])), "weights"),
]


@pytest.mark.parametrize("bad, message", BAD)
def test_rejects_nonsense(bad, message):
    kwargs = dict(layers=[AL], depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, distance_mm=5.0,
                  pixel_edges_um=np.arange(-10.0, 10.1, PIXEL_UM), n_rays=1000, **BOA_GEOMETRY)
    with pytest.raises(ValueError, match=message):
        trace_reference(**{**kwargs, **bad})
