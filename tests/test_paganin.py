"""The neutron Paganin-type filter: analytic limits, exact inverses, tau by hand, bad input."""

import math

import numpy as np
import pytest

from fwdfit import FwdfitError
from fwdfit.paganin import (
    paganin_filter_1d,
    paganin_filter_2d,
    paganin_tau_um2,
    paganin_tau_um2_spectrum,
    paganin_thickness_um,
)

PIXEL_UM = 2.4
BOA_DIVERGENCE = 0.040 / 7.5  # D / L, rad
AL = dict(sld_e6_per_A2=2.078, divergence_rad=BOA_DIVERGENCE)


def _block_thickness_um(x_um, depth_um=2000.0, half_width_um=500.0, edge_um=20.0):
    """Path length through a block with smooth (tanh) side faces, um."""
    return 0.5 * depth_um * (np.tanh((x_um + half_width_um) / edge_um)
                             - np.tanh((x_um - half_width_um) / edge_um))


def _forward(T_att, pixel_um, tau_um2):
    """T_meas = F^-1[(1 + tau k^2) F[T_att]] on the periodic grid of T_att."""
    k = 2 * np.pi * np.fft.rfftfreq(T_att.size, d=pixel_um)
    return np.fft.irfft(np.fft.rfft(T_att) * (1 + tau_um2 * k**2), n=T_att.size)


def test_tiny_tau_is_identity():
    x = np.arange(700) * PIXEL_UM - 840.0
    T = np.exp(-500e-6 * _block_thickness_um(x)) * (1 + 0.01 * np.sin(x / 7.0))
    np.testing.assert_allclose(paganin_filter_1d(T, PIXEL_UM, 1e-12), T, rtol=0, atol=1e-10)
    image = np.outer(np.linspace(0.9, 1.1, 30), T)
    np.testing.assert_allclose(paganin_filter_2d(image, PIXEL_UM, 1e-12), image, rtol=0,
                               atol=1e-10)


def test_inverts_its_own_forward_model():
    mu_per_m = 500.0  # 2 mm of it transmits exp(-1): visible contrast
    tau = 3780.0  # um^2, Al at 3.8 Å and 1.1 mm with mu = 1.39 /m
    x = (np.arange(4096) - 2048) * PIXEL_UM
    thickness = _block_thickness_um(x)
    T_att = np.exp(-1e-6 * mu_per_m * thickness)
    T_meas = _forward(T_att, PIXEL_UM, tau)
    window = slice(2048 - 400, 2048 + 400)  # +-960 um: constant (air) at both ends
    assert abs(T_meas[window] - T_att[window]).max() > 0.01  # the edges do change
    np.testing.assert_allclose(paganin_filter_1d(T_meas[window], PIXEL_UM, tau), T_att[window],
                               rtol=0, atol=1e-8)
    recovered = paganin_thickness_um(T_meas[window], PIXEL_UM, tau, mu_per_m)
    np.testing.assert_allclose(recovered, thickness[window], rtol=1e-6, atol=1e-6 * 2000.0)


def test_1d_and_2d_agree_on_an_image_constant_along_columns():
    x = np.arange(500) * PIXEL_UM - 600.0
    profile = np.exp(-300e-6 * _block_thickness_um(x - 200.0, edge_um=3.0)) - 0.1 * (x > 500)
    image = np.tile(profile, (40, 1))  # every row the same profile: no y structure
    tau = 5000.0
    filtered_2d = paganin_filter_2d(image, PIXEL_UM, tau)
    filtered_1d = paganin_filter_1d(profile, PIXEL_UM, tau)
    np.testing.assert_allclose(filtered_2d, np.tile(filtered_1d, (40, 1)), rtol=0, atol=1e-10)
    thickness_2d = paganin_thickness_um(image, PIXEL_UM, tau, 300.0)
    np.testing.assert_allclose(thickness_2d[17], paganin_thickness_um(profile, PIXEL_UM, tau, 300.0),
                               rtol=0, atol=1e-6)


def test_tau_by_hand_for_al_at_boa():
    wavelength_m = 3.8e-10
    sld_per_m2 = 2.078e-6 * 1e20  # Å^-2 -> m^-2
    delta = wavelength_m**2 * sld_per_m2 / (2 * math.pi)  # 4.78e-6
    for distance_m, mu_per_m, b_factor in [(1.1e-3, 1.39, 1.0), (34.4e-3, 12.0, 1.0),
                                           (8.5e-3, 1.39, 40.0)]:
        theta = 0.040 / 7.5
        tau_m2 = b_factor * delta * distance_m / mu_per_m - (theta * distance_m) ** 2 / 8
        tau = paganin_tau_um2(wavelength_A=3.8, mu_per_m=mu_per_m, distance_mm=1e3 * distance_m,
                              b_factor=b_factor, **AL)
        assert tau == pytest.approx(tau_m2 * 1e12, rel=1e-12)
    assert paganin_tau_um2(wavelength_A=3.8, mu_per_m=1.39, distance_mm=1.1, **AL) == \
        pytest.approx(3775.0, abs=0.1)

    taus = paganin_tau_um2(wavelength_A=3.8, mu_per_m=12.0, distance_mm=34.4,
                           sld_e6_per_A2=2.078, divergence_rad=np.array([0.0, 0.005, 0.01, 0.02]))
    assert np.all(np.diff(taus) < 0)  # divergence lowers tau
    assert taus[-1] < 0  # L/D = 50: the divergence term wins
    T = np.exp(-12e-6 * _block_thickness_um(np.arange(600) * PIXEL_UM - 720.0))
    with pytest.raises(FwdfitError, match="tau = .* um\\^2 <= 0.*divergence"):
        paganin_filter_1d(T, PIXEL_UM, taus[-1])
    with pytest.raises(FwdfitError, match="tau"):
        paganin_filter_2d(np.tile(T, (5, 1)), PIXEL_UM, 0.0)
    assert np.all(np.isfinite(paganin_filter_1d(T, PIXEL_UM, taus[-1], regularise=True)))
    assert np.all(np.isfinite(paganin_filter_2d(np.tile(T, (5, 1)), PIXEL_UM, taus[-1],
                                                regularise=True)))


def test_spectrum_modes():
    common = dict(sld_e6_per_A2=2.078, mu_per_m=1.0, mu_per_m_per_A=0.2,
                  divergence_rad=BOA_DIVERGENCE)
    lam, w = np.array([2.0, 5.0]), np.array([1.0, 3.0])

    def mono(wavelength_A, distance_mm):
        return paganin_tau_um2(wavelength_A=wavelength_A, distance_mm=distance_mm,
                               mu_per_m=1.0 + 0.2 * wavelength_A, sld_e6_per_A2=2.078,
                               divergence_rad=BOA_DIVERGENCE)

    tau_mean = paganin_tau_um2_spectrum(wavelength_A=lam, weight=w, distance_mm=8.5, **common)
    assert tau_mean == pytest.approx(mono(4.25, 8.5), rel=1e-12)
    tau_avg = paganin_tau_um2_spectrum(wavelength_A=lam, weight=w, distance_mm=[1.1, 8.5],
                                       mode="weighted_tau", **common)
    expected = [(mono(2.0, d) + 3 * mono(5.0, d)) / 4 for d in (1.1, 8.5)]
    np.testing.assert_allclose(tau_avg, expected, rtol=1e-12)
    with pytest.raises(FwdfitError, match="mode"):
        paganin_tau_um2_spectrum(wavelength_A=lam, weight=w, distance_mm=1.1, mode="x", **common)
    with pytest.raises(FwdfitError, match="weight"):
        paganin_tau_um2_spectrum(wavelength_A=lam, weight=[0.0, 0.0], distance_mm=1.1, **common)


def test_cosine_is_scaled_by_the_physical_transfer_function():
    period_px, tau = 48, 3780.0
    j = np.arange(40 * period_px)
    T = 0.8 + 0.1 * np.cos(2 * np.pi * j / period_px)
    gain = 1 / (1 + tau * (2 * np.pi / (period_px * PIXEL_UM)) ** 2)  # 0.082
    expected = 0.8 + 0.1 * gain * np.cos(2 * np.pi * j / period_px)
    np.testing.assert_allclose(paganin_filter_1d(T, PIXEL_UM, tau, pad="periodic"), expected,
                               rtol=0, atol=1e-12)
    centre = slice(600, T.size - 600)  # 23 kernel decay lengths from the padded ends
    np.testing.assert_allclose(paganin_filter_1d(T, PIXEL_UM, tau)[centre], expected[centre],
                               rtol=0, atol=1e-8)


@pytest.mark.parametrize("bad", [
    dict(T=[1.0, np.nan, 1.0]), dict(T=[1.0, np.inf, 1.0]), dict(pixel_um=0.0),
    dict(pixel_um=-2.4), dict(tau_um2=np.nan), dict(T=[[1.0, 0.9]]), dict(pad="zero"),
])
def test_bad_input_raises(bad):
    args = dict(T=[1.0, 0.9, 0.8], pixel_um=PIXEL_UM, tau_um2=100.0) | bad
    pad = args.pop("pad", "edge")
    with pytest.raises(FwdfitError):
        paganin_filter_1d(args["T"], args["pixel_um"], args["tau_um2"], pad=pad)


def test_bad_tau_input_and_nonpositive_filtered_transmission_raise():
    with pytest.raises(FwdfitError, match="wavelength_A"):
        paganin_tau_um2(wavelength_A=0.0, mu_per_m=1.39, distance_mm=1.1, **AL)
    with pytest.raises(FwdfitError, match="distance_mm"):
        paganin_tau_um2(wavelength_A=3.8, mu_per_m=1.39, distance_mm=-1.0, **AL)
    with pytest.raises(FwdfitError, match="<= 0"):
        paganin_thickness_um([0.5, -0.01, 0.5], PIXEL_UM, 1e-6, 1.39, pad="periodic")
